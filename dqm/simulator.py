"""In-process simulator of Distributed QuickMatch: all agents' steps in one process.

It runs the same core functions as the zenoh runtime (dqm.core.distributed,
partition, boundary, contested) in the same order, and meters what would cross
the network by encoding every message with dqm.messages exactly as the runtime
does. It is the reference the runtime is tested against.

Agents start with the features of their own images (image k of the sorted
image ids belongs to agent k mod m), so routing is real traffic.
"""
from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import numpy as np

from . import messages, protocol
from .core import distributed as dist
from .core.distributed import DQMConfig
from .core import partition
from .core.tree import canonical_labels
from .validation import InputError, check_descriptors, check_image_ids

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
    """Outcome of a distributed job: global labels plus everything needed for tables and pictures."""

    labels: np.ndarray  # (n,) canonical cluster labels
    holder: np.ndarray  # (n,) agent holding each feature at the end
    cells: np.ndarray  # (n,) routing cell of each feature
    owners: np.ndarray  # (n,) source agent of each feature
    seeds: np.ndarray
    config: DQMConfig
    traffic: Traffic
    stats: Dict[str, float] = field(default_factory=dict)
    per_agent: List[Dict[str, float]] = field(default_factory=list)
    initial_labels: Optional[np.ndarray] = None  # (n,) local cluster labels after step 3 (agent-prefixed)
    contested: Optional[np.ndarray] = None  # (n,) contested in the initial test
    handed_to: Optional[np.ndarray] = None  # (n,) first hand-down target (-1 = kept)

    @property
    def n_clusters(self) -> int:
        return int(self.labels.max() + 1) if len(self.labels) else 0


def image_owners(image_ids: np.ndarray, m: int) -> np.ndarray:
    """Source agent of every feature: image k (in sorted order of ids) belongs to agent k mod m."""
    _, inv = np.unique(image_ids, return_inverse=True)
    return (inv.ravel() % m).astype(np.int64)


def _send_features(traffic: Traffic, cfg: "DQMConfig", src: int, dst: int, phase: str, shard: dist.Shard,
                   units: np.ndarray, seqs: Dict[Tuple[int, int], int]) -> int:
    """Meter the features chunks of one (src, dst, phase) and their acks; returns the chunk count."""
    seq0 = seqs.get((src, dst), 0)
    msgs = protocol.feature_messages(cfg.job, src, phase, shard.ids, shard.image_ids, shard.descriptors,
                                     shard.sigma, units, seq0=seq0)
    for k, msg in enumerate(msgs):
        traffic.add(src, dst, "features", msg)
        traffic.add(dst, src, "ack", protocol.ack(cfg.job, dst, src, seq0 + k))
    seqs[(src, dst)] = seq0 + len(msgs)
    return len(msgs)


def simulate(descriptors, image_ids, config: DQMConfig, progress=None) -> DQMResult:
    """Run Distributed QuickMatch for ``config.agents`` agents in this process."""
    t_all = time.perf_counter()
    X = check_descriptors(descriptors)
    ids = check_image_ids(image_ids, len(X))
    n = len(X)
    if n == 0:
        raise InputError("no features to match (empty input)")
    cfg = config.validated(n)
    m = cfg.agents
    dim = X.shape[1]
    # features travel as uint8 (SIFT) or float32: every agent computes on what it receives
    store = protocol.wire_descriptors(np.asarray(descriptors) if np.asarray(descriptors).dtype == np.uint8 else X)
    X = store.astype(np.float64)
    owners = image_owners(ids, m)
    traffic = Traffic()
    gid = np.arange(n, dtype=np.int64)
    stats: Dict[str, float] = {}

    # 0. the coordinator broadcasts the seed integer
    for a in range(m):
        traffic.add(COORDINATOR, a, "start",
                    messages.encode("start", cfg.job, COORDINATOR, seed=cfg.seed, agents=m, mode=cfg.partition))

    # 1. partition seeds
    t = time.perf_counter()
    if cfg.partition == "seeded":
        seeds = partition.seeded_seeds(cfg.seed, m, dim, norm=cfg.seed_norm)
    else:
        samples = []
        for a in range(m):
            own = np.flatnonzero(owners == a)
            pick = own[partition.sample_for_seeds(X[own], gid[own], cfg.seed, cfg.samples_per_agent)]
            samples.append(pick)
            if a != 0:
                traffic.add(a, 0, "sample", messages.encode("sample", cfg.job, a, descriptors=store[pick]))
        pooled = np.concatenate(samples)
        seeds = partition.kmeans_seeds(X[pooled], m, cfg.seed)
        for b in range(1, m):
            traffic.add(0, b, "seeds", messages.encode("seeds", cfg.job, 0, seeds=seeds))
    stats["time_seeds"] = time.perf_counter() - t

    # 2. routing (default mode: exact sigma computed at the source, sent along)
    cores = [dist.AgentCore(a, cfg) for a in range(m)]
    cells = partition.route(X, seeds)
    parts_for: List[List[dist.Shard]] = [[] for _ in range(m)]
    seqs: Dict[Tuple[int, int], int] = {}
    for a in range(m):
        own = np.flatnonzero(owners == a)
        for b, sh in cores[a].route(gid[own], ids[own], store[own], seeds).items():
            if a != b:
                k = _send_features(traffic, cfg, a, b, "route", sh, np.full(len(sh), -1), seqs)
                traffic.add(a, b, "phase_end", protocol.phase_end(cfg.job, a, b, "route", k, len(sh)))
                traffic.features_moved += len(sh)
            parts_for[b].append(sh)
    routed_moves = traffic.features_moved

    # 3. local clustering, 4. boundary distances and exchanged minima
    minima = np.full((m, m), np.inf)
    for a in range(m):
        cores[a].set_shard(parts_for[a], seeds)
        minima[a] = cores[a].local_step()
        for b in range(m):
            if b != a:
                traffic.add(a, b, "minima", messages.encode("minima", cfg.job, a, values=minima[a]))
        if progress:
            progress(a + 1, 2 * m)
    per_agent = [{"features_routed": float(len(c.shard))} for c in cores]
    initial_labels = np.zeros(n, np.int64)
    contested0 = np.zeros(n, bool)
    offset = 0
    for c in cores:
        c.set_minima(minima)
        if c.first is not None:
            initial_labels[c.shard.ids] = c.first.labels + offset
            offset += c.first.n_clusters
            contested0[c.shard.ids] = c.contested_now()

    # 5. hand-down cascade m-1 .. 0, final re-clustering
    inbox: List[List[Tuple[int, dist.Shard, np.ndarray]]] = [[] for _ in range(m)]
    moves: Dict[int, np.ndarray] = {}
    holder = np.full(n, -1, np.int64)
    handed_to = np.full(n, -1, np.int64)
    final_labels = np.full(n, -1, np.int64)
    label_offset = 0
    arrival_failures = 0
    for a in range(m - 1, -1, -1):
        out = cores[a].cascade(inbox[a], moves)
        arrival_failures += out.arrival_failures
        sent = {}
        for b, (sh, units) in out.sends.items():
            sent[b] = _send_features(traffic, cfg, a, b, "handdown", sh, units, seqs)
            traffic.features_moved += len(sh)
            inbox[b].append((a, sh, units))
            first_time = handed_to[sh.ids] < 0
            handed_to[sh.ids[first_time]] = b
        moves[a] = out.moved
        for b in range(a):
            traffic.add(a, b, "phase_end", protocol.phase_end(
                cfg.job, a, b, "handdown", sent.get(b, 0), len(out.sends[b][0]) if b in out.sends else 0,
                out.moved))
        cur, res = out.final, out.final_result
        per_agent[a].update(features_final=float(len(cur)), time_cluster=cores[a].time_cluster,
                            time_boundary=cores[a].time_boundary)
        if len(cur):
            holder[cur.ids] = a
            final_labels[cur.ids] = res.labels + label_offset
            label_offset += res.n_clusters
            traffic.add(a, COORDINATOR, "result", messages.encode("result", cfg.job, a, ids=cur.ids,
                                                                   labels=res.labels.astype(np.int64)))
        if progress:
            progress(2 * m - a, 2 * m)

    assert (holder >= 0).all() and (final_labels >= 0).all()
    stats.update(
        time_total=time.perf_counter() - t_all,
        routed_moves=float(routed_moves),
        handdown_moves=float(traffic.features_moved - routed_moves),
        transfers_per_feature=traffic.features_moved / n,
        contested_features=float(contested0.sum()),
        arrival_check_failures=float(arrival_failures),
    )
    return DQMResult(
        labels=canonical_labels(final_labels), holder=holder, cells=cells, owners=owners, seeds=seeds,
        config=cfg, traffic=traffic, stats=stats, per_agent=per_agent, initial_labels=initial_labels,
        contested=contested0, handed_to=handed_to,
    )

