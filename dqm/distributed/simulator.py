"""In-process simulator of Distributed QuickMatch: all agents' steps in one process.

Every process is the runtime's own process host (:class:`dqm.distributed.hosting.ProcessHost`,
with the one agent driver :class:`dqm.distributed.driver.AgentDriver` per hosted agent), and the
coordinator is the runtime's own core (:class:`dqm.distributed.coordination.CoordinatorCore`), fed
from the in-memory network (:mod:`dqm.distributed.network`, the zenoh bus's delivery layer on a
virtual clock) instead of the zenoh bus: the same choreography, the same messages on every link,
metered by the same ledger (:mod:`dqm.distributed.ledger`), and decoded again so the codec is on the
path. It is the reference the runtime is tested against; its fault plan replays lost acks,
duplicates, delays and lost processes deterministically.

Agents start with the features of their own images (image k of the sorted
image ids belongs to agent k mod m), so routing is real traffic.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np

from .. import io
from ..validation import InputError, check_descriptors, check_image_ids, check_magnitude
from . import protocol
from .balanced import BalancedCore
from .config import DQMConfig
from .coordination import CoordinatorCore
from .driver import SETUP_STATES, AgentDriver, states_for
from .hosting import ProcessHost
from .ledger import COORDINATOR, TrafficLedger
from .network import LOST, FaultPlan, LoseProcess, MemoryNetwork
from .sources import AgentFeatures, agent_features, assemble_labels, image_owners, split_features

#: the simulator's name for the one traffic ledger (kept for callers of ``dqm.distributed.Traffic``)
Traffic = TrafficLedger


@dataclass
class DQMResult:
    """Outcome of a distributed job: global labels plus everything needed for tables and pictures.

    ``stats`` holds, among others, ``max_features_share`` (the most feature rows any
    agent held at once, measured by its driver at every message: its source's features until
    routed, its cell's, and every routed, copied or handed-down feature received and not yet let
    go, over n), ``max_pair_share`` (the
    busiest agent's pair count over the centralized pass's n(n-1)/2),
    ``bytes_over_raw`` (metered bytes over n * dim * itemsize),
    ``ghosts_per_feature``, ``busiest_cpu_s`` and ``arrival_check_failures``.
    """

    labels: np.ndarray  # (n,) canonical cluster labels
    holder: np.ndarray  # (n,) agent that decided each feature's cluster
    cells: np.ndarray  # (n,) routing cell of each feature
    owners: np.ndarray  # (n,) source agent of each feature
    sites: np.ndarray  # (m, dim) the cells' sites (the power diagram's centres), drawn from ``config.seed``
    config: DQMConfig
    traffic: Traffic
    stats: Dict[str, float] = field(default_factory=dict)
    per_agent: List[Dict[str, float]] = field(default_factory=list)
    weights: Optional[np.ndarray] = None  # power-diagram weights of the cells (None: plain Voronoi)
    initial_labels: Optional[np.ndarray] = None  # lean/paper: local cluster labels after step 1
    contested: Optional[np.ndarray] = None  # lean/paper: contested in the initial test
    handed_to: Optional[np.ndarray] = None  # lean/paper: first hand-down target (-1 = kept)
    copies: Optional[np.ndarray] = None  # balanced: (K, 2) ghost copies as (feature id, receiving agent)
    density: Optional[np.ndarray] = None  # balanced: every feature's density (as its owner computed it)
    parent: Optional[np.ndarray] = None  # balanced: tree parent (-1: none within rho sigma)
    parent_distance: Optional[np.ndarray] = None
    #: the processes the coordinator lost (as in a runtime report: process, phase, epoch) and the epochs run
    lost: List[dict] = field(default_factory=list)
    epochs: int = 1

    @property
    def n_clusters(self) -> int:
        return int(self.labels.max() + 1) if len(self.labels) else 0

    @property
    def seeds(self) -> np.ndarray:
        """The cells' sites under their earlier name (``seed`` is the one integer they come from)."""
        return self.sites



class _Clock:
    """CPU seconds per process (the simulator runs them one after another, so process time is theirs)."""

    def __init__(self, m: int):
        self.cpu = np.zeros(m)

    def run(self, p: int, fn: Callable, *args, **kwargs):
        t = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            self.cpu[p] += time.process_time() - t


class _ProcessLost(Exception):
    """The fault plan's loss of a process, raised where its agent enters the planned state."""

    def __init__(self, process: int):
        super().__init__(process)
        self.process = process


class _Job:
    """One simulated job: the processes (:class:`~dqm.distributed.hosting.ProcessHost`), the coordinator
    (:class:`~dqm.distributed.coordination.CoordinatorCore`) and the network between them."""

    def __init__(self, cfg: DQMConfig, held: List[AgentFeatures], net: MemoryNetwork, catalog: bool,
                 max_lost: Optional[int], recovery: str = "takeover"):
        self.cfg, self.net, self.held = cfg, net, held
        self.clock = _Clock(cfg.agents)
        self.core = CoordinatorCore(cfg, max_lost=max_lost, catalog=catalog, recovery=recovery)
        self.coord = net.endpoint(COORDINATOR)
        losses = net.plan.losses()
        self.hosts: Dict[int, ProcessHost] = {}
        self.gone: Dict[int, ProcessHost] = {}  # lost processes (one that had delivered everything keeps its part)
        for p in range(cfg.agents):
            on_state = self._loss_hook(p, losses[p]) if p in losses else None
            self.hosts[p] = ProcessHost(p, cfg, net.endpoint(p), held[p], lambda a: self.held[a],
                                        on_state=on_state, trace=True, on_state_always=True)

    def _loss_hook(self, process: int, when: LoseProcess):
        def hook(agent: int, entered: str) -> None:
            if entered == when.state and self.hosts[process].epoch == when.epoch:
                raise _ProcessLost(process)
        return hook

    def flush(self) -> None:
        """Send what the coordinator decided (entering its epoch first)."""
        self.core.address(self.coord)
        for p, kind, fields in self.core.take_outbox():
            self.coord.send_single(COORDINATOR, p, kind, **fields)
        self.core.take_events()

    def _at(self, p: int, fn: Callable, *args) -> None:
        """Run a step of process p; a planned loss there kills it and tells the coordinator."""
        try:
            self.clock.run(p, fn, *args)
        except _ProcessLost as lost:
            self.net.lose(lost.process)
            self.gone[lost.process] = self.hosts.pop(lost.process)

    def drivers(self) -> List:
        """The final epoch's driver of every agent (that finished)."""
        every = {**self.gone, **self.hosts}
        out = []
        for a in range(self.cfg.agents):
            current = every[int(self.core.owners[a])].slots[a]
            if current.state != "wait_finish":  # a finished agent running again when the job ended: its first run
                done = [h.slots[a] for h in self.gone.values()
                        if a in h.slots and h.slots[a].state == "wait_finish" and h.epoch == self.core.epoch]
                current = done[-1] if done else current
            out.append(current)
        return out

    def run(self, progress: Optional[Callable[[int, int], None]]) -> float:
        """Deliver messages and let every process advance until the coordinator has everything; returns the
        wall seconds the set-up (up to routing) took."""
        t0 = time.perf_counter()
        t_setup = None
        routed = SETUP_STATES.index("wait_routed")
        total = len(states_for(self.cfg.mode)) - 1
        shown = -1
        self.core.begin()
        self.flush()
        while not self.core.done:
            for p in sorted(self.hosts):
                if p in self.hosts:
                    self._at(p, self.hosts[p].settle)
            slots = [s for h in self.hosts.values() for s in h.slots.values() if hasattr(s, "step_index")]
            step = min((s.step_index for s in slots), default=0)
            if t_setup is None and step >= routed and slots:
                t_setup = time.perf_counter() - t0
            if progress and step > shown:
                shown = step
                progress(step, total)
            if not self._deliver_now():
                break
        if not self.core.done:
            stuck = {a: s.state for h in self.hosts.values() for a, s in h.slots.items() if s.state != "wait_finish"}
            raise RuntimeError(f"the simulated job stopped with agents in states {stuck}, the coordinator in phase "
                               f"{self.core.phase!r} (a bug)")
        return t_setup if t_setup is not None else time.perf_counter() - t0

    def _deliver_now(self) -> bool:
        """Deliver every message that arrives at the current virtual time (at least one, advancing the clock
        if none does); False when nothing is in flight or pending."""
        item = self.net.next()
        if item is None:
            return False
        clock = self.net.clock
        while item is not None:
            self._deliver(*item)
            if self.core.done or not self.net.peek_now(clock):
                break
            item = self.net.next()
        return True

    def _deliver(self, p: int, dst: int, msg: dict) -> None:
        if p == COORDINATOR:
            lost = msg["kind"] == LOST
            if lost or self.coord.accept(dst, msg):
                try:
                    if lost:
                        self.core.processes_lost([msg["src"]])
                    else:
                        self.core.handle(msg)
                finally:
                    self.flush()
            return
        host = self.hosts.get(p)
        if host is None or not self.net.endpoint(p).accept(dst, msg):
            return
        if msg["src"] == COORDINATOR:
            self._at(p, host.control, msg)
        else:
            self._at(p, host.deliver, dst, msg)

    def finish(self) -> Tuple[np.ndarray, np.ndarray]:
        """The job's labels; ``finish`` to every process."""
        try:
            ids, labels = self.core.result()
        finally:
            self.flush()
        while True:
            item = self.net.next()
            if item is None:
                break
            self._deliver(*item)
        return ids, labels


def simulate(descriptors, image_ids, config: DQMConfig, progress=None, catalog: bool = False,
             features: Optional[io.FeatureSet] = None, faults: Optional[FaultPlan] = None,
             max_lost: Optional[int] = None, recovery: str = "takeover") -> DQMResult:
    """Run Distributed QuickMatch for ``config.agents`` agents in this process.

    Agent a starts with the features of its images (:func:`dqm.distributed.sources.image_owners`),
    named on the wire as the runtime names them (:func:`dqm.distributed.sources.agent_features`).
    Every agent is an :class:`~dqm.distributed.driver.AgentDriver`, the runtime's driver, fed from an
    in-memory queue. ``progress``: a callable ``(done, total)`` called as the agents pass their
    states. ``catalog``: also meter the ``catalog`` messages that a runtime job writing a CLUSTERS
    file sends with its results; ``features``: the FEATURES set the descriptors and image ids come
    from, whose keypoints, image names and ground truth then travel in the catalogs as they do at the
    runtime's agents. ``faults``: what the network does wrong (:class:`~dqm.distributed.network.FaultPlan`:
    dropped, duplicated or delayed messages, lost processes), ``max_lost``: how many processes the
    coordinator may lose (default: half), ``recovery``: how a loss while the job runs is recovered
    (:data:`dqm.distributed.coordination.RECOVERY`). With faults the labels are those of the fault-free
    run, and the traffic includes what the faults cost (resends, acks, replays, restarted epochs).
    """
    t_all = time.perf_counter()
    X = check_descriptors(descriptors, keep_integer=True)
    ids = check_image_ids(image_ids, len(X))
    check_magnitude(X)  # agents cannot agree on a rescaling: refused as each agent refuses its own
    n = len(X)
    if n == 0:
        raise InputError("no features to match (empty input)")
    cfg = config.validated(n)
    m = cfg.agents
    dim = X.shape[1]
    # features travel as uint8 (SIFT) or float32: every agent computes on what it receives
    store = protocol.wire_descriptors(X)
    owners = image_owners(ids, m)
    if features is not None and len(features) != n:
        raise InputError(f"features has {len(features)} rows, the descriptors {n}: pass the set they come from")
    whole = io.FeatureSet(store, ids) if features is None else features
    held = [agent_features([part], a) for a, part in enumerate(split_features(whole, m))]
    net = MemoryNetwork(cfg.job, m, dim, faults)
    job = _Job(cfg, held, net, catalog, max_lost, recovery)
    stats: Dict[str, float] = {"time_setup": job.run(progress)}
    drivers = job.drivers()
    results = [(job.core.results[a]["ids"], job.core.results[a]["labels"]) for a in range(m)]
    res = (_balanced_outcome if cfg.mode == "balanced" else _cascade_outcome)(drivers, results, n)
    job.finish()
    cells = np.zeros(n, np.int64)
    for d in drivers:
        cells[(d.core.own if cfg.mode == "balanced" else d.core.shard).ids] = d.me
    source = drivers[0].source
    res.update(cells=cells, owners=owners, sites=source.seeds, weights=source.weights, config=drivers[0].cfg,
               traffic=net.meter)
    per_agent = [dict(d.core_stats) for d in drivers]
    for a in range(m):
        per_agent[a]["cpu_s"] = float(job.clock.cpu[a])
    raw = n * dim * store.dtype.itemsize
    central_pairs = max(1, n * (n - 1) // 2)
    stats.update(res.pop("stats"))
    stats.update(
        time_total=time.perf_counter() - t_all,
        routed_moves=float(net.features_moved["route"]),
        transfers_per_feature=sum(net.features_moved.values()) / n,
        max_features_share=max(p["held_peak"] for p in per_agent) / n,
        max_pair_share=max(p["pairs"] for p in per_agent) / central_pairs,
        bytes_over_raw=net.meter.total() / raw,
        busiest_cpu_s=float(job.clock.cpu.max()),
        largest_cell_share=float(np.bincount(cells, minlength=m).max() * m / n),
    )
    if cfg.mode != "balanced":
        stats["handdown_moves"] = float(net.features_moved["handdown"])
    return DQMResult(per_agent=per_agent, stats=stats, lost=job.core.lost, epochs=job.core.runs, **res)


def _holder(results: List[Tuple[np.ndarray, np.ndarray]], n: int) -> np.ndarray:
    holder = np.full(n, -1, np.int64)
    for a, (ids, _) in enumerate(results):
        holder[ids] = a
    if (holder < 0).any():
        raise RuntimeError("the distributed job lost features (a bug): some feature has no final cluster")
    return holder


def _balanced_outcome(drivers: List[AgentDriver], results, n: int) -> dict:
    """What the simulator reports of a balanced job beyond the labels, read from the agents' cores."""
    cores: List[BalancedCore] = [d.core for d in drivers]
    density, parent, pdist = np.full(n, np.nan), np.full(n, -1, np.int64), np.full(n, np.inf)
    for c in cores:
        own = c.own.ids
        density[own], parent[own], pdist[own] = c.density, c.parent, c.pdist
    per_agent = [d.core_stats for d in drivers]
    copies = [np.stack([c.own.ids[idx], np.full(len(idx), b)], axis=1) for c in cores for b, idx in c.shipped.items()]
    copies = np.concatenate(copies) if copies else np.zeros((0, 2), np.int64)
    return {
        "labels": assemble_labels(results)[1], "holder": _holder(results, n), "copies": copies,
        "density": density, "parent": parent, "parent_distance": pdist,
        "stats": {
            "ghosts_per_feature": sum(p.get("ghosts_sent", 0.0) for p in per_agent) / n,
            "ghosts_geometric_per_feature": sum(p.get("ghosts_geometric", 0.0) for p in per_agent) / n,
            "sketches_per_feature": sum(p.get("sketches_sent", 0.0) for p in per_agent) / n,
            "handed_per_feature": sum(p.get("features_handed", 0.0) for p in per_agent) / n,
            "arrival_check_failures": float(sum(c.failures for c in cores)),
        },
    }


def _cascade_outcome(drivers: List[AgentDriver], results, n: int) -> dict:
    """What the simulator reports of a lean / paper job beyond the labels: the first local clusters,
    the initially contested features and where each feature was first handed down."""
    m = len(drivers)
    initial_labels = np.zeros(n, np.int64)
    contested0 = np.zeros(n, bool)
    offset = 0
    for d in drivers:
        c = d.core
        if c.first is not None:
            initial_labels[c.shard.ids] = c.first.labels + offset
            offset += c.first.n_clusters
            contested0[c.shard.ids] = d.contested_initial
    handed_to = np.full(n, -1, np.int64)
    for a in range(m - 1, -1, -1):
        for b, ids in sorted(drivers[a].handed.items()):
            first_time = handed_to[ids] < 0
            handed_to[ids[first_time]] = b
    ids, labels = assemble_labels(results)
    assert np.array_equal(ids, np.arange(n))
    return {
        "labels": labels, "holder": _holder(results, n),
        "initial_labels": initial_labels, "contested": contested0, "handed_to": handed_to,
        "stats": {
            "contested_features": float(contested0.sum()),
            "arrival_check_failures": float(sum(d.core_stats.get("arrival_check_failures", 0.0) for d in drivers)),
            "ghosts_per_feature": 0.0,
        },
    }
