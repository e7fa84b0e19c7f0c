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

from . import messages
from .core import distributed as dist
from .core import partition
from .core.clustering import DEFAULT_RHO, KERNELS
from .core.tree import canonical_labels
from .validation import InputError, check_choice, check_descriptors, check_image_ids, check_positive

COORDINATOR = -1
#: feature rows per features message (bounded message size)
CHUNK_ROWS = 8192


@dataclass(frozen=True)
class DQMConfig:
    """Parameters of a distributed job (identical in the simulator and the runtime)."""

    agents: int
    seed: int = 0
    partition: str = "kmeans"
    mode: str = "default"
    rho: float = DEFAULT_RHO
    kernel: str = "quadratic"
    samples_per_agent: int = 64
    halo: float = 1.0
    job: str = "job"

    def validated(self, n_features: int) -> "DQMConfig":
        partition.check_agents(self.agents, n_features)
        partition.check_seed(self.seed)
        check_choice(self.partition, "partition", partition.PARTITION_MODES)
        check_choice(self.mode, "mode", dist.DQM_MODES)
        check_choice(self.kernel, "kernel", KERNELS)
        check_positive(self.rho, "rho")
        check_positive(self.halo, "halo")
        if not isinstance(self.samples_per_agent, int) or self.samples_per_agent < 1:
            raise InputError(f"samples_per_agent must be a positive integer, got {self.samples_per_agent!r}")
        return self


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

    def table(self) -> str:
        name = lambda i: "coord" if i == COORDINATOR else f"a{i}"  # noqa: E731
        lines = ["| link | bytes | messages |", "|---|---|---|"]
        links = defaultdict(lambda: [0, 0])
        for (s, d, k), v in self.bytes.items():
            links[(s, d)][0] += v
            links[(s, d)][1] += self.count[(s, d, k)]
        for (s, d), (b, c) in sorted(links.items()):
            lines.append(f"| {name(s)} -> {name(d)} | {b} | {c} |")
        lines.append(f"| total | {self.total()} | {self.messages()} |")
        lines.append("")
        lines.append("| kind | bytes | messages |")
        lines.append("|---|---|---|")
        for k, (b, c) in sorted(self.per_kind().items()):
            lines.append(f"| {k} | {b} | {c} |")
        return "\n".join(lines)


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


def _feature_messages(cfg: DQMConfig, src: int, shard: dist.Shard, units: np.ndarray, phase: str,
                      seq0: int) -> List[bytes]:
    out = []
    desc = shard.descriptors if shard.descriptors.dtype == np.uint8 else shard.descriptors.astype(np.float32)
    for k, s in enumerate(range(0, max(1, len(shard)), CHUNK_ROWS)):
        sl = slice(s, s + CHUNK_ROWS)
        out.append(messages.encode(
            "features", cfg.job, src, phase=phase, seq=seq0 + k, ids=shard.ids[sl].astype(np.int64),
            image_ids=shard.image_ids[sl].astype(np.int64), descriptors=np.ascontiguousarray(desc[sl]),
            sigma=shard.sigma[sl].astype(np.float64), unit=units[sl].astype(np.int64)))
    return out


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
    raw = np.asarray(descriptors)
    store = raw.astype(np.uint8) if raw.dtype == np.uint8 else X
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
        seeds = partition.seeded_seeds(cfg.seed, m, dim, norm=float(np.median(np.linalg.norm(X, axis=1))))
    else:
        samples = []
        for a in range(m):
            own = np.flatnonzero(owners == a)
            pick = own[partition.sample_for_seeds(X[own], gid[own], cfg.seed, cfg.samples_per_agent)]
            samples.append(pick)
            if a != 0:
                payload = store[pick] if store.dtype == np.uint8 else store[pick].astype(np.float32)
                traffic.add(a, 0, "sample", messages.encode("sample", cfg.job, a, descriptors=payload))
        pooled = np.concatenate(samples)
        seeds = partition.kmeans_seeds(X[pooled], m, cfg.seed)
        for b in range(1, m):
            traffic.add(0, b, "seeds", messages.encode("seeds", cfg.job, 0, seeds=seeds))
    stats["time_seeds"] = time.perf_counter() - t

    # 2. routing (default mode: exact sigma computed at the source, sent along)
    cells = partition.route(X, seeds)
    sigma0 = np.zeros(n)
    if cfg.mode == "default":
        for a in range(m):
            own = np.flatnonzero(owners == a)
            sigma0[own] = dist.source_sigma(X[own], ids[own])
    shards: List[dist.Shard] = []
    for b in range(m):
        parts = []
        for a in range(m):
            sel = np.flatnonzero((owners == a) & (cells == b))
            sh = dist.Shard(gid[sel], ids[sel], store[sel], sigma0[sel], cells[sel])
            if a != b:
                for k, msg in enumerate(_feature_messages(cfg, a, sh, np.full(len(sel), -1), "route", 0)):
                    traffic.add(a, b, "features", msg)
                    traffic.add(b, a, "ack", messages.encode("ack", cfg.job, b, seq=k, dst=a))
                traffic.add(a, b, "phase_end", messages.encode("phase_end", cfg.job, a, phase="route", dst=b,
                                                               messages=1, features=len(sel),
                                                               moved=np.zeros(0, np.int64)))
                traffic.features_moved += len(sel)
            parts.append(sh)
        shards.append(dist.Shard.concat(parts))
    routed_moves = traffic.features_moved

    # boundary distances depend only on a feature's descriptor and the seeds; an
    # agent keeps those it computed (for a reach at least as large as needed now)
    Hcache = np.zeros((n, m))
    Hreach = np.full(n, -1.0)

    def bounds(a: int, shard: dist.Shard, rch: np.ndarray) -> np.ndarray:
        todo = np.flatnonzero(Hreach[shard.ids] < rch)
        if len(todo):
            sub = shard.take(todo)
            H, tb = dist.timed(dist.boundary_distances, sub, seeds, cfg.mode, rch[todo])
            per_agent[a]["time_boundary"] = per_agent[a].get("time_boundary", 0.0) + tb
            Hcache[sub.ids] = H
            Hreach[sub.ids] = rch[todo]
        return Hcache[shard.ids]

    # 3. local clustering, 4. boundary distances and exchanged minima
    per_agent = [{"features_routed": float(len(s)), "time_boundary": 0.0} for s in shards]
    first: List[Optional[object]] = []
    minima = np.full((m, m), np.inf)
    H0, reach0 = [], []
    for a in range(m):
        (res, sig), tc = dist.timed(dist.cluster_shard, shards[a], cfg.mode, cfg.rho, cfg.kernel)
        if cfg.mode == "paper" and len(shards[a]):
            shards[a].sigma = sig
        rch = dist.reach(shards[a].sigma, cfg.mode, cfg.rho, cfg.halo)
        H = bounds(a, shards[a], rch)
        minima[a] = dist.minima_for_broadcast(H, a, m)
        per_agent[a]["time_cluster"] = tc
        first.append(res)
        H0.append(H)
        reach0.append(rch)
        for b in range(m):
            if b != a:
                traffic.add(a, b, "minima", messages.encode("minima", cfg.job, a, values=minima[a]))
        if progress:
            progress(a + 1, 2 * m)

    initial_labels = np.zeros(n, np.int64)
    contested0 = np.zeros(n, bool)
    offset = 0
    for a in range(m):
        if first[a] is not None:
            initial_labels[shards[a].ids] = first[a].labels + offset
            offset += first[a].n_clusters
            C = dist.contested_with(shards[a], H0[a], reach0[a], minima)
            contested0[shards[a].ids] = C.any(axis=1)

    # 5. hand-down cascade m-1 .. 0, final re-clustering
    inbox: List[List[Tuple[int, dist.Shard, np.ndarray]]] = [[] for _ in range(m)]
    location = np.eye(m, dtype=bool)  # location[k, b]: features of cell k are held by agent b
    location_at: Dict[int, np.ndarray] = {}  # the location map each sender decided with
    holder = np.full(n, -1, np.int64)
    handed_to = np.full(n, -1, np.int64)
    final_labels = np.full(n, -1, np.int64)
    label_offset = 0
    arrival_failures = 0
    for a in range(m - 1, -1, -1):
        received = [s for _, s, _ in inbox[a]]
        for sender, s_in, u_in in inbox[a]:  # arrival check of every received batch
            rch_in = dist.reach(s_in.sigma, cfg.mode, cfg.rho, cfg.halo)
            H_in = bounds(a, s_in, rch_in)
            C_in = dist.contested_with(s_in, H_in, rch_in, minima)
            arrival_failures += dist.arrival_check(u_in, C_in, a, sender, location_at[sender], cfg.mode)
        cur = dist.Shard.concat([shards[a]] + received) if received else shards[a]
        t = time.perf_counter()
        if received or a == m - 1:
            res, sig = dist.cluster_shard(cur, cfg.mode, cfg.rho, cfg.kernel)
        else:
            res, sig = first[a], cur.sigma
        if cfg.mode == "paper" and len(cur):
            cur.sigma = sig
        tc = time.perf_counter() - t
        keep = np.arange(len(cur))
        if a > 0 and len(cur):
            rch = dist.reach(cur.sigma, cfg.mode, cfg.rho, cfg.halo)
            H = bounds(a, cur, rch)
            C = dist.contested_with(cur, H, rch, minima)
            location_at[a] = location.copy()
            target, units = dist.hand_down(cur, res, C, a, cfg.mode, location)
            for b in np.unique(target[target != a]).tolist():
                sel = np.flatnonzero(target == b)
                sh = cur.take(sel)
                for k, msg in enumerate(_feature_messages(cfg, a, sh, units[sel], "handdown", 0)):
                    traffic.add(a, b, "features", msg)
                    traffic.add(b, a, "ack", messages.encode("ack", cfg.job, b, seq=k, dst=a))
                traffic.features_moved += len(sel)
                inbox[b].append((a, sh, units[sel]))
                first_time = handed_to[sh.ids] < 0
                handed_to[sh.ids[first_time]] = b
            moved = target != a
            dist.record_moves(location, cur.cells[moved], target[moved])
            pairs_moved = np.unique(np.stack([cur.cells[moved], target[moved]]), axis=1)
            for b in range(a):
                traffic.add(a, b, "phase_end", messages.encode(
                    "phase_end", cfg.job, a, phase="handdown", dst=b, messages=int((target == b).any()),
                    features=int((target == b).sum()), moved=pairs_moved.reshape(-1).astype(np.int64)))
            keep = np.flatnonzero(target == a)
            if len(keep) < len(cur):  # final re-clustering of what stays
                cur = cur.take(keep)
                t = time.perf_counter()
                res, _ = dist.cluster_shard(cur, "default" if cfg.mode == "default" else "paper",
                                            cfg.rho, cfg.kernel) if len(cur) else (None, None)
                tc += time.perf_counter() - t
        per_agent[a]["time_cluster"] += tc
        per_agent[a]["features_final"] = float(len(cur))
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

