"""The coordinator's decisions, sans I/O: epochs, takeovers, what to send next, when the job is
done, and the result.

:class:`CoordinatorCore` takes decoded messages (:meth:`~CoordinatorCore.handle`), the agent
processes whose liveliness tokens vanished (:meth:`~CoordinatorCore.processes_lost`) and, in
``--mode auto``, the measured link rates (:meth:`~CoordinatorCore.decide`). It puts what to send
in its outbox (``(process, kind, fields)``, :meth:`~CoordinatorCore.take_outbox`) and what the
operator should read in its events. It has no clock and no bus: the zenoh coordinator
(:mod:`dqm.runtime.coordinator`) feeds it from the bus and keeps the time limits; the simulator
(:mod:`dqm.distributed.simulator`) feeds it from memory, faults included.

Its phases: ``tokens`` (before :meth:`~CoordinatorCore.begin`), ``start`` (the epoch's ``start``
sent, waiting for every hosting process's ``ready``), ``probe`` (``--mode auto``: the shell
times the links), ``running`` (``go`` sent, collecting results, catalogs and statistics),
``takeover`` (a loss while running: waiting for every live process's ``taken``), then
``done`` (:meth:`~CoordinatorCore.result`) or ``failed``.

Losses (docs/runtime.md): a process that had delivered every result and statistic it owed is
lost harmlessly. Otherwise every agent it hosted goes to the next live process by index (p+1,
p+2, ... wrapping round). Before ``go`` (or with ``recovery="restart"``) the epoch goes up by one
and the job starts again. Once the job runs, a **takeover** follows instead: ``takeover`` tells every
live process the new owners, each answers ``taken``, then ``resume``: the new host runs the moved
agents from their start and every other process sends them again what it had sent them
(:class:`dqm.distributed.hosting.ProcessHost`), keeping all its own work. Either way the labels are
those of a run without the failure, because the cells, the seeds and every round depend only on
the seed integer and the data, never on which process hosts an agent.
More than ``max_lost`` lost processes (default: half, at least one), or none
left, fails the job with :class:`JobFailed` (after ``abort`` to every live process).
"""
from __future__ import annotations

from collections import defaultdict
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..validation import has_repeats
from ..wording import seconds
from . import costmodel, protocol, sources
from .config import RECOVERY, DQMConfig
from .driver import start_fields
from .gathering import GATHERER

#: an outgoing message of the coordinator: (process, kind, fields)
Outgoing = Tuple[int, str, dict]


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
    if not auto["rates_bytes_s"]:
        return f"--mode auto picked {auto['reason']} [no link probes]"
    rates = ", ".join(f"{p}: {costmodel.mbit_text(r)}" for p, r in auto["rates_bytes_s"].items())
    return (f"--mode auto picked {auto['reason']} [measured Mbit/s per process {rates}; "
            f"{auto['probe_s']:.2f} s of probes]")


class CoordinatorCore:
    """The coordinator's state and decisions (see the module's text). ``catalog``: the agents send
    their catalogs (a CLUSTERS file is wanted)."""

    def __init__(self, cfg: DQMConfig, max_lost: Optional[int] = None, catalog: bool = False,
                 recovery: str = "takeover"):
        if recovery not in RECOVERY:
            raise ValueError(f"recovery must be one of {', '.join(RECOVERY)}, got {recovery!r}")
        #: how a loss while the job runs is recovered (:data:`RECOVERY`)
        self.recovery = recovery
        #: the mode the job was started with (``auto``: :meth:`decide` picks the one :attr:`cfg` runs)
        self.requested = cfg
        self.cfg = cfg
        self.m = cfg.agents
        self.max_lost = default_max_lost(self.m) if max_lost is None else max_lost
        self.catalog = catalog
        self.phase = "tokens"
        self.epoch = 0
        #: epochs started in a mode (not counting ``--mode auto``'s measuring epoch)
        self.runs = 0
        self.owners = np.arange(self.m, dtype=np.int64)  # agent -> process hosting it
        self.dead: set = set()
        self.lost: List[dict] = []
        self.states: Dict[int, str] = {}
        self.ready: Dict[int, dict] = {}
        self.results: Dict[int, dict] = {}
        self.stats: Dict[int, dict] = {}
        self.stats_bytes: Dict[int, int] = {}
        self.catalog_parts: Dict[int, Dict[int, dict]] = defaultdict(dict)
        #: auto: the report's ``auto`` block once the mode is picked
        self.auto: Optional[dict] = None
        #: --mode auto, when the links are timed: (rate, mode) where every link at least ``rate`` fast settles the
        #: pick (:func:`costmodel.settled_above`), or None; set by :meth:`decide_unmeasured`
        self.settled: Optional[Tuple[float, str]] = None
        #: the CLUSTERS arrays once the job is done (with ``catalog``)
        self.clusters: Optional[sources.AssembledClusters] = None
        self.outbox: List[Outgoing] = []
        self.events: List[str] = []
        #: takeovers in this epoch; the processes that follow the current one
        self.round = 0
        self.taken: Dict[int, dict] = {}
        #: agents moved by a takeover in this epoch (they run again from their start)
        self.replaying: set = set()

    # ------------------------------------------------------------------ what the shell reads
    def address(self, transport) -> None:
        """Put ``transport`` (the coordinator's bus) in this core's epoch and agent -> process map, before it
        sends the outbox: a restart changes both, a takeover the map."""
        if transport.epoch != self.epoch:
            transport.set_epoch(self.epoch)
        if not np.array_equal(transport.owners, self.owners):
            transport.set_owners(self.owners)

    def take_outbox(self) -> List[Outgoing]:
        out, self.outbox = self.outbox, []
        return out

    def take_events(self) -> List[str]:
        out, self.events = self.events, []
        return out

    def hosts(self) -> List[int]:
        """The processes hosting agents in this epoch."""
        return sorted(set(int(o) for o in self.owners))

    def phase_of(self, p: int) -> str:
        """The phase of process p's own agent (as last reported), for messages."""
        if p in self.states:
            state = self.states[p]
            return state[5:] if state.startswith("wait_") else state
        return "start" if self.phase == "start" else "before the start"

    def catalog_done(self, a: int) -> bool:
        got = self.catalog_parts.get(a)
        return not self.catalog or bool(got) and len(got) == next(iter(got.values()))["parts"]

    def owes(self, p: int) -> bool:
        """Whether process p still owes a result, a catalog or statistics for an agent it hosts."""
        return any(int(self.owners[a]) == p and (a not in self.stats or not self.catalog_done(a))
                   for a in range(self.m))

    @property
    def done(self) -> bool:
        """Whether everything the job's result needs is in."""
        return (self.phase == "running" and len(self.stats) == self.m
                and all(self.catalog_done(a) for a in range(self.m))
                and (self.cfg.mode != "gather" or GATHERER in self.results))

    def unready(self) -> List[int]:
        """The processes whose ``ready`` (``taken`` during a takeover) is still missing."""
        if self.phase == "takeover":
            return [p for p in self._live() if p not in self.taken]
        return [p for p in self.hosts() if p not in self.ready]

    def _live(self) -> List[int]:
        return [p for p in range(self.m) if p not in self.dead]

    # ------------------------------------------------------------------ decisions
    def fail(self, failure: JobFailed) -> None:
        """Abort every live process and raise ``failure``."""
        for p in range(self.m):
            if p not in self.dead:
                self.outbox.append((p, "abort", {"reason": failure.what[:1000]}))
        self.phase = "failed"
        raise failure

    def begin(self, missing: Sequence[int] = ()) -> None:
        """Every process's token is present, or the shell gave up waiting for ``missing`` ones (at most
        :attr:`max_lost`: lost before the start): start the first epoch."""
        if missing:
            self.dead.update(int(p) for p in missing)
            self._reassign()
        self._start()

    def _start(self) -> None:
        """Send this epoch's ``start`` to every live process hosting agents; the ``ready`` answers follow."""
        measuring = self.requested.mode == "auto" and self.auto is None
        cfg = self.requested if measuring else self.cfg
        if not measuring:
            self.runs += 1
        self.results, self.stats, self.stats_bytes, self.ready, self.states = {}, {}, {}, {}, {}
        self.catalog_parts.clear()
        self.round, self.taken, self.replaying = 0, {}, set()
        self.phase = "start"
        fields = start_fields(cfg, self.owners, self.catalog)
        for p in self.hosts():
            self.outbox.append((p, "start", fields))

    def _all_ready(self) -> None:
        hosts = self.hosts()
        ref = self.ready[hosts[0]]
        for p in hosts:
            for name, field in (("dimension", "dim"), ("dtype", "dtype")):
                if self.ready[p][field] != ref[field]:
                    self.fail(JobFailed(f"agent {p} holds descriptors of {name} {self.ready[p][field]}, agent "
                                        f"{hosts[0]} of {name} {ref[field]}", p, "start",
                                        "Give every agent FEATURES of the same descriptor type.", refused=True))
        if self.requested.engine == "auto":  # the features in all decide, as in dqm match; go names the pick
            self.cfg = self.cfg.but(engine=self.requested.engine_for(self.job_shape().n))
        if self.requested.mode == "auto" and self.auto is None:
            self.phase = "probe"  # the shell calls decide_unmeasured(), and if that cannot, times the links
            return
        self._go()

    def _go(self) -> None:
        """Every process is ready: run. In the epoch where ``--mode auto`` measured, ``go`` names the
        mode it picked, and with ``--engine auto`` the engine (from the features in all), and the processes
        make those drivers (no second start)."""
        fields = {"mode": self.cfg.mode} if self.requested.mode == "auto" else {}
        if self.requested.engine == "auto":
            fields["engine"] = self.cfg.engine
        for p in self.hosts():
            self.outbox.append((p, "go", fields))
        self.phase = "running"

    def handle(self, msg: dict) -> None:
        """Record one decoded message: progress, refusal, ready, result, catalog, statistics."""
        kind, src = msg["kind"], msg["src"]
        if kind == "progress":
            self.states[src] = msg["state"]
        elif kind == "refuse":
            self.fail(JobFailed(f"agent {src} refused the job: {msg['reason']}", src, self.phase_of(src),
                                "Start every agent with the coordinator's algorithm options." if msg["param"] else
                                "Check that agent's log.", refused=True))
        elif kind == "ready" and self.phase == "start":
            self.ready[src] = msg
            if not self.unready():
                self._all_ready()
        elif kind == "taken" and self.phase == "takeover" and msg["round"] == self.round:
            self.taken[src] = msg
            if not self.unready():
                self.phase = "running"
                for p in self._live():
                    self.outbox.append((p, "resume", {"round": self.round}))
        elif self.phase not in ("running", "takeover"):
            return
        elif kind == "result":
            self.results[src] = msg
        elif kind == "catalog":
            self.catalog_parts[src][msg["part"]] = msg
        elif kind == "stats":
            self.stats[src] = msg["values"]
            # the stats message itself was sent after the agent's meter snapshot
            self.stats_bytes[src] = msg["_bytes"] + len(msg["_key"])

    def processes_lost(self, gone: Sequence[int]) -> None:
        """These processes' tokens vanished. One that owed nothing is lost harmlessly; otherwise its agents
        move to the next live processes and the next epoch starts (or the job fails: too many lost)."""
        gone = [int(p) for p in gone if p not in self.dead]
        if self.phase == "done":  # everything was in: nothing can be lost any more
            self.dead.update(gone)
            return
        if not gone:
            return
        running = self.phase in ("running", "takeover")
        # while an agent taken over runs again, it may still need what a finished agent had sent it: that one's
        # process, gone, can no longer send it again, so the finished agent runs again too
        replaying = any(a not in self.stats for a in self.replaying)
        owing = [p for p in gone if not running or replaying or self.owes(p)]
        self.dead.update(gone)
        for p in gone:
            if p not in owing:
                self.events.append(f"agent process {p} exited after delivering its results; nothing is lost")
                finished = np.flatnonzero(self.owners == p).astype(np.int64)
                for q in self._live():  # nobody waits for their acks (a later takeover may run them again)
                    self.outbox.append((q, "gone", {"agents": finished}))
        if not owing:
            return
        takeover = running and self.recovery == "takeover"
        before = self.owners.copy()
        self._reassign(restart=not takeover)
        if not takeover:
            self._start()
            return
        self.round += 1
        self.taken = {}
        self.phase = "takeover"
        self.replaying |= {a for a in range(self.m) if int(self.owners[a]) != int(before[a])}
        for p in self._live():
            self.outbox.append((p, "takeover", {"owners": self.owners.copy(), "round": self.round}))

    def _reassign(self, restart: bool = True) -> None:
        """Give every agent hosted by a dead process to the next live process by index; each such process
        counts as lost (also one that had exited after delivering its results of an earlier epoch).
        ``restart``: the next epoch starts (else a takeover follows in this one)."""
        orphaned = sorted({int(o) for o in self.owners} & self.dead)
        for p in orphaned:
            self.lost.append({"process": p, "phase": self.phase_of(p), "epoch": self.epoch,
                              "recovery": "restart" if restart else "takeover"})
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
        if restart:
            self.epoch += 1
        self.events.append(", ".join(f"agent process {q} was lost in phase {self.phase_of(q)}" for q in orphaned)
                           + "; " + ", ".join(f"agent {a} -> process {q}" for a, q in sorted(moved.items()))
                           + (f"; restarting at epoch {self.epoch}" if restart else
                              "; the survivors keep their work, the moved agents run again at their new process"))

    def job_shape(self) -> costmodel.JobShape:
        """The job as the cost model sees it, from the hosting processes' ``ready``."""
        hosts = self.hosts()
        ref = self.ready[hosts[0]]
        n = int(sum(self.ready[p]["features"] for p in hosts))
        return costmodel.JobShape(n=max(1, n), agents=self.m, dim=int(ref["dim"]),
                                  itemsize=np.dtype(ref["dtype"]).itemsize, engine=self.cfg.engine_for(n),
                                  copies=self.cfg.copies_per_feature)

    def decide_unmeasured(self, cores: float, gather_cores: float, kernel_cpu_s: Optional[float] = None) -> bool:
        """``--mode auto`` from cheap facts: when the cost model predicts one mode within
        :data:`costmodel.CLEAR_WITHIN` of the fastest at every link rate of :data:`costmodel.CLEAR_RATES_BYTES_S`
        (features, agents, cores and the pair rate decide it whatever the links), start that mode without timing
        the links; returns whether it did (else the shell measures them and calls :meth:`decide`).
        ``kernel_cpu_s``: the shell's :func:`dqm.core.pairs.pair_cpu_s_here` (None: the fit machine's speed)."""
        from ..validation import InputError

        hosts = self.hosts()

        def at(r: float) -> costmodel.Hosts:
            return costmodel.Hosts.of([r] * len(hosts), cores, gather_cores=gather_cores, kernel_cpu_s=kernel_cpu_s)

        self.settled = None
        try:
            job = self.job_shape()
            found = costmodel.rate_free_choice(job, at, modes=self.requested.auto_choices)
            if found is None:
                above = costmodel.settled_above(job, at, modes=self.requested.auto_choices)
                self.settled = None if above is None else above[:2]
        except InputError:
            return False  # the measuring path says what is wrong
        if found is None:
            return False
        mode, worst, (least, most) = found
        lo_s, hi_s = (costmodel.mbit_text(r) for r in (costmodel.CLEAR_RATES_BYTES_S[0],
                                                        costmodel.CLEAR_RATES_BYTES_S[-1]))
        how = "the fastest" if worst <= 1 + 1e-9 else f"within {100 * (worst - 1):.1f}% of the fastest"
        reason = (f"{mode} without timing the links: {how} at every link rate from {lo_s} to {hi_s} Mbit/s "
                  f"(predicted {seconds(least)} to {seconds(most)}; {job.n} features on {self.m} agents, "
                  f"{job.engine} engine, "
                  f"cores per host {cores:.3g}{costmodel.speed_text(kernel_cpu_s)})")
        self._picked(mode, {}, {mode: round(most, 3)}, reason, 0.0, {}, cores, gather_cores, job.n, kernel_cpu_s)
        return True

    @property
    def enough_rate(self) -> Optional[float]:
        """--mode auto: a probe reading (bytes/s) at which a link needs no finer timing (:attr:`settled` times
        :data:`costmodel.SETTLED_MARGIN`), or None."""
        return None if self.settled is None else self.settled[0] * costmodel.SETTLED_MARGIN

    def decide(self, rates: Dict[int, float], cores: float, gather_cores: float, probe_s: float,
               pairs: Optional[Dict[int, list]] = None, kernel_cpu_s: Optional[float] = None,
               at_least: Sequence[int] = ()) -> None:
        """``--mode auto``: pick the mode from the measured rates (bytes/s to each hosting process) and pair
        rate (``kernel_cpu_s``, as in :meth:`decide_unmeasured`) with the cost model, and run it (``go`` names
        it: the processes make its drivers in this epoch). ``at_least``: the processes whose rate is only a
        lower bound (a probe pair read at least :attr:`enough_rate`). When every link is at least that fast
        the pick is :attr:`settled`'s mode."""
        from ..validation import InputError

        hosts = self.hosts()
        try:
            job = self.job_shape()
            choice = costmodel.choose(job, costmodel.Hosts.of([rates[p] for p in hosts], cores,
                                                              gather_cores=gather_cores, kernel_cpu_s=kernel_cpu_s),
                                      started=True, modes=self.requested.auto_choices)
        except InputError as exc:
            self.fail(JobFailed(f"--mode auto cannot pick a mode: {exc}", None, "probe",
                                "Give the job's mode explicitly (--mode balanced, lean or gather)."))
        mode, reason = choice.mode, choice.reason
        enough = self.enough_rate
        if enough is not None and all(rates[p] >= enough for p in hosts):
            floor, mode = self.settled
            reason = (f"{mode}: every link measured at least {costmodel.mbit_text(enough)} Mbit/s, and {mode} is "
                      f"predicted within {100 * (costmodel.CLEAR_WITHIN - 1):.0f}% of the fastest at every rate from "
                      f"{costmodel.mbit_text(floor)} Mbit/s up ({job.n} features on {self.m} agents, "
                      f"{job.engine} engine, cores per host "
                      f"{cores:.3g}{costmodel.speed_text(kernel_cpu_s)})")
        self._picked(mode, rates, choice.predicted_s, reason, probe_s, pairs or {}, cores,
                     gather_cores, job.n, kernel_cpu_s, at_least)

    def _picked(self, mode: str, rates: Dict[int, float], predicted_s: Dict[str, Optional[float]], reason: str,
                probe_s: float, pairs: Dict[int, list], cores: float, gather_cores: float, n: int,
                kernel_cpu_s: Optional[float], at_least: Sequence[int] = ()) -> None:
        hosts = self.hosts()
        self.cfg = self.cfg.but(mode=mode)
        self.auto = {
            "rates_bytes_s": {str(p): round(rates[p], 1) for p in hosts if p in rates},
            "rates_at_least": [str(p) for p in hosts if p in at_least],
            "picked": mode, "engine": self.cfg.engine, "predicted_s": predicted_s, "reason": reason,
            "probe_s": probe_s,
            "probe_pairs": {str(p): [list(x) for x in pairs.get(p, [])] for p in hosts if p in pairs},
            "cores_per_host": cores, "gather_cores": gather_cores, "features": n, "kernel_cpu_s": kernel_cpu_s,
        }
        self.runs += 1
        self._go()

    def result(self) -> Tuple[np.ndarray, np.ndarray]:
        """Once :attr:`done`: the job's ``(ids, labels)`` (gather: the gathering agent's, every feature's), the
        CLUSTERS arrays with ``catalog``, and ``finish`` to every live process."""
        if self.cfg.mode == "gather":
            ids, labels = self.results[GATHERER]["ids"], self.results[GATHERER]["labels"]
        else:
            ids, labels = sources.assemble_labels([(self.results[a]["ids"], self.results[a]["labels"])
                                                   for a in range(self.m)])
        if has_repeats(ids):
            self.fail(JobFailed("two agents reported the same feature (feature ids must be unique across the "
                                "job: give each FEATURES file its own feature_ids, or none)", None, "result"))
        if self.catalog:
            try:
                catalogs = {a: protocol.merge_parts("catalog", list(self.catalog_parts[a].values()))
                            for a in range(self.m)}
                self.clusters = sources.assemble_clusters(ids, labels, catalogs)
            except ValueError as exc:  # MessageError included: parts that do not fit together
                self.fail(JobFailed(f"the agents' catalogs do not describe their results ({exc})", None, "result"))
        n_clusters = int(labels.max() + 1) if len(labels) else 0
        for p in self.hosts():
            if p not in self.dead:
                self.outbox.append((p, "finish", {"clusters": n_clusters}))
        self.phase = "done"
        return ids, labels
