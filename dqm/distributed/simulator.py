"""In-process simulator of Distributed QuickMatch: all agents' steps in one process.

It runs the same code as the zenoh runtime (dqm.distributed: seeding,
cascade, balanced) in the same order, and meters what would cross the network
by encoding every message with dqm.distributed.protocol / messages exactly as
the runtime does (and decoding it again, so the codec is on the path). It is
the reference the runtime is tested against.

Agents start with the features of their own images (image k of the sorted
image ids belongs to agent k mod m), so routing is real traffic.
"""
from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np

from ..validation import InputError, check_descriptors, check_image_ids, check_magnitude
from .. import io
from . import cascade, keys, messages, protocol, seeding
from .balanced import ROUNDS, BalancedCore
from .config import DQMConfig, params_hash
from .shard import Shard
from .sources import agent_features, assemble_labels, image_owners, split_features

COORDINATOR = -1


class Traffic:
    """Bytes and messages per directed link and per message kind."""

    def __init__(self):
        self.bytes: Dict[Tuple[int, int, str], int] = defaultdict(int)
        self.count: Dict[Tuple[int, int, str], int] = defaultdict(int)
        self.features_moved = 0

    def add(self, src: int, dst: int, kind: str, payload: bytes, key_bytes: int = 0) -> None:
        self.bytes[(src, dst, kind)] += len(payload) + key_bytes
        self.count[(src, dst, kind)] += 1

    def total(self, kind: Optional[str] = None) -> int:
        return sum(v for (s, d, k), v in self.bytes.items() if kind is None or k == kind)

    def messages(self, kind: Optional[str] = None) -> int:
        return sum(v for (s, d, k), v in self.count.items() if kind is None or k == kind)

    def per_link(self) -> Dict[Tuple[int, int], int]:
        out: Dict[Tuple[int, int], int] = defaultdict(int)
        for (s, d, _), v in self.bytes.items():
            out[(s, d)] += v
        return dict(out)

    def per_kind(self) -> Dict[str, Tuple[int, int]]:
        out: Dict[str, List[int]] = defaultdict(lambda: [0, 0])
        for (s, d, k), v in self.bytes.items():
            out[k][0] += v
            out[k][1] += self.count[(s, d, k)]
        return {k: (v[0], v[1]) for k, v in out.items()}

    def as_json(self) -> dict:
        name = lambda i: "coordinator" if i == COORDINATOR else f"agent{i}"  # noqa: E731
        return {
            "links": [{"src": name(s), "dst": name(d), "kind": k, "bytes": v, "messages": self.count[(s, d, k)]}
                      for (s, d, k), v in sorted(self.bytes.items())],
            "total_bytes": self.total(), "total_messages": self.messages(),
        }

    def report(self) -> dict:
        """Per-link and per-kind totals in the runtime report's shape (dqm.protocol.traffic_table)."""
        name = lambda i: "coordinator" if i == COORDINATOR else f"agent{i}"  # noqa: E731
        links: Dict[Tuple[int, int], List[int]] = defaultdict(lambda: [0, 0])
        for (s, d, k), v in self.bytes.items():
            links[(s, d)][0] += v
            links[(s, d)][1] += self.count[(s, d, k)]
        return {
            "links": [{"src": name(s), "dst": name(d), "bytes": b, "messages": c}
                      for (s, d), (b, c) in sorted(links.items())],
            "kinds": {k: {"bytes": b, "messages": c} for k, (b, c) in sorted(self.per_kind().items())},
            "total_bytes": self.total(),
        }

    def table(self) -> str:
        return protocol.traffic_table(self.report())


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
    seeds: np.ndarray
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


class _Wire:
    """Meters every message the runtime would send and hands the receiver the decoded payload."""

    def __init__(self, traffic: Traffic, job: str, m: int, dim: int):
        self.traffic = traffic
        self.keys = {dst: len(keys.coordinator_inbox(job) if dst < 0 else keys.agent_inbox(job, dst))
                     for dst in range(-1, m)}
        self.job = job
        self.m = m
        self.dim = dim
        self.seqs: Dict[Tuple[int, int], int] = defaultdict(int)

    def add(self, src: int, dst: int, kind: str, payload: bytes) -> None:
        """Meter one message as the runtime does: payload plus the key it is put on."""
        self.traffic.add(src, dst, kind, payload, key_bytes=self.keys[dst])

    def _decode(self, payload: bytes) -> dict:
        return messages.decode(payload, job=self.job, n_agents=self.m, dim=self.dim)

    def _next(self, src: int, dst: int) -> int:
        seq = self.seqs[(src, dst)]
        self.seqs[(src, dst)] = seq + 1
        return seq

    def single(self, kind: str, src: int, dst: int, **fields) -> dict:
        payload = messages.encode(kind, self.job, src, seq=self._next(src, dst), **fields)
        self.add(src, dst, kind, payload)
        return self._decode(payload)

    def phase_end(self, src: int, dst: int, phase: str, n_messages: int, n_features: int,
                  moved: Optional[np.ndarray] = None) -> None:
        self.add(src, dst, "phase_end", protocol.phase_end(self.job, src, dst, phase, n_messages, n_features, moved,
                                                           seq=self._next(src, dst)))

    def _numbered(self, src: int, dst: int, kind: str, build: Callable[[int], List[bytes]]) -> List[bytes]:
        """Messages numbered on the (src, dst) link from its next sequence number, each with its ack."""
        seq0 = self.seqs[(src, dst)]
        msgs = build(seq0)
        for k, msg in enumerate(msgs):
            self.add(src, dst, kind, msg)
            self.add(dst, src, "ack", protocol.ack(self.job, dst, src, seq0 + k))
        self.seqs[(src, dst)] = seq0 + len(msgs)
        return msgs

    def parts(self, kind: str, src: int, dst: int, payload: dict) -> dict:
        msgs = self._numbered(src, dst, kind,
                              lambda seq0: protocol.data_messages(kind, self.job, src, payload, seq0=seq0))
        return protocol.merge_parts(kind, [self._decode(m) for m in msgs])

    def features(self, src: int, dst: int, phase: str, shard: Shard, units: Optional[np.ndarray],
                 moved: Optional[np.ndarray] = None) -> None:
        """The features chunks of one (src, dst, phase), their acks and the phase end."""
        msgs = self._numbered(src, dst, "features", lambda seq0: protocol.feature_messages(
            self.job, src, phase, shard.ids, shard.image_ids, shard.descriptors, shard.sigma, units, seq0=seq0))
        self.phase_end(src, dst, phase, len(msgs), len(shard), moved)
        self.traffic.features_moved += len(shard)


class _Clock:
    """CPU seconds per agent (the simulator runs agents one after another, so process time is theirs)."""

    def __init__(self, m: int):
        self.cpu = np.zeros(m)

    def run(self, a: int, fn: Callable, *args, **kwargs):
        t = time.process_time()
        out = fn(*args, **kwargs)
        self.cpu[a] += time.process_time() - t
        return out


def _setup(wire: _Wire, clock: _Clock, cfg: DQMConfig, sources: List[seeding.SourceSide], dim: int) -> None:
    """Seeds, weights, sketch basis and sigma fill, as dqm.distributed.seeding describes."""
    m = cfg.agents
    leader = seeding.Leader(cfg, dim)
    samples = {}
    for a in range(m):
        p = clock.run(a, sources[a].sample_payload)
        samples[a] = p if a == seeding.LEADER else wire.single("sample", a, seeding.LEADER, **p)
    seeds = clock.run(seeding.LEADER, leader.seeds_payload, samples)
    for a in range(m):
        got = seeds if a == seeding.LEADER else wire.single("seeds", seeding.LEADER, a, **seeds)
        sources[a].on_seeds(got)
    if seeds["fill"]:
        sig = {a: (sources[a].sigmas_payload() if a == seeding.LEADER else
                   wire.parts("sigmas", a, seeding.LEADER, sources[a].sigmas_payload())) for a in range(m)}
        value = leader.fill_value(sig)
        for a in range(m):
            got = value if a == seeding.LEADER else wire.single("fill", seeding.LEADER, a, value=value)["value"]
            sources[a].on_fill(got)
    while not sources[0].final:
        counts = {a: (clock.run(a, sources[a].counts_payload) if a == seeding.LEADER else
                      wire.single("counts", a, seeding.LEADER, **clock.run(a, sources[a].counts_payload)))
                  for a in range(m)}
        w = clock.run(seeding.LEADER, leader.weights_payload, counts)
        for a in range(m):
            sources[a].on_weights(w if a == seeding.LEADER else wire.single("weights", seeding.LEADER, a, **w))


def simulate(descriptors, image_ids, config: DQMConfig, progress=None, catalog: bool = False,
             features: Optional[io.FeatureSet] = None) -> DQMResult:
    """Run Distributed QuickMatch for ``config.agents`` agents in this process.

    Agent a starts with the features of its images (:func:`dqm.distributed.sources.image_owners`),
    named on the wire as the runtime names them (:func:`dqm.distributed.sources.agent_features`).
    ``progress``: a callable ``(done, total)`` called after each protocol step. ``catalog``: also
    meter the ``catalog`` messages that a runtime job writing a CLUSTERS file sends with its results;
    ``features``: the FEATURES set the descriptors and image ids come from, whose keypoints, image
    names and ground truth then travel in the catalogs as they do at the runtime's agents.
    """
    t_all = time.perf_counter()
    X = check_descriptors(descriptors)
    ids = check_image_ids(image_ids, len(X))
    check_magnitude(X)  # agents cannot agree on a rescaling: refused as each agent refuses its own
    n = len(X)
    if n == 0:
        raise InputError("no features to match (empty input)")
    cfg = config.validated(n)
    m = cfg.agents
    dim = X.shape[1]
    # features travel as uint8 (SIFT) or float32: every agent computes on what it receives
    store = protocol.wire_descriptors(np.asarray(descriptors) if np.asarray(descriptors).dtype == np.uint8 else X)
    owners = image_owners(ids, m)
    if features is not None and len(features) != n:
        raise InputError(f"features has {len(features)} rows, the descriptors {n}: pass the set they come from")
    whole = io.FeatureSet(store, ids) if features is None else features
    held = [agent_features([part], a) for a, part in enumerate(split_features(whole, m))]
    traffic = Traffic()
    wire = _Wire(traffic, cfg.job, m, dim)
    clock = _Clock(m)

    # the coordinator broadcasts the seed integer (and the parameters every agent checks); every agent
    # answers ready; the coordinator says go
    text = cfg.params_text()
    for a in range(m):
        wire.single("start", COORDINATOR, a, seed=cfg.seed, agents=m, owners=np.arange(m, dtype=np.int64),
                    params=text, params_hash=params_hash(text), catalog=int(catalog))
    for a in range(m):
        wire.single("ready", a, COORDINATOR, dim=dim, dtype=store.dtype.str, hosted=np.array([a], np.int64),
                    features=int((owners == a).sum()))
    for a in range(m):
        wire.single("go", COORDINATOR, a)
    sources = [clock.run(a, seeding.SourceSide, a, cfg, h.ids, h.image_ids, h.descriptors) for a, h in enumerate(held)]
    t = time.perf_counter()
    _setup(wire, clock, cfg, sources, dim)
    seeds, weights = sources[0].seeds, sources[0].weights
    stats: Dict[str, float] = {"time_setup": time.perf_counter() - t}

    # routing
    parts_for: List[List[Shard]] = [[] for _ in range(m)]
    for a in range(m):
        for b, sh in clock.run(a, sources[a].route).items():
            if a != b:
                wire.features(a, b, "route", sh, None)
            parts_for[b].append(sh)
    routed = traffic.features_moved
    cells = np.zeros(n, np.int64)
    for b in range(m):
        for sh in parts_for[b]:
            cells[sh.ids] = b

    run = _run_balanced if cfg.mode == "balanced" else _run_cascade
    res = run(cfg, wire, clock, sources, parts_for, seeds, weights, n, progress)
    if catalog:  # what the CLUSTERS file needs of each agent's own features, with its result
        for a, h in enumerate(held):
            wire.parts("catalog", a, COORDINATOR, h.catalog)
    n_clusters = int(res["labels"].max()) + 1
    for a in range(m):  # the coordinator's end of job (the agents' own stats reports are not metered)
        wire.single("finish", COORDINATOR, a, clusters=n_clusters)
    res.update(cells=cells, owners=owners, seeds=seeds, weights=weights, config=cfg, traffic=traffic)
    per_agent = res.pop("per_agent")
    for a in range(m):
        per_agent[a]["cpu_s"] = float(clock.cpu[a])
    raw = n * dim * store.dtype.itemsize
    central_pairs = max(1, n * (n - 1) // 2)
    stats.update(res.pop("stats"))
    stats.update(
        time_total=time.perf_counter() - t_all,
        routed_moves=float(routed),
        transfers_per_feature=traffic.features_moved / n,
        max_features_share=max(p["max_held"] for p in per_agent) / n,
        max_pair_share=max(p["pairs"] for p in per_agent) / central_pairs,
        bytes_over_raw=traffic.total() / raw,
        busiest_cpu_s=float(clock.cpu.max()),
        largest_cell_share=float(np.bincount(cells, minlength=m).max() * m / n),
    )
    return DQMResult(per_agent=per_agent, stats=stats, **res)


def _run_balanced(cfg, wire, clock, sources, parts_for, seeds, weights, n, progress) -> dict:
    m = cfg.agents
    cores = [BalancedCore(a, cfg, sources[a].sketch_space()) for a in range(m)]
    for a in range(m):
        cores[a].set_shard(parts_for[a], seeds, weights)
    inbox: List[Dict[int, dict]] = [{} for _ in range(m)]
    for r, name in enumerate(ROUNDS):
        outs = [cores[a].step(inbox[a]) for a in range(m)]
        inbox = [{} for _ in range(m)]
        for a in range(m):
            for b, payload in outs[a].items():
                inbox[b][a] = wire.parts(name, a, b, payload)
        if progress:
            progress(r + 1, len(ROUNDS) + 1)
    holder = np.full(n, -1, np.int64)
    results = []
    density, parent, pdist = np.full(n, np.nan), np.full(n, -1, np.int64), np.full(n, np.inf)
    for a in range(m):
        ids, lab = cores[a].finish(inbox[a])
        wire.single("result", a, COORDINATOR, ids=ids, labels=lab)
        holder[ids] = a
        results.append((ids, lab))
        own = cores[a].own.ids
        density[own], parent[own], pdist[own] = cores[a].density, cores[a].parent, cores[a].pdist
        clock.cpu[a] += cores[a].cpu
    if progress:
        progress(len(ROUNDS) + 1, len(ROUNDS) + 1)
    if (holder < 0).any():
        raise RuntimeError("balanced mode lost features (a bug): some feature has no final cluster")
    per_agent = [dict(cores[a].stats) for a in range(m)]
    ghosts = sum(p.get("ghosts_sent", 0.0) for p in per_agent)
    copies = [np.stack([c.own.ids[idx], np.full(len(idx), b)], axis=1) for c in cores for b, idx in c.shipped.items()]
    copies = np.concatenate(copies) if copies else np.zeros((0, 2), np.int64)
    return {
        "labels": assemble_labels(results)[1], "holder": holder, "per_agent": per_agent, "copies": copies,
        "density": density, "parent": parent, "parent_distance": pdist,
        "stats": {
            "ghosts_per_feature": ghosts / n,
            "ghosts_geometric_per_feature": sum(p.get("ghosts_geometric", 0.0) for p in per_agent) / n,
            "sketches_per_feature": sum(p.get("sketches_sent", 0.0) for p in per_agent) / n,
            "handed_per_feature": sum(p.get("features_handed", 0.0) for p in per_agent) / n,
            "arrival_check_failures": float(sum(c.failures for c in cores)),
        },
    }


def _run_cascade(cfg, wire, clock, sources, parts_for, seeds, weights, n, progress) -> dict:
    m = cfg.agents
    cores = [cascade.CascadeCore(a, cfg) for a in range(m)]
    # local clustering, boundary distances and exchanged minima
    minima = np.full((m, m), np.inf)
    for a in range(m):
        cores[a].set_shard(parts_for[a], seeds, weights)
        minima[a] = clock.run(a, cores[a].local_step)
        for b in range(m):
            if b != a:
                wire.single("minima", a, b, values=minima[a])
        if progress:
            progress(a + 1, 2 * m)
    initial_labels = np.zeros(n, np.int64)
    contested0 = np.zeros(n, bool)
    offset = 0
    for c in cores:
        c.set_minima(minima)
        if c.first is not None:
            initial_labels[c.shard.ids] = c.first.labels + offset
            offset += c.first.n_clusters
            contested0[c.shard.ids] = c.contested_now()
    # hand-down cascade m-1 .. 0, final re-clustering
    inbox: List[List[Tuple[int, Shard, np.ndarray]]] = [[] for _ in range(m)]
    moves: Dict[int, np.ndarray] = {}
    holder = np.full(n, -1, np.int64)
    handed_to = np.full(n, -1, np.int64)
    results = []
    failures = 0
    routed = wire.traffic.features_moved
    for a in range(m - 1, -1, -1):
        out = clock.run(a, cores[a].cascade, inbox[a], moves)
        failures += out.arrival_failures
        for b in range(a):
            sh, units = out.sends.get(b, (None, None))
            if sh is not None:
                inbox[b].append((a, sh, units))
                first_time = handed_to[sh.ids] < 0
                handed_to[sh.ids[first_time]] = b
            else:
                sh, units = Shard.empty(0), np.zeros(0, np.int64)
            if len(sh):
                wire.features(a, b, "handdown", sh, units, out.moved)
            else:
                wire.phase_end(a, b, "handdown", 0, 0, out.moved)
        moves[a] = out.moved
        cur, res = out.final, out.final_result
        ids, lab = (cur.ids, res.labels.astype(np.int64)) if len(cur) else (np.zeros(0, np.int64),) * 2
        holder[ids] = a
        results.append((ids, lab))
        wire.single("result", a, COORDINATOR, ids=ids, labels=lab)
        if progress:
            progress(2 * m - a, 2 * m)
    ids, final_labels = assemble_labels(results)
    assert (holder >= 0).all() and np.array_equal(ids, np.arange(n))
    per_agent = [{"features_routed": float(len(c.shard)), "features_final": float((holder == c.me).sum()),
                  "time_cluster": c.time_cluster, "time_boundary": c.time_boundary,
                  "pairs": float(c.pairs_computed), "max_held": float(c.max_held)} for c in cores]
    return {
        "labels": final_labels, "holder": holder, "per_agent": per_agent,
        "initial_labels": initial_labels, "contested": contested0, "handed_to": handed_to,
        "stats": {
            "handdown_moves": float(wire.traffic.features_moved - routed),
            "contested_features": float(contested0.sum()),
            "arrival_check_failures": float(failures),
            "ghosts_per_feature": 0.0,
        },
    }
