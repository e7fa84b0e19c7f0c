"""In-process simulator of Distributed QuickMatch: all agents' steps in one process.

Every agent is the runtime's own driver (:class:`dqm.distributed.driver.AgentDriver`),
fed from an in-memory queue (:class:`dqm.distributed.driver.MemoryBus`) instead
of the zenoh bus: the same choreography, the same messages on every link, metered
by the same ledger (:mod:`dqm.distributed.ledger`), and decoded again so the codec
is on the path. It is the reference the runtime is tested against.

Agents start with the features of their own images (image k of the sorted
image ids belongs to agent k mod m), so routing is real traffic.
"""
from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np

from .. import io
from ..validation import InputError, check_descriptors, check_image_ids, check_magnitude
from . import protocol
from .balanced import BalancedCore
from .config import DQMConfig
from .driver import SETUP_STATES, AgentDriver, MemoryBus, ready_fields, start_fields
from .ledger import COORDINATOR, TrafficLedger
from .sources import agent_features, assemble_labels, image_owners, split_features

#: the simulator's name for the one traffic ledger (kept for callers of ``dqm.distributed.Traffic``)
Traffic = TrafficLedger


@dataclass
class DQMResult:
    """Outcome of a distributed job: global labels plus everything needed for tables and pictures.

    ``stats`` holds, among others, ``max_features_share`` (the most features any
    agent held at once, copies included, over n), ``max_pair_share`` (the
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

    @property
    def n_clusters(self) -> int:
        return int(self.labels.max() + 1) if len(self.labels) else 0

    @property
    def seeds(self) -> np.ndarray:
        """The cells' sites under their earlier name (``seed`` is the one integer they come from)."""
        return self.sites



class _Clock:
    """CPU seconds per agent (the simulator runs agents one after another, so process time is theirs)."""

    def __init__(self, m: int):
        self.cpu = np.zeros(m)

    def run(self, a: int, fn: Callable, *args, **kwargs):
        t = time.process_time()
        out = fn(*args, **kwargs)
        self.cpu[a] += time.process_time() - t
        return out


class _Coordinator:
    """The coordinator's side in memory: start, ready, go, then results and catalogs, then finish."""

    def __init__(self, bus: MemoryBus, cfg: DQMConfig, catalog: bool):
        self.bus = bus
        self.cfg = cfg
        self.catalog = catalog
        self.results: Dict[int, Tuple[np.ndarray, np.ndarray]] = {}
        self.catalog_parts: Dict[int, int] = defaultdict(int)

    def start(self, hosted: List[np.ndarray], dim_of: Callable[[int], np.ndarray]) -> None:
        m = self.cfg.agents
        fields = start_fields(self.cfg, np.arange(m, dtype=np.int64), self.catalog)
        for a in range(m):
            self.bus.send_single(COORDINATOR, a, "start", **fields)
        for a in range(m):
            self.bus.send_single(a, COORDINATOR, "ready", **ready_fields(dim_of(a), [a], len(hosted[a])))
        for a in range(m):
            self.bus.send_single(COORDINATOR, a, "go")

    def take(self, msg: dict) -> None:
        if msg["kind"] == "result":
            self.results[msg["src"]] = (msg["ids"], msg["labels"])

    def finish(self, n_clusters: int) -> None:
        for a in range(self.cfg.agents):  # the coordinator's end of job
            self.bus.send_single(COORDINATOR, a, "finish", clusters=n_clusters)


def _pump(drivers: List[AgentDriver], bus: MemoryBus, coord: _Coordinator, clock: _Clock,
          progress: Optional[Callable[[int, int], None]]) -> float:
    """Deliver queued messages and let every agent advance until the job is done; returns the wall
    seconds the set-up (up to routing) took."""
    t0 = time.perf_counter()
    t_setup = None
    routed = SETUP_STATES.index("wait_routed")
    total = len(drivers[0].states) - 1
    shown = -1
    while True:
        for a, d in enumerate(drivers):
            clock.run(a, d.settle)
        step = min(d.step_index for d in drivers)
        if t_setup is None and step >= routed:
            t_setup = time.perf_counter() - t0
        if progress and step > shown:
            shown = step
            progress(step, total)
        if not bus.queue:
            break
        while bus.queue:
            dst, msg = bus.queue.popleft()
            if dst == COORDINATOR:
                coord.take(msg)
            elif msg["src"] != COORDINATOR:  # start and go were played by the coordinator's side
                clock.run(dst, drivers[dst].handle, msg)
    stuck = [d.me for d in drivers if d.state != "wait_finish"]
    if stuck:
        raise RuntimeError(f"the simulated job stopped with agents {stuck} in state {drivers[stuck[0]].state!r} "
                           "(a bug)")
    return t_setup if t_setup is not None else time.perf_counter() - t0


def simulate(descriptors, image_ids, config: DQMConfig, progress=None, catalog: bool = False,
             features: Optional[io.FeatureSet] = None) -> DQMResult:
    """Run Distributed QuickMatch for ``config.agents`` agents in this process.

    Agent a starts with the features of its images (:func:`dqm.distributed.sources.image_owners`),
    named on the wire as the runtime names them (:func:`dqm.distributed.sources.agent_features`).
    Every agent is an :class:`~dqm.distributed.driver.AgentDriver`, the runtime's driver, fed from an
    in-memory queue. ``progress``: a callable ``(done, total)`` called as the agents pass their
    states. ``catalog``: also meter the ``catalog`` messages that a runtime job writing a CLUSTERS
    file sends with its results; ``features``: the FEATURES set the descriptors and image ids come
    from, whose keypoints, image names and ground truth then travel in the catalogs as they do at the
    runtime's agents.
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
    bus = MemoryBus(cfg.job, m, dim)
    clock = _Clock(m)
    coord = _Coordinator(bus, cfg, catalog)
    coord.start([h.ids for h in held], lambda a: held[a].descriptors)
    drivers = [clock.run(a, AgentDriver, a, cfg, bus, h.ids, h.image_ids, h.descriptors,
                         catalog=h.catalog if catalog else None, trace=True) for a, h in enumerate(held)]
    for d in drivers:
        d.begin(cfg.seed)
    stats: Dict[str, float] = {"time_setup": _pump(drivers, bus, coord, clock, progress)}

    results = [coord.results[a] for a in range(m)]
    res = (_balanced_outcome if cfg.mode == "balanced" else _cascade_outcome)(drivers, results, n)
    n_clusters = int(res["labels"].max()) + 1
    coord.finish(n_clusters)
    cells = np.zeros(n, np.int64)
    for d in drivers:
        cells[(d.core.own if cfg.mode == "balanced" else d.core.shard).ids] = d.me
    source = drivers[0].source
    res.update(cells=cells, owners=owners, sites=source.seeds, weights=source.weights, config=drivers[0].cfg,
               traffic=bus.meter)
    per_agent = [dict(d.core_stats) for d in drivers]
    for a in range(m):
        per_agent[a]["cpu_s"] = float(clock.cpu[a])
    raw = n * dim * store.dtype.itemsize
    central_pairs = max(1, n * (n - 1) // 2)
    stats.update(res.pop("stats"))
    stats.update(
        time_total=time.perf_counter() - t_all,
        routed_moves=float(bus.features_moved["route"]),
        transfers_per_feature=sum(bus.features_moved.values()) / n,
        max_features_share=max(p["max_held"] for p in per_agent) / n,
        max_pair_share=max(p["pairs"] for p in per_agent) / central_pairs,
        bytes_over_raw=bus.meter.total() / raw,
        busiest_cpu_s=float(clock.cpu.max()),
        largest_cell_share=float(np.bincount(cells, minlength=m).max() * m / n),
    )
    if cfg.mode != "balanced":
        stats["handdown_moves"] = float(bus.features_moved["handdown"])
    return DQMResult(per_agent=per_agent, stats=stats, **res)


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
