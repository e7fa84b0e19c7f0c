"""The coordinator process: the zenoh shell around the one coordinator core.

Every decision (epochs, takeovers after a lost process, ``max_lost``, the ``--mode auto`` pick,
when the job is done, the labels and the CLUSTERS arrays) is made by
:class:`dqm.distributed.coordination.CoordinatorCore`, the same core the simulator runs. This
module holds its I/O: it waits for every agent process's liveliness token, feeds the core the bus's
messages and the tokens that vanish, sends what the core decided, keeps the time limits (ready,
phase, job), times the links for ``--mode auto`` (``probe`` messages, :mod:`dqm.runtime.measure`)
and writes the report (labels + traffic per link and per kind) or, when the job fails, the
failure's paragraph (docs/runtime.md).
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

from .. import io, outputs, signals
from ..distributed import keys, messages, sources
from ..distributed.config import DQMConfig
from ..distributed.coordination import (  # noqa: F401 - JobFailed and the helpers are this module's API too
    CoordinatorCore,
    JobFailed,
    auto_summary,
    default_max_lost,
    failure_paragraph,
)
from ..distributed.gathering import GATHERER
from ..distributed.ledger import COORDINATOR, TrafficLedger
from ..logging_config import tag_lines
from ..wording import count, seconds
from . import measure
from .bus import AccessDenied, Bus, check_job_free, open_client
from .limits import DEFAULT_READY_TIMEOUT_S, RuntimeLimits

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


class _Restart(Exception):
    """The epoch changed while the links were being timed (a process was lost): measure again."""


class Coordinator:
    """The zenoh shell around :class:`~dqm.distributed.coordination.CoordinatorCore`: it feeds the core
    from the bus (messages, vanished liveliness tokens), sends what the core puts in its outbox, keeps
    the time limits, times the links for ``--mode auto`` and writes the report."""

    def __init__(self, bus: Bus, cfg: DQMConfig, ready_timeout_s: float = 30.0, job_timeout_s: float = 600.0,
                 max_lost: Optional[int] = None, view=None, phase_timeout_s: float = 120.0,
                 catalog: bool = False, host_cores: Optional[float] = None, gather_cores: Optional[float] = None,
                 announce: Optional[Callable[[str], None]] = None, recovery: str = "takeover"):
        self.bus = bus
        self.core = CoordinatorCore(cfg, max_lost=max_lost, catalog=catalog, recovery=recovery)
        #: auto: the cores of each agent host, and those this host gives a gather, for the cost model (None:
        #: this host's, :func:`measure.host_cores`)
        self.host_cores, self.gather_cores = host_cores, gather_cores
        self.announce = announce or (lambda text: log.info("%s", text))
        self.probe_answers: Dict[int, float] = {}
        self._probes: Optional[measure.ProbeEncoder] = None
        self.job = cfg.job
        self.m = cfg.agents
        self.seed = cfg.seed
        self.ready_timeout_s = ready_timeout_s
        self.job_timeout_s = job_timeout_s
        self.phase_timeout_s = phase_timeout_s
        self.view = view
        self.t0 = time.monotonic()
        self._since = (self.core.phase, self.core.epoch, self.t0)  # when the core entered its phase

    @property
    def cfg(self) -> DQMConfig:
        """The configuration the job runs (with ``--mode auto``: the picked mode once picked)."""
        return self.core.cfg

    @property
    def clusters(self) -> Optional[sources.AssembledClusters]:
        return self.core.clusters

    # ------------------------------------------------------------------ the core's I/O
    def _flush(self) -> None:
        """Send what the core decided (entering its epoch first), show its events."""
        core = self.core
        core.address(self.bus)
        for p, kind, fields in core.take_outbox():
            try:
                self.bus.send_single(COORDINATOR, p, kind, **fields)
            except Exception:
                if kind != "abort":
                    raise
        for text in core.take_events():
            self._event(text)
        if self._since[:2] != (core.phase, core.epoch):
            self._since = (core.phase, core.epoch, time.monotonic())

    def _drive(self, fn, *args):
        """Call a decision of the core, then send what it decided (also when it failed the job)."""
        try:
            return fn(*args)
        finally:
            self._flush()

    def _event(self, text: str) -> None:
        if self.view is None or self.view.stream is not sys.stderr:
            log.warning("%s", text)
        if self.view is not None:
            self.view.event(text)

    def fail(self, failure: JobFailed) -> None:
        self._drive(self.core.fail, failure)

    def _abort_all(self, reason: str) -> None:
        try:
            self.fail(JobFailed(reason))
        except JobFailed:
            pass

    def _poll(self) -> None:
        """Take the next message (if any) to the core; show progress; record probe answers."""
        item = self.bus.receive(timeout=0.1)
        if item is None:
            return
        _, msg = item
        if msg["kind"] == "progress" and self.view is not None:
            src = msg["src"]
            self.view.update(src, int(self.core.owners[src]), msg["state"], msg["features"], msg["bytes"])
        if msg["kind"] == "probe" and self.core.phase == "probe":
            # when the process received the probe, by its own clock (else: when its answer arrived here)
            stamp = measure.answer_stamp(msg["data"])
            self.probe_answers[msg["token"]] = msg["_t"] if stamp is None else stamp
            return
        self._drive(self.core.handle, msg)

    def _check_deaths(self) -> None:
        """Processes whose token vanished go to the core (after the messages they sent just before)."""
        gone = [p for p in range(self.m) if p not in self.core.dead and self.bus.agent_alive(p) is False]
        if not gone:
            return
        t = time.monotonic()
        while time.monotonic() - t < 0.3:  # a refusal sent just before the exit comes first
            self._poll()
        self._drive(self.core.processes_lost, gone)

    def _check_time(self) -> None:
        core = self.core
        now = time.monotonic()
        if now - self.t0 > self.job_timeout_s:
            slow = [a for a in range(self.m) if a not in core.stats]
            self._log_state(slow)
            self.fail(JobFailed(f"the job did not finish within {seconds(self.job_timeout_s)}",
                                slow[0] if slow else None,
                                core.phase_of(slow[0]) if slow else "",
                                "Raise --timeout, or check the slow agent's log."))
        if core.phase in ("start", "takeover") and now - self._since[2] > self.phase_timeout_s:
            slow = core.unready()
            self.fail(JobFailed(f"agent process {slow[0]} did not get ready within {seconds(self.phase_timeout_s)}",
                                slow[0], core.phase, "Check that agent's log."))

    def _log_state(self, slow: List[int]) -> None:
        """What the coordinator holds when the job runs out of time: whose results and statistics are missing,
        the agents' last states and the messages it refused (so that a lost message can be told from a slow agent)."""
        rejected, duplicates, _ = self.bus.meter.counters()
        missing = [a for a in range(self.m) if a not in self.core.results]
        log.warning("at the job timeout: results missing from agents %s, statistics from %s; last states %s; "
                    "messages refused here %s, duplicates %d", missing, slow,
                    {a: self.core.states.get(a, "?") for a in slow}, rejected or "none", duplicates)

    def _step(self) -> None:
        self._poll()
        self._check_deaths()
        self._check_time()

    # ------------------------------------------------------------------ the job
    def _wait_tokens(self) -> List[int]:
        """Wait for every process's liveliness token; returns those still missing at the ready timeout (at
        most ``max_lost``: lost before the start)."""
        log.info("waiting up to %s for the %s of job %r", seconds(self.ready_timeout_s),
                 count(self.m, "agent process", "agent processes"), self.cfg.job)
        while True:
            missing = [p for p in range(self.m) if not self.bus.agent_alive(p)]
            if not missing:
                return []
            self.bus.receive(timeout=0.1)
            if time.monotonic() - self.t0 > self.ready_timeout_s:
                if len(missing) == self.m:
                    self.fail(JobFailed(f"no agent process appeared within {seconds(self.ready_timeout_s)}", None,
                                        "start", "Start the agents with the coordinator's --connect endpoint and "
                                        "--job id."))
                if len(missing) > self.core.max_lost:  # not lost: never seen (still starting, or elsewhere)
                    shown = ", ".join(map(str, missing[:10])) + (" ..." if len(missing) > 10 else "")
                    self.fail(JobFailed(
                        f"{len(missing)} of {self.m} agent processes ({shown}) did not appear within the ready "
                        f"timeout of {seconds(self.ready_timeout_s)}, more than the {self.core.max_lost} the job may "
                        "do without", missing[0], "start",
                        "They may still be starting (many processes on few cores start slowly: start fewer agents "
                        "per host, or raise --ready-timeout), or cannot reach the router (check their logs)."))
                return missing

    def wait_agents_left(self, timeout_s: float) -> bool:
        """After ``finish``: wait until no agent process's token is left (a process leaves once it has its
        ``finish``), at most ``timeout_s``, so that closing the coordinator's session cuts no one off;
        returns whether they all left."""
        end = time.monotonic() + timeout_s
        while any(self.bus.agent_alive(p) for p in range(self.m)):
            if time.monotonic() > end:
                return False
            time.sleep(0.005)
        return True

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
        epoch = self.core.epoch
        while token not in self.probe_answers:
            self._step()
            if self.core.epoch != epoch:
                raise _Restart()
            if time.monotonic() - t > timeout_s:
                self.fail(JobFailed(f"an agent process did not answer the link probe within {seconds(timeout_s)}",
                                    None, "probe", "Check the agents' logs; every process of a --mode auto job "
                                    "must be started with --mode auto."))
        return self.probe_answers.pop(token)

    def _kernel_cpu_s(self) -> Optional[float]:
        """This host's all-pairs kernel for the job's descriptors (CPU-seconds per pair-dimension,
        :func:`dqm.core.pairs.pair_cpu_s_here`: a few milliseconds while the agents wait for ``go``); None, with
        a warning, when it cannot be timed (the cost model then assumes the fit machine's speed)."""
        from ..core.pairs import pair_cpu_s_here

        shape = self.core.job_shape()
        try:
            return pair_cpu_s_here(shape.dim, "uint8" if shape.itemsize == 1 else "float32")
        except Exception as exc:  # noqa: BLE001 - a timing, not the job: --mode auto goes on without it
            log.warning("--mode auto could not time this host's pair kernel (%s: %s); the cost model assumes "
                        "the speed of the machine it was fitted on", type(exc).__name__, exc)
            return None

    def _measure(self) -> None:
        """--mode auto: let the core pick the mode from the job's size where the links cannot change the
        answer; else time the link to each hosting process, then let the core pick."""
        t0 = time.monotonic()
        own = self.gather_cores or measure.host_cores()
        kernel = self._kernel_cpu_s()
        if self._drive(self.core.decide_unmeasured, self.host_cores or own, own, kernel):
            self.announce(auto_summary(self.core.auto))
            return
        epoch = self.bus.epoch
        self.probe_answers.clear()
        self._probes = measure.ProbeEncoder(lambda token, data: messages.encode(
            "probe", self.job, COORDINATOR, epoch=epoch, token=token, reply=measure.STAMP_BYTES, data=data))
        tokens: Iterator[int] = itertools.cycle((1, 2))
        rates: Dict[int, measure.LinkRate] = {}
        start = measure.START_PROBE_BYTES
        hosts = self.core.hosts()
        enough = self.core.enough_rate  # where the pick is settled above some rate, a lower bound does
        for p in hosts:
            rates[p] = measure.measure_link(p, self._probe_pair, self._probe_answer, tokens, time.monotonic, start,
                                            enough)
            start = measure.next_start_bytes(rates[p])
        self._drive(self.core.decide, {p: rates[p].bytes_s for p in hosts}, self.host_cores or own, own,
                    time.monotonic() - t0, {p: rates[p].pairs for p in hosts}, kernel,
                    [p for p in hosts if rates[p].at_least])
        self.announce(auto_summary(self.core.auto))

    def run(self, tcp_port: Optional[int] = None) -> dict:
        self.t0 = t0 = time.monotonic()
        missing = self._wait_tokens()
        t_ready = time.monotonic()
        self._drive(self.core.begin, missing)
        while not self.core.done:
            if self.core.phase == "probe":
                try:
                    self._measure()
                except _Restart:
                    pass
                continue
            self._step()
        # the router's sockets counted before ``finish``: the agents leave (and their sockets close) once they have it
        wire = tcp_bytes_received(tcp_port) if tcp_port else None
        ids, labels = self._drive(self.core.result)
        t_done = time.monotonic()
        if self.view is not None:
            self.view.close()
        return self.report(ids, labels, t_ready - t0, t_done - t_ready, wire)

    def _rejected(self) -> Dict[str, float]:
        """Messages refused, per reason, summed over the agent processes and the coordinator."""
        out: Dict[str, float] = defaultdict(float)
        for st in self.core.stats.values():
            for k, v in st.items():
                if k.startswith("rejected:"):
                    out[k[9:]] += v
        for k, v in self.bus.meter.counters()[0].items():
            out[k] += v
        return dict(out)

    def report(self, ids, labels, t_ready, t_run, wire) -> dict:
        core = self.core
        everything = TrafficLedger()  # what every agent said it sent, its stats message, and the coordinator's sends
        for a, st in core.stats.items():
            everything.add_stats(a, st)
        for a, b in core.stats_bytes.items():
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
        agents = {str(a): TrafficLedger.strip_stats(st) for a, st in core.stats.items()}
        out = {
            "job": self.job, "agents": self.m, "seed": self.seed, "mode": self.cfg.mode, "engine": self.cfg.engine,
            "features": int(len(ids)),
            "clusters": int(labels.max() + 1) if len(labels) else 0,
            "ids": ids.tolist(), "labels": labels.tolist(),
            "time_ready_s": t_ready, "time_run_s": t_run,
            "epochs": core.runs, "lost": core.lost, "owners": [int(o) for o in core.owners],
            "images_note": core.clusters.note if core.clusters is not None else "",
            **traffic, "wire_bytes_received_by_router": wire,
            "rejected": self._rejected(),
            "duplicates": int(sum(st.get("duplicates", 0) for st in core.stats.values())
                              + self.bus.meter.counters()[1]),
            "per_agent": agents,
        }
        if self.cfg.mode == "gather":  # the gathering agent's match
            out["match_s"] = float(core.stats.get(GATHERER, {}).get("match_s", 0.0))
        if core.auto is not None:
            out["auto"] = {**core.auto, "probe_bytes": probe_bytes}
        return out


#: how long the coordinator waits, once the job is done, for the agent processes to leave before it closes
FINISH_WAIT_S = 2.0
#: exit codes of ``dqm coordinator`` (docs/runtime.md)
EXIT_OK, EXIT_FAILED, EXIT_REFUSED = 0, 3, 4  # 130 / 143: dqm.signals
#: the job ran, but --clusters was taken meanwhile by another run or program (the result kept under the next free
#: name): the exit code of bad input
EXIT_OUTPUT_TAKEN = 2


def failure_path(out: str) -> Path:
    """Where the coordinator writes why a job failed, next to the report it could not write."""
    p = Path(out)
    return p.with_name(p.stem + ".failure.json")


def _write_json(path: Path, obj: dict) -> None:
    outputs.write_text(path, json.dumps(obj))


def clusters_params(cfg: DQMConfig) -> dict:
    """The ``params`` of a distributed job's CLUSTERS file: what made the clusters."""
    return {"distributed": True, "mode": cfg.mode, "engine": cfg.engine, "agents": cfg.agents, "seed": cfg.seed,
            "job": cfg.job, "partition": cfg.partition, "rho": cfg.rho, "kernel": cfg.kernel, "parent": "any"}


def main_coordinator(cfg: DQMConfig, endpoint: str, out: Optional[str], tls: Optional[dict] = None,
                     tcp_port: Optional[int] = None, limits: Optional[RuntimeLimits] = None,
                     progress_fd: Optional[int] = None, clusters: Optional[str] = None,
                     host_cores: Optional[float] = None, gather_cores: Optional[float] = None) -> int:
    """Entry point of ``dqm coordinator``: returns the process exit code. ``out``: the report JSON;
    ``limits``: timeouts, lease, ``max_lost``, recovery (None: the defaults); ``clusters``: the CLUSTERS file
    to write (the agents then send their catalogs); ``host_cores``, ``gather_cores``: --mode auto's cores per
    agent host and at this host (None: this host's)."""
    from .console import JobView
    from .lifeline import watch_parent

    signals.install_sigterm(force=True)
    watch_parent()
    tag_lines("coordinator")
    keys.check_job(cfg.job)
    limits = limits or RuntimeLimits()
    session = open_client(endpoint, tls, deadline_s=limits.connect_timeout_s, lease_ms=limits.lease_ms)
    check_job_free(session, keys.alive_coordinator(cfg.job), "the coordinator", cfg.job, endpoint)
    view = JobView.for_fd(progress_fd, cfg.agents)
    bus = Bus(session, cfg.job, -1, cfg.agents, max_bytes=limits.max_message_bytes)
    try:
        bus.check_access(endpoint, tls, f"the coordinator of job {cfg.job!r}")
    except AccessDenied:
        bus.close()
        raise
    coord = Coordinator(bus, cfg, limits.ready_timeout_s or DEFAULT_READY_TIMEOUT_S, limits.job_timeout_s,
                        max_lost=limits.max_lost, view=view, phase_timeout_s=limits.phase_timeout_s,
                        catalog=clusters is not None, host_cores=host_cores, gather_cores=gather_cores,
                        announce=lambda text: print(text, flush=True), recovery=limits.recovery)
    try:
        rep = coord.run(tcp_port=tcp_port)
        taken = None
        if clusters:  # before the report: a report names a CLUSTERS file that exists
            try:
                io.write_clusters(clusters, coord.clusters.features, {"labels": coord.clusters.labels},
                                  clusters_params(coord.cfg))
            except outputs.OutputTaken as exc:  # kept under the next free name; the report says which
                taken = exc
                log.error("%s", exc)
            rep["clusters_file"] = str(outputs.written(clusters))
            if coord.clusters.note:
                log.warning("%s", coord.clusters.note)
        if out:
            _write_json(Path(out), rep)
        print(f"{rep['features']} features -> {rep['clusters']} clusters ({rep['mode']} mode), {rep['total_bytes']} "
              "bytes metered"
                  + (f", {len(rep['lost'])} agent process(es) lost and replaced" if rep["lost"] else "")
                  + (f"; wrote {rep['clusters_file']}" if clusters else ""))
        # the finish messages reach the agents before the session closes: they leave once they have them (a
        # blind 0.2-s sleep here was in every job's time to result)
        if not coord.wait_agents_left(FINISH_WAIT_S):
            log.warning("some agent processes had not left %s after the job's end; closing anyway",
                        seconds(FINISH_WAIT_S))
        return EXIT_OK if taken is None else EXIT_OUTPUT_TAKEN
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
