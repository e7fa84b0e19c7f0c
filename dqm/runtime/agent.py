"""A Distributed QuickMatch agent: one OS process, message-driven.

It starts with the features of its own images, declares its inbox and its
liveliness token, waits for the coordinator's seed integer, and then runs the
protocol of dqm.protocol with the algorithm of dqm.core.distributed.AgentCore
(the same code the simulator runs). All waiting is bounded; a vanished
coordinator or an abort message ends the process with a clear error.
"""
from __future__ import annotations

import os
import signal
import sys
import time
from collections import defaultdict
from typing import Dict, List, Optional, Tuple

import numpy as np

from .. import messages, protocol
from ..core import distributed as dist
from ..core import partition
from . import keys
from .bus import Bus, open_client


class JobAborted(RuntimeError):
    pass


def _fault_hook(me: int, state: str) -> None:
    """Test hook: with DQM_FAULT_PAUSE="<agent>:<state>" the agent stops (writing the
    file named by DQM_FAULT_MARKER) when it enters that state, so a test can kill it there."""
    spec = os.environ.get("DQM_FAULT_PAUSE")
    if not spec or spec != f"{me}:{state}":
        return
    marker = os.environ.get("DQM_FAULT_MARKER")
    if marker:
        with open(marker, "w") as fh:
            fh.write(f"{os.getpid()}\n")
    time.sleep(float(os.environ.get("DQM_FAULT_SECONDS", "60")))


class Terminated(BaseException):
    """SIGTERM received: leave the loop, close the session."""


def _on_sigterm(signum, frame):  # pragma: no cover - exercised by process tests
    raise Terminated()


class AgentProcess:
    def __init__(self, me: int, cfg: dist.DQMConfig, bus: Bus, ids: np.ndarray, image_ids: np.ndarray,
                 descriptors: np.ndarray, phase_timeout_s: float = 120.0, log=None):
        self.me = me
        self.cfg = cfg
        self.m = cfg.agents
        self.bus = bus
        self.ids = np.asarray(ids, np.int64)
        self.image_ids = np.asarray(image_ids, np.int64)
        self.desc = protocol.wire_descriptors(descriptors)
        self.core = dist.AgentCore(me, cfg)
        self.state = "wait_start"
        self.phase_timeout_s = phase_timeout_s
        self.phase_started = time.monotonic()
        self.log = log or (lambda text: print(f"[agent {me}] {text}", file=sys.stderr, flush=True))
        self.seed: Optional[int] = None
        self.seeds: Optional[np.ndarray] = None
        self.samples: Dict[int, np.ndarray] = {}
        self.chunks: Dict[Tuple[int, str], List[dict]] = defaultdict(list)
        self.ends: Dict[Tuple[int, str], dict] = {}
        self.minima_rows: Dict[int, np.ndarray] = {}
        self.finished = False
        _fault_hook(me, "wait_start")
        self.times: Dict[str, float] = {}

    # ------------------------------------------------------------------ messages
    def handle(self, msg: dict) -> None:
        kind, src = msg["kind"], msg["src"]
        if kind == "start" and src == -1:
            if msg["agents"] != self.m:
                raise JobAborted(f"coordinator runs {msg['agents']} agents, this agent was started with {self.m}")
            if msg["mode"] != self.cfg.partition:
                raise JobAborted(f"coordinator uses partition {msg['mode']!r}, this agent {self.cfg.partition!r}")
            self.seed = partition.check_seed(msg["seed"])
        elif kind == "sample" and self.me == 0 and src >= 0:
            self.samples[src] = msg["descriptors"]
        elif kind == "seeds" and src == 0:
            self.seeds = np.array(msg["seeds"], dtype=np.float64)
        elif kind == "features" and src >= 0:
            self.chunks[(src, msg["phase"])].append(msg)
        elif kind == "phase_end" and src >= 0 and msg["dst"] == self.me:
            self.ends[(src, msg["phase"])] = msg
        elif kind == "minima" and src >= 0:
            self.minima_rows[src] = np.array(msg["values"], dtype=np.float64)
        elif kind == "abort" and src == -1:
            raise JobAborted(f"coordinator aborted the job: {msg['reason']}")
        elif kind == "finish" and src == -1:
            self.finished = True

    def _complete(self, src: int, phase: str) -> bool:
        end = self.ends.get((src, phase))
        return end is not None and len(self.chunks[(src, phase)]) == end["messages"]

    def _shard_from(self, src: int, phase: str) -> Tuple[dist.Shard, np.ndarray]:
        ch = sorted(self.chunks[(src, phase)], key=lambda c: c["seq"])
        dim = self.desc.shape[1]
        if not ch:
            return dist.Shard.empty(dim, self.desc.dtype), np.zeros(0, np.int64)
        ids = np.concatenate([c["ids"] for c in ch])
        desc = np.concatenate([c["descriptors"] for c in ch])
        if desc.dtype != self.desc.dtype:
            raise JobAborted(f"agent {src} sent {desc.dtype} descriptors, this agent holds {self.desc.dtype}")
        shard = dist.Shard(ids, np.concatenate([c["image_ids"] for c in ch]), desc,
                           np.concatenate([c["sigma"] for c in ch]),
                           partition.route(desc.astype(np.float64), self.seeds))
        return shard, np.concatenate([c["unit"] for c in ch])

    def _send_features(self, dst: int, phase: str, shard: dist.Shard, units: np.ndarray) -> int:
        seq0 = self.bus.next_seq(dst, protocol.chunk_count(len(shard)))
        msgs = protocol.feature_messages(self.cfg.job, self.me, phase, shard.ids, shard.image_ids,
                                         shard.descriptors, shard.sigma, units, seq0=seq0)
        for k, payload in enumerate(msgs):
            self.bus.send(dst, "features", payload, seq=seq0 + k)
        return len(msgs)

    def _enter(self, state: str) -> None:
        now = time.monotonic()
        self.times[f"time_{self.state}"] = now - self.phase_started
        self.state = state
        self.phase_started = now
        _fault_hook(self.me, state)

    # ------------------------------------------------------------------ protocol steps
    def advance(self) -> None:
        s = self.state
        if s == "wait_start" and self.seed is not None:
            if self.cfg.partition == "seeded":
                self.seeds = partition.seeded_seeds(self.seed, self.m, self.desc.shape[1], norm=self.cfg.seed_norm)
                self._enter("route")
            else:
                pick = partition.sample_for_seeds(self.desc, self.ids, self.seed, self.cfg.samples_per_agent)
                if self.me == 0:
                    self.samples[0] = self.desc[pick]
                    self._enter("collect_samples")
                else:
                    self.bus.send(0, "sample", messages.encode("sample", self.cfg.job, self.me,
                                                               descriptors=np.ascontiguousarray(self.desc[pick])))
                    self._enter("wait_seeds")
        elif s == "collect_samples" and len(self.samples) == self.m:
            pooled = np.concatenate([self.samples[a] for a in range(self.m)]).astype(np.float64)
            self.seeds = partition.kmeans_seeds(pooled, self.m, self.seed)
            payload = messages.encode("seeds", self.cfg.job, 0, seeds=self.seeds)
            for b in range(1, self.m):
                self.bus.send(b, "seeds", payload)
            self._enter("route")
        elif s == "wait_seeds" and self.seeds is not None:
            self._enter("route")
        elif s == "route":
            parts = self.core.route(self.ids, self.image_ids, self.desc, self.seeds)
            self.own_part = parts[self.me]
            for b in range(self.m):
                if b != self.me:
                    k = self._send_features(b, "route", parts[b], np.full(len(parts[b]), -1))
                    self.bus.send(b, "phase_end", protocol.phase_end(self.cfg.job, self.me, b, "route", k,
                                                                     len(parts[b])))
            self._enter("wait_routed")
        elif s == "wait_routed" and all(self._complete(b, "route") for b in range(self.m) if b != self.me):
            parts = [self.own_part] + [self._shard_from(b, "route")[0] for b in range(self.m) if b != self.me]
            self.core.set_shard(parts, self.seeds)
            row = self.core.local_step()
            self.minima_rows[self.me] = row
            payload = messages.encode("minima", self.cfg.job, self.me, values=row)
            for b in range(self.m):
                if b != self.me:
                    self.bus.send(b, "minima", payload)
            self._enter("wait_minima")
        elif s == "wait_minima" and len(self.minima_rows) == self.m:
            self.core.set_minima(np.stack([self.minima_rows[a] for a in range(self.m)]))
            self._enter("wait_handdown")
        elif s == "wait_handdown" and all(self._complete(b, "handdown") for b in range(self.me + 1, self.m)):
            received, moves = [], {}
            for b in range(self.m - 1, self.me, -1):
                shard, units = self._shard_from(b, "handdown")
                if len(shard):
                    received.append((b, shard, units))
                moves[b] = protocol.unpack_moved(self.ends[(b, "handdown")]["moved"]).reshape(-1)
            out = self.core.cascade(received, moves)
            for b in range(self.me):
                sh, units = out.sends.get(b, (None, None))
                k = self._send_features(b, "handdown", sh, units) if sh is not None else 0
                self.bus.send(b, "phase_end", protocol.phase_end(
                    self.cfg.job, self.me, b, "handdown", k, len(sh) if sh is not None else 0, out.moved))
            labels = out.final_result.labels if out.final_result is not None else np.zeros(0, np.int64)
            self.bus.send(-1, "result", messages.encode("result", self.cfg.job, self.me, ids=out.final.ids,
                                                        labels=labels.astype(np.int64)))
            self._enter("wait_acks")
            self.stats = {
                "features_routed": float(len(self.core.shard)), "features_final": float(len(out.final)),
                "time_cluster": self.core.time_cluster, "time_boundary": self.core.time_boundary,
                "arrival_check_failures": float(out.arrival_failures),
                "handed_down": float(sum(len(v[0]) for v in out.sends.values())),
            }
        elif s == "wait_acks" and self.bus.unacknowledged() == 0:
            stats = dict(self.stats)
            stats.update(self.times)
            for reason, count in self.bus.meter.rejected.items():
                stats[f"rejected:{reason}"] = float(count)
            stats["duplicates"] = float(self.bus.meter.duplicates)
            stats["resent"] = float(self.bus.meter.resent)
            for (src, dst, kind), (b, c) in self.bus.meter.sent.items():
                stats[f"sent:{dst}:{kind}:bytes"] = float(b)
                stats[f"sent:{dst}:{kind}:messages"] = float(c)
            self.bus.send(-1, "stats", messages.encode("stats", self.cfg.job, self.me, values=stats))
            self._enter("wait_finish")
        elif s == "wait_finish" and self.finished:
            self._enter("done")

    def run(self, overall_timeout_s: float = 600.0) -> None:
        t0 = time.monotonic()
        while self.state != "done":
            msg = self.bus.receive(timeout=0.05)
            if msg is not None:
                self.handle(msg)
            before = None
            while before != self.state:  # advance as far as possible
                before = self.state
                self.advance()
            self.bus.resend_due()
            if self.state not in ("wait_start",) and self.bus.coordinator_alive() is False:
                raise JobAborted("the coordinator vanished (liveliness token lost)")
            if time.monotonic() - self.phase_started > self.phase_timeout_s:
                raise TimeoutError(f"agent {self.me} waited more than {self.phase_timeout_s:.0f} s in state "
                                   f"{self.state!r}")
            if time.monotonic() - t0 > overall_timeout_s:
                raise TimeoutError(f"agent {self.me} exceeded the overall timeout of {overall_timeout_s:.0f} s")


def load_agent_features(paths, me: int):
    """Own features from FEATURES files; global ids from ``feature_ids`` or (agent << 32) + row."""
    from ..io import load_features

    ids, imgs, descs = [], [], []
    offset = 0
    for p in paths:
        fs = load_features(p)
        with np.load(p, allow_pickle=False) as z:
            fid = z["feature_ids"] if "feature_ids" in z.files else None
        if fid is None:
            fid = (np.int64(me) << np.int64(32)) + offset + np.arange(len(fs), dtype=np.int64)
        offset += len(fs)
        ids.append(np.asarray(fid, np.int64))
        imgs.append(np.asarray(fs.image_ids, np.int64))
        descs.append(protocol.wire_descriptors(fs.descriptors))
    if not descs:
        raise ValueError("no features files given")
    return np.concatenate(ids), np.concatenate(imgs), np.concatenate(descs)


def main_agent(me: int, cfg: dist.DQMConfig, endpoint: str, paths, tls: Optional[dict] = None,
               connect_timeout_s: float = 5.0, phase_timeout_s: float = 120.0,
               max_message_bytes: int = messages.MAX_MESSAGE_BYTES) -> int:
    """Entry point of ``dqm agent``: returns the process exit code."""
    signal.signal(signal.SIGTERM, _on_sigterm)
    keys.check_job(cfg.job)
    ids, imgs, desc = load_agent_features(paths, me)
    session = open_client(endpoint, tls, deadline_s=connect_timeout_s)
    bus = Bus(session, cfg.job, me, cfg.agents, dim=desc.shape[1], max_bytes=max_message_bytes)
    agent = AgentProcess(me, cfg, bus, ids, imgs, desc, phase_timeout_s=phase_timeout_s)
    try:
        agent.run()
        return 0
    except (JobAborted, TimeoutError) as exc:
        agent.log(f"error: {exc}")
        return 3
    except (KeyboardInterrupt, Terminated):
        agent.log("interrupted, leaving")
        return 130
    finally:
        bus.close()
