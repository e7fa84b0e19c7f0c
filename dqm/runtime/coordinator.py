"""The coordinator: waits for every agent's liveliness token, broadcasts the
partition seed integer, collects the agents' results and statistics, watches
liveliness (a lost agent aborts the job with a clear message within seconds),
and writes the report (labels + traffic per link and per kind).
"""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Dict, Optional

import numpy as np

from ..distributed import messages
from ..core.tree import canonical_labels
from ..distributed import keys
from .agent import Terminated, _on_sigterm
from .bus import Bus, open_client


class JobFailed(RuntimeError):
    pass


def tcp_bytes_received(port: int) -> Optional[int]:
    """Sum of ``bytes_received`` over established TCP sockets whose local port is ``port``
    (the router's side of every client link), from ``ss -tin``; None if ss is unavailable."""
    try:
        out = subprocess.run(["ss", "-tinH", "state", "established", f"( sport = :{port} )"],
                             capture_output=True, text=True, timeout=5).stdout
    except (OSError, subprocess.TimeoutExpired):
        return None
    total = 0
    for tok in out.split():
        if tok.startswith("bytes_received:"):
            total += int(tok.split(":")[1])
    return total


class Coordinator:
    def __init__(self, bus: Bus, job: str, m: int, seed: int, partition: str,
                 ready_timeout_s: float = 30.0, job_timeout_s: float = 600.0, log=None):
        self.bus = bus
        self.job = job
        self.m = m
        self.seed = seed
        self.partition = partition
        self.ready_timeout_s = ready_timeout_s
        self.job_timeout_s = job_timeout_s
        self.results: Dict[int, dict] = {}
        self.stats: Dict[int, dict] = {}
        self.stats_bytes: Dict[int, int] = {}
        self.log = log or (lambda text: print(f"[coordinator] {text}", file=sys.stderr, flush=True))
        self.phase = "ready"

    def _abort(self, reason: str) -> None:
        payload = messages.encode("abort", self.job, -1, reason=reason)
        for a in range(self.m):
            try:
                self.bus.send(a, "abort", payload)
            except Exception:  # noqa: BLE001 - best effort while failing
                pass
        raise JobFailed(reason)

    def run(self, tcp_port: Optional[int] = None) -> dict:
        t0 = time.monotonic()
        # readiness: every agent's token before anything is sent
        while not all(self.bus.agent_alive(a) for a in range(self.m)):
            self.bus.receive(timeout=0.1)
            gone = [a for a in range(self.m) if self.bus.agent_alive(a) is False]
            if gone:
                self._abort(f"agent {gone[0]} died (its liveliness token vanished) before the job started; "
                            "job aborted")
            if time.monotonic() - t0 > self.ready_timeout_s:
                missing = [a for a in range(self.m) if not self.bus.agent_alive(a)]
                self._abort(f"agents {missing} not ready after {self.ready_timeout_s:.0f} s")
        t_ready = time.monotonic()
        start = messages.encode("start", self.job, -1, seed=self.seed, agents=self.m, mode=self.partition)
        for a in range(self.m):
            self.bus.send(a, "start", start)
        self.phase = "running"
        while len(self.stats) < self.m:
            msg = self.bus.receive(timeout=0.1)
            if msg is not None:
                if msg["kind"] == "result" and msg["src"] >= 0:
                    self.results[msg["src"]] = msg
                elif msg["kind"] == "stats" and msg["src"] >= 0:
                    self.stats[msg["src"]] = msg["values"]
                    # the stats message itself was sent after the agent's meter snapshot
                    self.stats_bytes[msg["src"]] = msg["_bytes"] + len(keys.coordinator_inbox(self.job))
            for a in range(self.m):
                if a not in self.stats and self.bus.agent_alive(a) is False:
                    where = "after sending its result" if a in self.results else "before sending its result"
                    self._abort(f"agent {a} died (its liveliness token vanished) {where}; job aborted")
            if time.monotonic() - t0 > self.job_timeout_s:
                self._abort(f"job did not finish within {self.job_timeout_s:.0f} s "
                            f"(results from {sorted(self.results)})")
        t_done = time.monotonic()
        wire = tcp_bytes_received(tcp_port) if tcp_port else None
        ids = np.concatenate([self.results[a]["ids"] for a in range(self.m)])
        lab, offset = [], 0
        for a in range(self.m):
            la = self.results[a]["labels"]
            lab.append(la + offset)
            offset += int(la.max()) + 1 if len(la) else 0
        labels = np.concatenate(lab)
        order = np.argsort(ids, kind="stable")
        ids, labels = ids[order], canonical_labels(labels[order])
        if len(np.unique(ids)) != len(ids):
            self._abort("two agents reported the same feature")
        finish = messages.encode("finish", self.job, -1, clusters=int(labels.max() + 1) if len(labels) else 0)
        for a in range(self.m):
            self.bus.send(a, "finish", finish)
        return self.report(ids, labels, t_ready - t0, t_done - t_ready, wire)

    def report(self, ids, labels, t_ready, t_run, wire) -> dict:
        links = defaultdict(lambda: [0, 0])
        kinds = defaultdict(lambda: [0, 0])
        for a, st in self.stats.items():
            for k, v in st.items():
                if k.startswith("sent:"):
                    _, dst, kind, what = k.split(":")
                    i = 0 if what == "bytes" else 1
                    links[(a, int(dst))][i] += int(v)
                    kinds[kind][i] += int(v)
        for a, b in self.stats_bytes.items():
            links[(a, -1)][0] += b
            links[(a, -1)][1] += 1
            kinds["stats"][0] += b
            kinds["stats"][1] += 1
        for (src, dst, kind), (b, c) in self.bus.meter.snapshot()[0].items():
            links[(src, dst)][0] += b
            links[(src, dst)][1] += c
            kinds[kind][0] += b
            kinds[kind][1] += c
        name = lambda i: "coordinator" if i < 0 else f"agent{i}"  # noqa: E731
        total = sum(b for b, _ in links.values())
        agents = {str(a): {k: v for k, v in st.items() if not k.startswith("sent:")} for a, st in self.stats.items()}
        return {
            "job": self.job, "agents": self.m, "seed": self.seed, "features": int(len(ids)),
            "clusters": int(labels.max() + 1) if len(labels) else 0,
            "ids": ids.tolist(), "labels": labels.tolist(),
            "time_ready_s": t_ready, "time_run_s": t_run,
            "links": [{"src": name(s), "dst": name(d), "bytes": b, "messages": c}
                      for (s, d), (b, c) in sorted(links.items())],
            "kinds": {k: {"bytes": b, "messages": c} for k, (b, c) in sorted(kinds.items())},
            "total_bytes": total, "wire_bytes_received_by_router": wire,
            "rejected": {k: v for st in self.stats.values() for k, v in st.items() if k.startswith("rejected:")},
            "per_agent": agents,
        }


def main_coordinator(m: int, seed: int, partition: str, endpoint: str, job: str, out: Optional[str],
                     tls: Optional[dict] = None, tcp_port: Optional[int] = None,
                     ready_timeout_s: float = 30.0, job_timeout_s: float = 600.0,
                     connect_timeout_s: float = 5.0) -> int:
    signal.signal(signal.SIGTERM, _on_sigterm)
    keys.check_job(job)
    session = open_client(endpoint, tls, deadline_s=connect_timeout_s)
    bus = Bus(session, job, -1, m)
    coord = Coordinator(bus, job, m, seed, partition, ready_timeout_s, job_timeout_s)
    try:
        rep = coord.run(tcp_port=tcp_port)
        if out:
            p = Path(out)
            p.parent.mkdir(parents=True, exist_ok=True)
            tmp = p.with_suffix(p.suffix + ".tmp")
            tmp.write_text(json.dumps(rep))
            tmp.replace(p)
        coord.log(f"{rep['features']} features -> {rep['clusters']} clusters, {rep['total_bytes']} bytes metered")
        time.sleep(0.2)  # let the finish messages leave before closing
        return 0
    except JobFailed as exc:
        coord.log(f"error: {exc}")
        time.sleep(0.2)
        return 3
    except (KeyboardInterrupt, Terminated):
        coord.log("interrupted, aborting the job")
        try:
            coord._abort("coordinator interrupted")
        except JobFailed:
            pass
        return 130
    finally:
        bus.close()
