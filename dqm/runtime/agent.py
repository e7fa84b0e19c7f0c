"""A Distributed QuickMatch agent process: the zenoh shell around the one agent driver.

It starts with the features of its own images, declares its inbox and its
liveliness token, and waits for the coordinator's ``start``. Each start opens an
epoch with an :class:`~dqm.distributed.driver.AgentDriver` per hosted agent (its
own, and any lost agent's cell the coordinator gave it), the same driver the
in-process simulator runs, here fed from the bus. This module holds the host
control plane (start, go, abort, finish), the bounded waiting and the exit
codes. All waiting is bounded; a vanished coordinator or an abort message ends
the process with a clear error.
"""
from __future__ import annotations

import logging
import os
import time
from typing import Callable, Dict, List, Optional

import numpy as np

from .. import signals
from ..distributed import keys, messages, protocol, sources
from ..distributed.config import DQMConfig, differing_param, params_hash, parse_params
from ..distributed.costmodel import AUTO_MODES
from ..distributed.driver import AgentDriver, JobAborted, ready_fields
from ..distributed.ledger import COORDINATOR
from ..logging_config import tag_lines
from .bus import Bus, check_job_free, open_client
from .gather import gather_payload
from .measure import probe_answer

log = logging.getLogger("dqm.runtime")

__all__ = ["AgentHost", "CoordinatorLost", "GatherSource", "JobAborted", "Refused", "RouterLost",
           "fault_pause_from_env", "main_agent", "parse_peer_features"]


def fault_pause_from_env() -> Optional[Callable[[int, str], None]]:
    """The test hook, read once at start-up: with DQM_FAULT_PAUSE="<agent>:<state>" the agent stops when
    it enters that state, writing its pid to the file named by DQM_FAULT_MARKER, so that a test can kill
    it there. It goes on after DQM_FAULT_SECONDS (default 60), or as soon as the test deletes the marker
    file. Returns the ``on_state`` callback for :class:`~dqm.distributed.driver.AgentDriver`, or None."""
    spec = os.environ.get("DQM_FAULT_PAUSE")
    if not spec:
        return None
    marker = os.environ.get("DQM_FAULT_MARKER")
    seconds = float(os.environ.get("DQM_FAULT_SECONDS", "60"))

    def pause(agent: int, state: str) -> None:
        if spec != f"{agent}:{state}":
            return
        if marker:
            with open(marker, "w") as fh:
                fh.write(f"{os.getpid()}\n")
        end = time.monotonic() + seconds
        while time.monotonic() < end and (not marker or os.path.exists(marker)):
            time.sleep(0.05)

    return pause


class Refused(RuntimeError):
    """This process will not take part in the job (a parameter differs, a takeover is impossible)."""


class CoordinatorLost(RuntimeError):
    """The coordinator's liveliness token vanished."""


class RouterLost(RuntimeError):
    """The session's router is gone: nothing can arrive or leave any more."""


class GatherSource:
    """One hosted agent of a ``gather`` job (``--mode gather``, or ``auto`` when the coordinator picked it):
    on ``go`` it sends its features to the coordinator as ``gather`` messages
    (:func:`dqm.runtime.gather.gather_payload` in parts, numbered on its link, not acknowledged: BLOCK puts on a
    reliable session, like the stand-alone gathering) and its catalog when the job asked for it, then its
    statistics once the catalog is acknowledged, and waits for ``finish``. The same calls as
    :class:`~dqm.distributed.driver.AgentDriver` (``begin``, ``handle``, ``settle``, ``check_timeout``)."""

    def __init__(self, me: int, cfg: DQMConfig, bus: Bus, features: sources.AgentFeatures, epoch: int,
                 home: int, catalog: bool, phase_timeout_s: float = 120.0):
        self.me, self.cfg, self.bus, self.features = me, cfg, bus, features
        self.epoch, self.home, self.catalog = epoch, home, catalog
        self.phase_timeout_s = phase_timeout_s
        self.state = "wait_start"
        self.phase_started = time.monotonic()
        self.cpu0 = time.process_time()
        self.times: Dict[str, float] = {}

    def _enter(self, state: str) -> None:
        now = time.monotonic()
        self.times[f"time_{self.state}"] = self.times.get(f"time_{self.state}", 0.0) + now - self.phase_started
        self.state, self.phase_started = state, now
        self.bus.send(self.me, COORDINATOR, "progress", messages.encode(
            "progress", self.cfg.job, self.me, epoch=self.epoch, state=state, features=len(self.features),
            bytes=int(self.bus.meter.sent_by(self.me))))

    def begin(self, seed: int) -> None:
        """``go``: send the features (and the catalog) to the coordinator."""
        self._enter("gather")
        f = self.features
        payload = gather_payload(f.ids, f.image_ids, f.descriptors)
        seq0 = self.bus.next_seq(self.me, COORDINATOR, protocol.part_count("gather", payload))
        for msg in protocol.data_messages("gather", self.cfg.job, self.me, payload, seq0=seq0, epoch=self.epoch):
            self.bus.send(self.me, COORDINATOR, "gather", msg)
        if self.catalog:
            payload = self.features.catalog
            n = protocol.part_count("catalog", payload)
            seq0 = self.bus.next_seq(self.me, COORDINATOR, n)
            for j, msg in enumerate(protocol.data_messages("catalog", self.cfg.job, self.me, payload, seq0=seq0,
                                                           epoch=self.epoch)):
                self.bus.send(self.me, COORDINATOR, "catalog", msg, seq=seq0 + j)
        self._enter("wait_acks")

    def handle(self, msg: dict) -> None:
        """Nothing comes to a gathering source from other agents."""

    def settle(self) -> None:
        """Once the catalog is acknowledged (at once without one): the statistics, then wait for ``finish``."""
        if self.state == "wait_acks" and self.bus.unacknowledged(self.me) == 0:
            self._enter("wait_finish")
            stats = dict(self.times)
            stats["cpu_s"] = time.process_time() - self.cpu0
            stats["host"] = float(self.home)
            stats["features"] = float(len(self.features))
            if self.me == self.home:  # the process's counters, reported once
                stats.update(self.bus.meter.counter_stats())
            stats.update(self.bus.meter.as_stats(src=self.me))
            self.bus.send_single(self.me, COORDINATOR, "stats", values=stats)

    def check_timeout(self) -> None:
        """A catalog unacknowledged for longer than the phase timeout ends the process (TimeoutError)."""
        if self.state == "wait_acks" and time.monotonic() - self.phase_started > self.phase_timeout_s:
            raise TimeoutError(f"agent {self.me} waited more than {self.phase_timeout_s:.0f} s for the coordinator "
                               "to acknowledge its catalog")


class AgentHost:
    """One agent process: its own agent (``home``) and any lost agents' cells the coordinator gave it.

    Control messages (``start``, ``go``, ``abort``, ``finish``) come from the
    coordinator; each ``start`` opens an epoch with a fresh
    :class:`~dqm.distributed.driver.AgentDriver` for every agent this process
    hosts (its own features, and the features of a lost agent re-read from that
    agent's files). ``on_state(agent, state)`` is handed to the driver of this
    process's own agent in the first epoch (a test's fault injection).
    """

    def __init__(self, home: int, cfg: DQMConfig, bus: Bus, paths: Dict[int, List[str]],
                 phase_timeout_s: float = 120.0, own: Optional[sources.AgentFeatures] = None,
                 on_state: Optional[Callable[[int, str], None]] = None):
        self.home = home
        self.cfg = cfg
        self.bus = bus
        self.paths = paths
        self.phase_timeout_s = phase_timeout_s
        self.on_state = on_state
        self.features: Dict[int, sources.AgentFeatures] = {
            home: own if own is not None else sources.load_agent_features(paths[home], home)}
        bus.dim = self.features[home].descriptors.shape[1]
        self.slots: Dict[int, object] = {}  # AgentDriver, or GatherSource in a gather job
        #: the configuration of the running epoch: ``cfg`` with, when ``cfg.mode`` is auto, the coordinator's pick
        self.job_cfg = cfg
        self.ran = False  # whether an epoch of a mode that computes has started (fault injection: the first)
        self.epoch = -1
        self.seed: Optional[int] = None
        self.done = False
        self.t0 = time.monotonic()
        self._router_checked = self.t0

    @property
    def phase(self) -> str:
        """Where this process is, for messages: its own agent's state."""
        slot = self.slots.get(self.home)
        return slot.state if slot is not None else "wait_start"

    def _load(self, agent: int):
        if agent not in self.features:
            if agent not in self.paths:
                raise Refused(f"cannot take over agent {agent}: this process has no path to its FEATURES files "
                              f"(start agents with --peer-features {agent}=FILE)")
            try:
                self.features[agent] = sources.load_agent_features(self.paths[agent], agent)
            except (OSError, ValueError) as exc:
                raise Refused(f"cannot take over agent {agent}: {exc}") from None
        return self.features[agent]

    def job_config(self, params: str) -> DQMConfig:
        """This process's configuration for a ``start`` whose parameter text is ``params``: its own, except
        that a process started with mode auto takes the mode the coordinator names (auto while it measures,
        then gather, lean or balanced); the parameter check that follows compares everything else."""
        if self.cfg.mode != "auto":
            return self.cfg
        theirs = parse_params(params).get("mode", "").strip("'\"")
        return self.cfg.but(mode=theirs) if theirs in AUTO_MODES + ("auto",) else self.cfg

    def _refuse(self, reason: str, param: str = "") -> None:
        self.bus.send_single(self.home, -1, "refuse", reason=reason, param=param)
        raise Refused(reason)

    def control(self, msg: dict) -> None:
        kind = msg["kind"]
        if kind == "start":
            if msg["epoch"] <= self.epoch:
                return  # a repeated start of this epoch
            self.bus.set_epoch(msg["epoch"])
            self.bus.set_owners(msg["owners"])
            cfg = self.job_config(msg["params"])
            mine = cfg.params_text()
            if msg["params_hash"] != params_hash(mine) or msg["agents"] != self.cfg.agents:
                name, ours, theirs = differing_param(mine, msg["params"]) or ("params", "?", "?")
                self._refuse(f"parameter {name} differs: this agent has {name}={ours}, the coordinator "
                             f"{name}={theirs}; start every process of a job with the same algorithm options", name)
            hosted = [int(a) for a in np.flatnonzero(msg["owners"] == self.home)]
            if self.home not in hosted:
                self._refuse(f"the coordinator gave this process's own agent {self.home} to another process")
            try:
                feats = {a: self._load(a) for a in hosted}
            except Refused as exc:
                self._refuse(str(exc))
            dims = {f.descriptors.shape[1] for f in feats.values()}  # the home agent is among them
            if len(dims) != 1:
                self._refuse(f"the FEATURES files of agents {hosted} have different dimensions {sorted(dims)}",
                             "dimension")
            self.bus.dim = dims.pop()
            self.bus.host(hosted)
            self.epoch = msg["epoch"]
            self.seed = msg["seed"]
            previous, self.job_cfg = self.job_cfg.mode, cfg
            if "auto" in (cfg.mode, previous):
                log.info("epoch %d: mode %s", self.epoch, cfg.mode)
            if cfg.mode == "auto":  # the coordinator measures the links, then starts the mode it picked
                self.slots = {}
            elif cfg.mode == "gather":
                self.slots = {a: GatherSource(a, cfg, self.bus, f, self.epoch, self.home, bool(msg["catalog"]),
                                              self.phase_timeout_s) for a, f in feats.items()}
            else:
                first = not self.ran  # faults are injected into the first run only
                self.slots = {a: AgentDriver(a, cfg, self.bus, f.ids, f.image_ids, f.descriptors,
                                             phase_timeout_s=self.phase_timeout_s, epoch=self.epoch, home=self.home,
                                             catalog=f.catalog if msg["catalog"] else None,
                                             on_state=self.on_state if first and a == self.home else None)
                              for a, f in feats.items()}
                self.ran = True
            if self.epoch > 0 and previous != "auto":  # a restart (not the start of the mode auto picked)
                log.warning("epoch %d: hosting agents %s", self.epoch, hosted)
            self.bus.send_single(self.home, COORDINATOR, "ready", **ready_fields(
                self.features[self.home].descriptors, hosted, sum(len(f) for f in feats.values())))
        elif kind == "go" and msg["epoch"] == self.epoch:
            for slot in self.slots.values():
                slot.begin(self.seed)
        elif kind == "probe":  # --mode auto: the coordinator times its link to this process; answer at once
            self.bus.send(self.home, COORDINATOR, "probe", messages.encode(
                "probe", self.cfg.job, self.home, epoch=msg["epoch"], token=msg["token"], reply=0,
                data=probe_answer(msg["reply"], msg["_t"])))
        elif kind == "abort":
            raise JobAborted(f"the coordinator aborted the job: {msg['reason']}")
        elif kind == "finish":
            self.done = True

    def run(self) -> None:
        while not self.done:
            item = self.bus.receive(timeout=0.05)
            if item is not None:
                dst, msg = item
                if msg["src"] == -1:
                    self.control(msg)
                elif dst in self.slots:
                    self.slots[dst].handle(msg)
            for a in sorted(self.slots):
                self.slots[a].settle()
            self.bus.resend_due()
            self._check_router()
            if self.epoch >= 0 and self.bus.coordinator_alive() is False:
                raise CoordinatorLost(f"the coordinator vanished (its liveliness token was lost) while this agent was "
                                      f"in phase {self.phase}")
            for slot in self.slots.values():
                slot.check_timeout()
            if self.epoch < 0 and time.monotonic() - self.t0 > self.phase_timeout_s:
                raise TimeoutError(f"no start from a coordinator within {self.phase_timeout_s:.0f} s")

    def _check_router(self) -> None:
        """Every 0.25 s: the router must still be there (else the agent would wait out its phase timeout and
        blame the coordinator)."""
        now = time.monotonic()
        if now - self._router_checked < 0.25:
            return
        self._router_checked = now
        if not self.bus.router_connected():
            where = "waiting for its coordinator" if self.epoch < 0 else f"in phase {self.phase}"
            raise RouterLost(f"the zenoh router is gone (the session to it closed) while this agent was {where}")


def parse_peer_features(specs: Optional[List[str]]) -> Dict[int, List[str]]:
    """``["2=/data/a2.npz,/data/a2b.npz", ...]`` -> {2: [...]}: where a lost agent's images can be re-read."""
    from ..validation import InputError

    out: Dict[int, List[str]] = {}
    for spec in specs or []:
        agent, sep, paths = spec.partition("=")
        if not sep or not agent.strip().isdigit() or not paths:
            raise InputError(f"--peer-features must look like AGENT=FILE[,FILE...], got {spec!r}")
        out[int(agent)] = [p for p in paths.split(",") if p]
    return out


#: exit codes of ``dqm agent`` (docs/runtime.md)
EXIT_OK, EXIT_FAILED, EXIT_REFUSED, EXIT_COORDINATOR_LOST = 0, 3, 4, 5  # 130 / 143: dqm.signals


def main_agent(me: int, cfg: DQMConfig, endpoint: str, paths, tls: Optional[dict] = None,
               connect_timeout_s: float = 5.0, phase_timeout_s: float = 120.0,
               max_message_bytes: int = messages.MAX_MESSAGE_BYTES,
               peers: Optional[Dict[int, List[str]]] = None) -> int:
    """Entry point of ``dqm agent``: returns the process exit code."""
    from .lifeline import watch_parent

    signals.install_sigterm(force=True)
    watch_parent()
    keys.check_job(cfg.job)
    files = dict(peers or {})
    files[me] = list(paths)
    tag_lines(f"agent {me}")
    own = sources.load_agent_features(paths, me)
    session = open_client(endpoint, tls, deadline_s=connect_timeout_s)
    check_job_free(session, keys.alive_agent(cfg.job, me), f"agent {me}", cfg.job, endpoint)
    host = None
    bus = None
    try:
        bus = Bus(session, cfg.job, me, cfg.agents, max_bytes=max_message_bytes)
        bus.check_access(endpoint, tls, f"agent process {me} of job {cfg.job!r}")
        host = AgentHost(me, cfg, bus, files, phase_timeout_s=phase_timeout_s, own=own,
                         on_state=fault_pause_from_env())
        log.info("connected to the router at %s; waiting for the coordinator of job %r", endpoint, cfg.job)
        host.run()
        return EXIT_OK
    except Refused as exc:
        log.error("refused: %s", exc)
        time.sleep(0.3)  # let the refusal reach the coordinator before the token goes
        return EXIT_REFUSED
    except (CoordinatorLost, RouterLost) as exc:
        where = f" (router: {endpoint})" if isinstance(exc, RouterLost) else ""
        log.error("error: %s%s. This agent leaves; to run the job again, start %sthe coordinator and every agent "
                  "again with the same options (a job restarts from the beginning).", exc, where,
                  "the router, " if isinstance(exc, RouterLost) else "")
        return EXIT_COORDINATOR_LOST
    except (JobAborted, TimeoutError) as exc:
        log.error("error: %s", exc)
        return EXIT_FAILED
    except KeyboardInterrupt as exc:  # Ctrl-C, and SIGTERM as signals.Terminated
        log.warning("%s, leaving", signals.word(exc))
        return signals.exit_code(exc)
    finally:
        if bus is not None:
            bus.close()
        else:
            session.close()
