"""One agent process's control plane, sans I/O: the coordinator's ``start``, ``go``, ``abort`` and
``finish``, and the drivers of the agents the process hosts.

A process starts out hosting its own agent (``home``). Each ``start`` opens an epoch: the process
checks the job's parameters against its own, takes the agents the ``owners`` field gives it (its
own, and a lost agent's cell after a takeover, whose features ``load`` provides), and makes a
driver for each: an :class:`~dqm.distributed.driver.AgentDriver` (balanced, lean, paper) or a
:class:`~dqm.distributed.gathering.GatherDriver` (gather); in an ``auto`` epoch none (the
coordinator picks the mode first, and its ``go`` names it: the drivers are made then). It then answers
``ready``. ``go`` begins every driver.

When a process is lost while the job runs, the coordinator sends ``takeover`` (the agents' new
processes): the process that now hosts a lost agent makes a fresh driver for it, every process
addresses it there, and all answer ``taken``. On ``resume`` every process sends the moved agents
again everything it had sent them in this epoch (the delivery layer's log), and the new host runs
them from their start: what they send that others already have is dropped there as a duplicate
(the same sequence numbers, since every driver is deterministic), the rest arrives. The other
agents keep everything they computed.

The zenoh agent process (:mod:`dqm.runtime.agent`) and the simulator (:mod:`dqm.distributed.simulator`)
both run :class:`ProcessHost`; its transport is their bus, which also learns the epoch, the owners
and the hosted agents from it.
"""
from __future__ import annotations

import logging
from typing import Callable, Dict, List, Optional, Protocol

import numpy as np

from .config import DISTRIBUTED_ENGINES, DQMConfig, differing_param, params_hash, parse_params
from .costmodel import AUTO_MODES, ENGINES_RUN
from .driver import AgentDriver, JobAborted, Transport, ready_fields
from .gathering import GatherDriver
from .ledger import COORDINATOR
from .sources import AgentFeatures

log = logging.getLogger("dqm.distributed")



class Refused(RuntimeError):
    """This process will not take part in the job (a parameter differs, a takeover is impossible)."""


class HostTransport(Transport, Protocol):
    """A :class:`~dqm.distributed.driver.Transport` that also follows the job's epochs and hosts."""

    dim: Optional[int]

    def set_epoch(self, epoch: int) -> None: ...

    def set_owners(self, owners) -> None: ...

    def host(self, agents) -> None: ...

    def replay(self, agents) -> None: ...

    def forget(self, agents) -> None: ...


class ProcessHost:
    """One process's agents (see the module's text). ``features``: the home agent's features;
    ``load(agent)``: another agent's features for a takeover (raises :class:`Refused` when it
    cannot); ``on_state(agent, state)``: handed to the home agent's driver in the first epoch that
    computes (a test's fault injection), or in every epoch with ``on_state_always``; ``trace``: the
    drivers keep what the simulator reports; ``gather_threads``: the threads of the match when this process
    hosts the gathering agent of a gather job (None: :func:`dqm.core.pairs.default_threads`)."""

    def __init__(self, home: int, cfg: DQMConfig, transport: HostTransport, features: AgentFeatures,
                 load: Callable[[int], AgentFeatures], phase_timeout_s: float = 120.0,
                 on_state: Optional[Callable[[int, str], None]] = None, trace: bool = False,
                 on_state_always: bool = False, gather_threads: Optional[int] = None):
        self.home = home
        self.cfg = cfg
        self.bus = transport
        self.load = load
        self.phase_timeout_s = phase_timeout_s
        self.on_state = on_state
        self.on_state_always = on_state_always
        self.trace = trace
        self.gather_threads = gather_threads
        self.features: Dict[int, AgentFeatures] = {home: features}
        transport.dim = features.descriptors.shape[1]
        self.slots: Dict[int, object] = {}  # AgentDriver, or GatherDriver in a gather job
        #: the configuration of the running epoch: ``cfg`` with, when ``cfg.mode`` is auto, the coordinator's pick
        self.job_cfg = cfg
        self.ran = False  # whether drivers were made in an epoch (fault injection: into the first)
        self.epoch = -1
        self.seed: Optional[int] = None
        self.done = False
        self.catalog = False
        self.owners: Optional[np.ndarray] = None  # agent -> process, as the coordinator last said
        self.round = 0  # the last takeover followed in this epoch
        self.waiting: List[int] = []  # agents taken over, to run from their start on ``resume``
        self.moved: List[int] = []  # agents whose process changed since the last resume
        self.hosted: List[int] = []  # the agents this process hosts in this epoch
        self.early: List[tuple] = []  # (agent, message) that came before the go of an auto epoch made the drivers

    @property
    def phase(self) -> str:
        """Where this process is, for messages: its own agent's state."""
        slot = self.slots.get(self.home)
        return slot.state if slot is not None else "wait_start"

    def _features(self, agent: int) -> AgentFeatures:
        if agent not in self.features:
            self.features[agent] = self.load(agent)
        return self.features[agent]

    def job_config(self, params: str) -> DQMConfig:
        """This process's configuration for a ``start`` whose parameter text is ``params``: its own, except
        that a process started with mode auto takes the mode the coordinator names (auto while it measures,
        then gather, lean or balanced), and one started with engine auto the engine it names; the parameter
        check that follows compares everything else."""
        cfg = self.cfg
        theirs = parse_params(params)
        if cfg.mode == "auto":
            mode = theirs.get("mode", "").strip("'\"")
            cfg = cfg.but(mode=mode) if mode in AUTO_MODES + ("auto",) else cfg
        if cfg.engine == "auto":  # a later epoch's start names the engine the coordinator picked
            engine = theirs.get("engine", "").strip("'\"")
            cfg = cfg.but(engine=engine) if engine in DISTRIBUTED_ENGINES else cfg
        return cfg

    def _refuse(self, reason: str, param: str = "") -> None:
        self.bus.send_single(self.home, COORDINATOR, "refuse", reason=reason, param=param)
        raise Refused(reason)

    def control(self, msg: dict) -> bool:
        """Handle a message of the coordinator; False for a kind that is not the control plane's (``probe``:
        the shell answers it). Raises :class:`Refused` (after telling the coordinator) or
        :class:`~dqm.distributed.driver.JobAborted`."""
        kind = msg["kind"]
        if kind == "start":
            self._start(msg)
        elif kind == "go" and msg["epoch"] == self.epoch:
            if self.job_cfg.mode == "auto" or self.job_cfg.engine == "auto":
                self._pick(msg.get("mode", ""), msg.get("engine", ""))
            for slot in self.slots.values():
                slot.begin(self.seed)
        elif kind == "takeover":
            self._takeover(msg)
        elif kind == "resume" and msg["round"] == self.round:
            self._resume()
        elif kind == "gone" and msg["epoch"] == self.epoch:
            self.bus.forget(msg["agents"])
        elif kind == "abort":
            raise JobAborted(f"the coordinator aborted the job: {msg['reason']}")
        elif kind == "finish":
            self.done = True
        elif kind not in ("go", "resume", "gone"):
            return False
        return True

    def _start(self, msg: dict) -> None:
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
        hosted = [int(a) for a in np.flatnonzero(np.asarray(msg["owners"]) == self.home)]
        if self.home not in hosted:
            self._refuse(f"the coordinator gave this process's own agent {self.home} to another process")
        try:
            feats = {a: self._features(a) for a in hosted}
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
        self.owners = np.asarray(msg["owners"], np.int64).copy()
        self.round, self.waiting, self.moved, self.early = 0, [], [], []
        previous, self.job_cfg = self.job_cfg.mode, cfg
        if "auto" in (cfg.mode, previous):
            log.info("epoch %d: mode %s", self.epoch, cfg.mode)
        self.catalog = bool(msg["catalog"])
        self.hosted = hosted
        if "auto" in (cfg.mode, cfg.engine):  # the coordinator picks, then its go names the mode or engine
            self.slots = {}
        else:
            self._make_drivers()
        if self.epoch > 0 and previous != "auto":  # a restart (not the start of the mode auto picked)
            log.info("epoch %d: hosting agents %s", self.epoch, hosted)
        self.bus.send_single(self.home, COORDINATOR, "ready", **ready_fields(
            self.features[self.home].descriptors, hosted, sum(len(f) for f in feats.values())))

    def _make_drivers(self) -> None:
        first = not self.ran or self.on_state_always  # faults are injected into the first run only
        self.slots = {a: self._driver(a, self._features(a), first) for a in self.hosted}
        self.ran = True

    def _pick(self, mode: str, engine: str) -> None:
        """``go`` of an auto epoch: the mode (``--mode auto``) and the engine (``--engine auto``) the
        coordinator picked; make their drivers (no second start)."""
        if self.job_cfg.mode == "auto":
            if mode not in AUTO_MODES:
                raise JobAborted(f"the coordinator's go names no mode of {', '.join(AUTO_MODES)} in a --mode auto "
                                 f"job (got {mode!r})")
            self.job_cfg = self.job_cfg.but(mode=mode)
            log.info("epoch %d: mode %s", self.epoch, mode)
        if self.job_cfg.engine == "auto":
            if engine not in ENGINES_RUN:
                raise JobAborted(f"the coordinator's go names no engine ({' or '.join(ENGINES_RUN)}) in an --engine "
                                 f"auto job (got {engine!r})")
            self.job_cfg = self.job_cfg.but(engine=engine)
            log.info("epoch %d: engine %s", self.epoch, engine)
        self._make_drivers()
        early, self.early = self.early, []
        for dst, msg in early:
            self.deliver(dst, msg)

    def _driver(self, a: int, f: AgentFeatures, faults: bool = False):
        """A fresh driver of hosted agent ``a`` in this epoch (``faults``: with the test's ``on_state``)."""
        cfg = self.job_cfg
        if cfg.mode == "gather":
            return GatherDriver(a, cfg, self.bus, f, self.epoch, self.home, self.catalog, self.phase_timeout_s,
                                self.gather_threads, on_state=self.on_state if faults and a == self.home else None)
        return AgentDriver(a, cfg, self.bus, f.ids, f.image_ids, f.descriptors, phase_timeout_s=self.phase_timeout_s,
                           epoch=self.epoch, home=self.home, catalog=f.catalog if self.catalog else None,
                           trace=self.trace, on_state=self.on_state if faults and a == self.home else None)

    def _takeover(self, msg: dict) -> None:
        """A process was lost while the job ran: address every agent at its new process; make a driver (not
        begun: :meth:`_resume`) for each agent this process now hosts that it did not; answer ``taken``."""
        if msg["epoch"] != self.epoch or msg["round"] <= self.round:
            return  # of another epoch, or a repeated one
        owners = np.asarray(msg["owners"], np.int64)
        self.moved = sorted(set(self.moved) | {int(a) for a in np.flatnonzero(owners != self.owners)})
        self.owners = owners.copy()
        self.bus.set_owners(owners)
        hosted = [int(a) for a in np.flatnonzero(owners == self.home)]
        try:
            new = {a: self._features(a) for a in hosted if a not in self.slots}
        except Refused as exc:
            self._refuse(str(exc))
        for a, f in new.items():
            self.slots[a] = self._driver(a, f)
            self.waiting.append(a)
        self.bus.host(hosted)
        self.round = int(msg["round"])
        if new:
            log.info("takeover %d: hosting agents %s", self.round, hosted)
        self.bus.send_single(self.home, COORDINATOR, "taken", round=self.round, hosted=np.asarray(hosted, np.int64))

    def _resume(self) -> None:
        """Every process follows the takeover: send the moved agents again what this process had sent them,
        and run the agents taken over from their start (their messages that others had are dropped there as
        duplicates; the rest arrive)."""
        moved, self.moved = self.moved, []
        self.bus.replay(moved)
        waiting, self.waiting = self.waiting, []
        for a in waiting:
            if a in self.slots:
                self.slots[a].begin(self.seed)

    def deliver(self, dst: int, msg: dict) -> None:
        """A message of another agent for hosted agent ``dst``. In an auto epoch the drivers are made on ``go``,
        and another process's first messages can come before this process's ``go``: they wait for it."""
        if dst in self.slots:
            self.slots[dst].handle(msg)
        elif dst in self.hosted and self.job_cfg.mode == "auto":
            self.early.append((dst, msg))

    def settle(self) -> None:
        """Let every hosted agent advance as far as its messages allow."""
        for a in sorted(self.slots):
            self.slots[a].settle()

    def check_timeouts(self) -> None:
        for slot in self.slots.values():
            slot.check_timeout()
