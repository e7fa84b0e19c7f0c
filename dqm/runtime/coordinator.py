"""The coordinator: waits for every agent process's liveliness token, starts the
job (the seed integer and the parameters every agent checks), collects the
agents' results and statistics, and writes the report (labels + traffic per
link and per kind).

It also keeps the job alive when agent processes die (docs/runtime.md):

* liveliness tells it that process p died, in any phase;
* if p had already delivered every result and statistic it owed, nothing is
  lost and the job goes on;
* otherwise every agent p hosted goes to the next live process by index
  (p+1, p+2, ... wrapping round), the epoch goes up by one, and the job starts
  again: every process drops the old epoch's state, the new owner re-reads
  the lost agent's FEATURES files, and the features routed to its cell are
  sent again by their owners. Messages of older epochs are refused and
  counted. The labels are those of a run without the failure: the cells,
  the seeds and every round depend only on the seed integer and the data;
* more than ``max_lost`` lost processes (default: half of them, at least 1),
  or none left, ends the job with one paragraph saying what failed, which
  agent, in which phase and what to do.

Two modes are the coordinator's own (docs/runtime.md):

* ``gather``: the agents send their features (``gather`` messages,
  :mod:`dqm.runtime.gather`) and the coordinator runs :func:`dqm.quickmatch`
  with the job's kernel and rho; the report has the same fields as a
  distributed job's;
* ``auto``: once every process is ready (``start`` with mode auto), the
  coordinator times its link to each process (``probe`` messages,
  :mod:`dqm.runtime.measure`), picks gather, lean or balanced with
  :mod:`dqm.distributed.costmodel`, says which and why, and starts the job
  again (the next epoch) in the mode it picked; the report's ``auto`` block
  holds the rates, the pick, the predictions and the reason.
"""
from __future__ import annotations

import itertools
import json
import logging
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Callable, Dict, Iterator, List, Optional

import numpy as np

from .. import io, signals
from ..distributed import costmodel, keys, messages, protocol, sources
from ..distributed.config import DQMConfig
from ..distributed.driver import start_fields
from ..distributed.ledger import COORDINATOR, TrafficLedger
from ..logging_config import tag_lines
from ..validation import InputError
from ..wording import count, seconds
from . import measure
from .bus import AccessDenied, Bus, check_job_free, open_client
from .gather import GatheredParts, match_gathered

log = logging.getLogger("dqm.runtime")


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


class JobFailed(RuntimeError):
    """The job cannot finish: ``what`` failed at ``agent`` in ``phase``; ``advice`` says what to do."""

    def __init__(self, what: str, agent: Optional[int] = None, phase: str = "", advice: str = "",
                 refused: bool = False):
        super().__init__(what)
        self.what, self.agent, self.phase, self.advice, self.refused = what, agent, phase, advice, refused

    def as_dict(self) -> dict:
        return {"what": self.what, "agent": self.agent, "phase": self.phase, "advice": self.advice,
                "refused": self.refused}


def failure_paragraph(failure: dict) -> str:
    """The operator's paragraph for a failed job (what, which agent, which phase, what to do)."""
    where = []
    if failure.get("agent") is not None:
        where.append(f"agent {failure['agent']}")
    if failure.get("phase"):
        where.append(f"phase {failure['phase']}")
    text = f"The distributed job failed: {failure['what']}"
    text += f" ({', '.join(where)})." if where else "."
    if failure.get("advice"):
        text += f" {failure['advice']}"
    return text


def default_max_lost(m: int) -> int:
    """How many agent processes a job may lose by default: half of them, at least one (if m > 1)."""
    return max(1 if m > 1 else 0, m // 2)


def auto_summary(auto: dict) -> str:
    """The one line that says what ``--mode auto`` picked and why, from a report's ``auto`` block."""
    rates = ", ".join(f"{p}: {costmodel.mbit_text(r)}" for p, r in auto["rates_bytes_s"].items())
    return (f"--mode auto picked {auto['reason']} [measured Mbit/s per process {rates}; "
            f"{auto['probe_s']:.2f} s of probes]")


class _Lost(Exception):
    """A process that owed work died: the coordinator reassigns and starts a new epoch."""


class Coordinator:
    def __init__(self, bus: Bus, cfg: DQMConfig, ready_timeout_s: float = 30.0, job_timeout_s: float = 600.0,
                 max_lost: Optional[int] = None, view=None, phase_timeout_s: float = 120.0,
                 catalog: bool = False, host_cores: Optional[float] = None, gather_cores: Optional[float] = None,
                 announce: Optional[Callable[[str], None]] = None):
        self.bus = bus
        #: the mode the job was started with (``auto``: :meth:`_decide` picks the one :attr:`cfg` runs)
        self.requested = cfg
        self.cfg = cfg
        #: auto: the cores of each agent host, and those this host gives a gather, for the cost model (None:
        #: this host's, :func:`measure.host_cores`)
        self.host_cores, self.gather_cores = host_cores, gather_cores
        self.announce = announce or (lambda text: log.info("%s", text))
        #: auto: the report's ``auto`` block once the mode is picked
        self.auto: Optional[dict] = None
        self.probe_answers: Dict[int, float] = {}
        #: gather: the agents' features as they arrive
        self.gathered: Optional[GatheredParts] = None
        self.match_s = 0.0
        self._probes: Optional[measure.ProbeEncoder] = None
        self.runs = 0
        self.job = cfg.job
        self.m = cfg.agents
        self.seed = cfg.seed
        self.ready_timeout_s = ready_timeout_s
        self.job_timeout_s = job_timeout_s
        self.phase_timeout_s = phase_timeout_s
        self.max_lost = default_max_lost(self.m) if max_lost is None else max_lost
        self.results: Dict[int, dict] = {}
        self.stats: Dict[int, dict] = {}
        self.stats_bytes: Dict[int, int] = {}
        #: whether the agents send their catalogs (what a CLUSTERS file needs); the parts per agent
        self.catalog = catalog
        self.catalog_parts: Dict[int, Dict[int, dict]] = defaultdict(dict)
        #: the CLUSTERS arrays once the job is done (with ``catalog``)
        self.clusters: Optional[sources.AssembledClusters] = None
        self.view = view
        self.phase = "ready"
        self.epoch = 0
        self.owners = np.arange(self.m, dtype=np.int64)
        self.dead: set = set()
        self.lost: List[dict] = []
        self.states: Dict[int, str] = {}
        self.ready: Dict[int, dict] = {}
        self.t0 = time.monotonic()

    # ------------------------------------------------------------------ helpers
    def _send(self, p: int, kind: str, **fields) -> None:
        self.bus.send_single(-1, p, kind, **fields)

    def _hosts(self) -> List[int]:
        return sorted(set(int(o) for o in self.owners))

    def _event(self, text: str) -> None:
        if self.view is None or self.view.stream is not sys.stderr:
            log.warning("%s", text)
        if self.view is not None:
            self.view.event(text)

    def _abort_all(self, reason: str) -> None:
        for p in range(self.m):
            if p not in self.dead:
                try:
                    self._send(p, "abort", reason=reason[:1000])
                except Exception:  # noqa: BLE001 - best effort while failing
                    pass

    def fail(self, failure: JobFailed) -> None:
        self._abort_all(failure.what)
        raise failure

    def _phase_of(self, p: int) -> str:
        """The phase of process p's own agent (as last reported), for messages."""
        if p in self.states:
            state = self.states[p]
            return state[5:] if state.startswith("wait_") else state
        return "start" if self.phase == "start" else "before the start"

    def _poll(self) -> None:
        """Take the next message (if any) and record it: progress, refusal, ready, result, statistics."""
        item = self.bus.receive(timeout=0.1)
        if item is None:
            return
        _, msg = item
        kind, src = msg["kind"], msg["src"]
        if kind == "progress":
            self.states[src] = msg["state"]
            if self.view is not None:
                self.view.update(src, int(self.owners[src]), msg["state"], msg["features"], msg["bytes"])
        elif kind == "refuse":
            self.fail(JobFailed(f"agent {src} refused the job: {msg['reason']}", src, self._phase_of(src),
                                "Start every agent with the coordinator's algorithm options." if msg["param"] else
                                "Check that agent's log.", refused=True))
        elif kind == "ready" and self.phase == "start":
            self.ready[src] = msg
        elif kind == "result" and self.phase == "running":
            self.results[src] = msg
        elif kind == "catalog" and self.phase == "running":
            self.catalog_parts[src][msg["part"]] = msg
        elif kind == "stats" and self.phase == "running":
            self.stats[src] = msg["values"]
            # the stats message itself was sent after the agent's meter snapshot
            self.stats_bytes[src] = msg["_bytes"] + len(msg["_key"])
        elif kind == "gather" and self.phase == "running" and self.gathered is not None:
            self.gathered.take(msg)
        elif kind == "probe" and self.phase == "probe":
            # when the process received the probe, by its own clock (else: when its answer arrived here)
            stamp = measure.answer_stamp(msg["data"])
            self.probe_answers[msg["token"]] = msg["_t"] if stamp is None else stamp

    def _deaths(self) -> List[int]:
        return [p for p in range(self.m) if p not in self.dead and self.bus.agent_alive(p) is False]

    def _catalog_done(self, a: int) -> bool:
        got = self.catalog_parts.get(a)
        return not self.catalog or bool(got) and len(got) == next(iter(got.values()))["parts"]

    def _owes(self, p: int) -> bool:
        """Whether process p still owes a result, a catalog or statistics for an agent it hosts."""
        return any(int(self.owners[a]) == p and (a not in self.stats or not self._catalog_done(a))
                   for a in range(self.m))

    def _check_deaths(self) -> None:
        """Mark processes whose token vanished as dead; raise _Lost if one of them still owed work."""
        gone = self._deaths()
        if not gone:
            return
        t = time.monotonic()
        while time.monotonic() - t < 0.3:  # a refusal sent just before the exit comes first
            self._poll()
        owing = [p for p in gone if self.phase != "running" or self._owes(p)]
        self.dead.update(gone)
        for p in gone:
            if p not in owing:
                self._event(f"agent process {p} exited after delivering its results; nothing is lost")
        if owing:
            raise _Lost()

    def _reassign(self) -> None:
        """Give every agent hosted by a dead process to the next live process by index; each such process
        counts as lost (also one that had exited after delivering its results of an earlier epoch)."""
        orphaned = sorted({int(o) for o in self.owners} & self.dead)
        for p in orphaned:
            self.lost.append({"process": p, "phase": self._phase_of(p), "epoch": self.epoch})
        p, phase = self.lost[-1]["process"], self.lost[-1]["phase"]
        if len(self.dead) == self.m:
            self.fail(JobFailed("every agent process was lost", p, phase,
                                "Check the agents' logs and hosts, then start the job again."))
        if len(self.lost) > self.max_lost:
            self.fail(JobFailed(
                f"{len(self.lost)} agent processes were lost ({', '.join(str(x['process']) for x in self.lost)}), more "
                f"than the limit of {self.max_lost}", p, phase,
                "Check the agents' logs and hosts, then start the job again (raise --max-lost to let fewer "
                "survivors carry more agents)."))
        moved = {}
        for a in range(self.m):
            owner = int(self.owners[a])
            if owner in self.dead:
                nxt = next(q for q in [(owner + k) % self.m for k in range(1, self.m + 1)] if q not in self.dead)
                self.owners[a] = nxt
                moved[a] = nxt
        self.epoch += 1
        self._event(", ".join(f"agent process {q} was lost in phase {self._phase_of(q)}" for q in orphaned) + "; "
                    + ", ".join(f"agent {a} -> process {q}" for a, q in sorted(moved.items()))
                    + f"; restarting at epoch {self.epoch}")

    def _check_time(self) -> None:
        if time.monotonic() - self.t0 > self.job_timeout_s:
            slow = [a for a in range(self.m) if a not in self.stats]
            self.fail(JobFailed(f"the job did not finish within {seconds(self.job_timeout_s)}",
                                slow[0] if slow else None,
                                self._phase_of(slow[0]) if slow else "",
                                "Raise --timeout, or check the slow agent's log."))

    # ------------------------------------------------------------------ the job
    def _wait_tokens(self) -> None:
        log.info("waiting up to %s for the %s of job %r", seconds(self.ready_timeout_s),
                 count(self.m, "agent process", "agent processes"), self.cfg.job)
        while True:
            missing = [p for p in range(self.m) if not self.bus.agent_alive(p)]
            if not missing:
                return
            self.bus.receive(timeout=0.1)
            if time.monotonic() - self.t0 > self.ready_timeout_s:
                if len(missing) == self.m:
                    self.fail(JobFailed(f"no agent process appeared within {seconds(self.ready_timeout_s)}", None,
                                        "start", "Start the agents with the coordinator's --connect endpoint and "
                                        "--job id."))
                if len(missing) > self.max_lost:  # not lost: never seen (still starting, or elsewhere)
                    shown = ", ".join(map(str, missing[:10])) + (" ..." if len(missing) > 10 else "")
                    self.fail(JobFailed(
                        f"{len(missing)} of {self.m} agent processes ({shown}) did not appear within the ready "
                        f"timeout of {seconds(self.ready_timeout_s)}, more than the {self.max_lost} the job may do "
                        "without", missing[0], "start",
                        "They may still be starting (many processes on few cores start slowly: start fewer agents "
                        "per host, or raise --ready-timeout), or cannot reach the router (check their logs)."))
                self.dead.update(missing)  # never appeared: lost before the start
                self._reassign()
                return

    def _start(self, cfg: DQMConfig) -> List[int]:
        """Send the current epoch's ``start`` (``cfg``'s parameters) to every live process hosting agents and
        wait until every one is ready with descriptors of one dimension and type; returns those processes."""
        self.bus.set_epoch(self.epoch)
        self.bus.set_owners(self.owners)
        self.results, self.stats, self.stats_bytes, self.ready, self.states = {}, {}, {}, {}, {}
        self.catalog_parts.clear()
        self.phase = "start"
        hosts = self._hosts()
        start = start_fields(cfg, self.owners, self.catalog)
        for p in hosts:
            self._send(p, "start", **start)
        t = time.monotonic()
        while len(self.ready) < len(hosts):
            self._poll()
            self._check_deaths()
            self._check_time()
            if time.monotonic() - t > self.phase_timeout_s:
                slow = [p for p in hosts if p not in self.ready]
                self.fail(JobFailed(f"agent process {slow[0]} did not get ready within {seconds(self.phase_timeout_s)}",
                                    slow[0], "start", "Check that agent's log."))
        ref = self.ready[hosts[0]]
        for p in hosts:
            for name, field in (("dimension", "dim"), ("dtype", "dtype")):
                if self.ready[p][field] != ref[field]:
                    self.fail(JobFailed(f"agent {p} holds descriptors of {name} {self.ready[p][field]}, agent "
                                        f"{hosts[0]} of {name} {ref[field]}", p, "start",
                                        "Give every agent FEATURES of the same descriptor type.", refused=True))
        return hosts

    def _epoch(self) -> None:
        """Start the current epoch and run it to the end; raises _Lost when a process owing work dies."""
        self.runs += 1
        hosts = self._start(self.cfg)
        self.gathered = GatheredParts(range(self.m)) if self.cfg.mode == "gather" else None
        for p in hosts:
            self._send(p, "go")
        self.phase = "running"
        while (len(self.stats) < self.m or not all(self._catalog_done(a) for a in range(self.m))
               or (self.gathered is not None and not self.gathered.complete())):
            self._poll()
            self._check_deaths()
            self._check_time()

    # ------------------------------------------------------------------ --mode auto
    def _probe_pair(self, p: int, token_a: int, token_b: int, nbytes: int) -> None:
        """Send process ``p`` two probes of ``nbytes`` filler bytes back to back, both encoded first (not
        numbered: a probe is answered, not acknowledged)."""
        payloads = [self._probes.encode(t, nbytes) for t in (token_a, token_b)]  # both ready before the first put
        for payload in payloads:
            self.bus.send(COORDINATOR, p, "probe", payload)

    def _probe_answer(self, token: int, timeout_s: float) -> float:
        """When the process received probe ``token`` (its clock, from the answer's stamp), polling meanwhile."""
        t = time.monotonic()
        while token not in self.probe_answers:
            self._poll()
            self._check_deaths()
            self._check_time()
            if time.monotonic() - t > timeout_s:
                self.fail(JobFailed(f"an agent process did not answer the link probe within {seconds(timeout_s)}",
                                    None, "probe", "Check the agents' logs; every process of a --mode auto job "
                                    "must be started with --mode auto."))
        return self.probe_answers.pop(token)

    def _decide(self) -> None:
        """--mode auto: start every process in mode auto, time the link to each, pick the mode the job runs."""
        hosts = self._start(self.requested)
        self.phase = "probe"
        t0 = time.monotonic()
        epoch = self.bus.epoch
        self._probes = measure.ProbeEncoder(lambda token, data: messages.encode(
            "probe", self.job, COORDINATOR, epoch=epoch, token=token, reply=measure.STAMP_BYTES, data=data))
        tokens: Iterator[int] = itertools.cycle((1, 2))
        rates: Dict[int, measure.LinkRate] = {}
        start = measure.START_PROBE_BYTES
        for p in hosts:
            rates[p] = measure.measure_link(p, self._probe_pair, self._probe_answer, tokens, time.monotonic, start)
            start = measure.next_start_bytes(rates[p])
        probe_s = time.monotonic() - t0
        ref = self.ready[hosts[0]]
        n = int(sum(self.ready[p]["features"] for p in hosts))
        dtype = np.dtype(ref["dtype"])
        own = self.gather_cores or measure.host_cores()
        cores = self.host_cores or own
        try:
            job = costmodel.JobShape(n=max(1, n), agents=self.m, dim=int(ref["dim"]), itemsize=dtype.itemsize)
            choice = costmodel.choose(job, costmodel.Hosts.of([rates[p].bytes_s for p in hosts], cores,
                                                              gather_cores=own), started=True,
                                      modes=self.requested.auto_choices)
        except InputError as exc:
            self.fail(JobFailed(f"--mode auto cannot pick a mode: {exc}", None, "probe",
                                "Give the job's mode explicitly (--mode balanced, lean or gather)."))
        self.cfg = self.requested.but(mode=choice.mode)
        self.auto = {
            "rates_bytes_s": {str(p): round(rates[p].bytes_s, 1) for p in hosts},
            "picked": choice.mode, "predicted_s": choice.predicted_s, "reason": choice.reason,
            "probe_s": probe_s,
            "probe_pairs": {str(p): [list(x) for x in rates[p].pairs] for p in hosts},
            "cores_per_host": cores, "gather_cores": own, "features": n,
        }
        self.announce(auto_summary(self.auto))
        self.epoch += 1  # the picked mode runs in the next epoch (every process starts it afresh)

    def run(self, tcp_port: Optional[int] = None) -> dict:
        self.t0 = t0 = time.monotonic()
        self._wait_tokens()
        t_ready = time.monotonic()
        while True:
            try:
                if self.requested.mode == "auto" and self.auto is None:
                    self._decide()
                self._epoch()
                break
            except _Lost:
                self._reassign()
        if self.cfg.mode == "gather":
            ids, labels = self._match()
        else:
            ids, labels = sources.assemble_labels([(self.results[a]["ids"], self.results[a]["labels"])
                                                   for a in range(self.m)])
        t_done = time.monotonic()
        wire = tcp_bytes_received(tcp_port) if tcp_port else None
        if len(np.unique(ids)) != len(ids):
            self.fail(JobFailed("two agents reported the same feature (feature ids must be unique across the "
                                "job: give each FEATURES file its own feature_ids, or none)", None, "result"))
        if self.catalog:
            try:
                catalogs = {a: protocol.merge_parts("catalog", list(self.catalog_parts[a].values()))
                            for a in range(self.m)}
                self.clusters = sources.assemble_clusters(ids, labels, catalogs)
            except ValueError as exc:  # MessageError included: parts that do not fit together
                self.fail(JobFailed(f"the agents' catalogs do not describe their results ({exc})", None, "result"))
        for p in self._hosts():
            if p not in self.dead:
                self._send(p, "finish", clusters=int(labels.max() + 1) if len(labels) else 0)
        if self.view is not None:
            self.view.close()
        return self.report(ids, labels, t_ready - t0, t_done - t_ready, wire)

    def _match(self):
        """gather: :func:`dqm.quickmatch` of every agent's features at this host (the job's kernel and rho)."""
        t = time.monotonic()
        self.phase = "match"
        try:
            out = match_gathered(*self.gathered.features(), self.cfg.params)
        except ValueError as exc:  # InputError included: duplicate ids, mixed types, over the memory budget
            self.fail(JobFailed(f"the gathered features cannot be matched: {exc}", None, "match"))
        self.match_s = time.monotonic() - t
        return out

    def _rejected(self) -> Dict[str, float]:
        """Messages refused, per reason, summed over the agent processes and the coordinator."""
        out: Dict[str, float] = defaultdict(float)
        for st in self.stats.values():
            for k, v in st.items():
                if k.startswith("rejected:"):
                    out[k[9:]] += v
        for k, v in self.bus.meter.counters()[0].items():
            out[k] += v
        return dict(out)

    def report(self, ids, labels, t_ready, t_run, wire) -> dict:
        everything = TrafficLedger()  # what every agent said it sent, its stats message, and the coordinator's sends
        for a, st in self.stats.items():
            everything.add_stats(a, st)
        for a, b in self.stats_bytes.items():
            everything.add(a, COORDINATOR, "stats", b)
        for (src, dst, kind), (b, c) in self.bus.meter.entries().items():
            everything.add(src, dst, kind, b, c)
        ledger = TrafficLedger()  # --mode auto's link probes are not the job's traffic: they go to the auto block
        probe_bytes = 0
        for (src, dst, kind), (b, c) in everything.entries().items():
            if kind == "probe":
                probe_bytes += b
            else:
                ledger.add(src, dst, kind, b, c)
        traffic = ledger.report()
        agents = {str(a): TrafficLedger.strip_stats(st) for a, st in self.stats.items()}
        out = {
            "job": self.job, "agents": self.m, "seed": self.seed, "mode": self.cfg.mode, "features": int(len(ids)),
            "clusters": int(labels.max() + 1) if len(labels) else 0,
            "ids": ids.tolist(), "labels": labels.tolist(),
            "time_ready_s": t_ready, "time_run_s": t_run,
            "epochs": self.runs, "lost": self.lost, "owners": [int(o) for o in self.owners],
            "images_note": self.clusters.note if self.clusters is not None else "",
            **traffic, "wire_bytes_received_by_router": wire,
            "rejected": self._rejected(),
            "duplicates": int(sum(st.get("duplicates", 0) for st in self.stats.values())
                              + self.bus.meter.counters()[1]),
            "per_agent": agents,
        }
        if self.cfg.mode == "gather":
            out["match_s"] = self.match_s
        if self.auto is not None:
            out["auto"] = {**self.auto, "probe_bytes": probe_bytes}
        return out


#: exit codes of ``dqm coordinator`` (docs/runtime.md)
EXIT_OK, EXIT_FAILED, EXIT_REFUSED = 0, 3, 4  # 130 / 143: dqm.signals


def failure_path(out: str) -> Path:
    """Where the coordinator writes why a job failed, next to the report it could not write."""
    p = Path(out)
    return p.with_name(p.stem + ".failure.json")


def _write_json(path: Path, obj: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(obj))
    tmp.replace(path)


def clusters_params(cfg: DQMConfig) -> dict:
    """The ``params`` of a distributed job's CLUSTERS file: what made the clusters."""
    return {"distributed": True, "mode": cfg.mode, "agents": cfg.agents, "seed": cfg.seed, "job": cfg.job,
            "partition": cfg.partition, "rho": cfg.rho, "kernel": cfg.kernel, "parent": "any"}


def main_coordinator(cfg: DQMConfig, endpoint: str, out: Optional[str], tls: Optional[dict] = None,
                     tcp_port: Optional[int] = None, ready_timeout_s: float = 30.0, job_timeout_s: float = 600.0,
                     connect_timeout_s: float = 5.0, max_lost: Optional[int] = None,
                     progress_fd: Optional[int] = None, phase_timeout_s: float = 120.0,
                     clusters: Optional[str] = None, host_cores: Optional[float] = None,
                     gather_cores: Optional[float] = None) -> int:
    """Entry point of ``dqm coordinator``: returns the process exit code. ``out``: the report JSON;
    ``clusters``: the CLUSTERS file to write (the agents then send their catalogs); ``host_cores``,
    ``gather_cores``: --mode auto's cores per agent host and at this host (None: this host's)."""
    from .console import JobView
    from .lifeline import watch_parent

    signals.install_sigterm(force=True)
    watch_parent()
    tag_lines("coordinator")
    keys.check_job(cfg.job)
    session = open_client(endpoint, tls, deadline_s=connect_timeout_s)
    check_job_free(session, keys.alive_coordinator(cfg.job), "the coordinator", cfg.job, endpoint)
    view = JobView.for_fd(progress_fd, cfg.agents)
    bus = Bus(session, cfg.job, -1, cfg.agents)
    try:
        bus.check_access(endpoint, tls, f"the coordinator of job {cfg.job!r}")
    except AccessDenied:
        bus.close()
        raise
    coord = Coordinator(bus, cfg, ready_timeout_s, job_timeout_s, max_lost=max_lost, view=view,
                        phase_timeout_s=phase_timeout_s, catalog=clusters is not None, host_cores=host_cores,
                        gather_cores=gather_cores,
                        announce=lambda text: print(text, flush=True))
    try:
        rep = coord.run(tcp_port=tcp_port)
        if clusters:  # before the report: a report names a CLUSTERS file that exists
            io.write_clusters(clusters, coord.clusters.features, {"labels": coord.clusters.labels},
                              clusters_params(coord.cfg))
            rep["clusters_file"] = str(clusters)
            if coord.clusters.note:
                log.warning("%s", coord.clusters.note)
        if out:
            _write_json(Path(out), rep)
        print(f"{rep['features']} features -> {rep['clusters']} clusters ({rep['mode']} mode), {rep['total_bytes']} "
              "bytes metered"
                  + (f", {len(rep['lost'])} agent process(es) lost and replaced" if rep["lost"] else "")
                  + (f"; wrote {clusters}" if clusters else ""))
        time.sleep(0.2)  # let the finish messages leave before closing
        return EXIT_OK
    except JobFailed as exc:
        if view is not None:
            view.close()
        log.error("%s", failure_paragraph(exc.as_dict()))
        if out:
            _write_json(failure_path(out), exc.as_dict())
        time.sleep(0.2)
        return EXIT_REFUSED if exc.refused else EXIT_FAILED
    except KeyboardInterrupt as exc:  # Ctrl-C, and SIGTERM as signals.Terminated
        log.warning("%s, aborting the job", signals.word(exc))
        coord._abort_all(f"coordinator {signals.word(exc)}")
        return signals.exit_code(exc)
    finally:
        bus.close()
