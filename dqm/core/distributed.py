"""Distributed QuickMatch (Serlin et al.): the steps one agent runs on its own data.

Pure functions on a :class:`Shard` (the features an agent holds); no I/O. The
in-process simulator (dqm.simulator) and the zenoh runtime (dqm.runtime) call
exactly these, so they cannot drift apart.

Protocol (m agents, agent i owns Voronoi cell i of the seeds):

1. seeds from one integer (dqm.core.partition);
2. routing: every agent sends each of its source features to the agent of its
   cell. In the default mode the source agent, which holds whole images, first
   computes the exact distinctiveness sigma of its features and sends it along;
   the paper mode recomputes sigma inside each cell (``per-agent sigma``);
3. every agent clusters its cell with the finite (quadratic) kernel;
4. boundary distances: bisector distances of held features to all cells; the
   exchanged minima ``e[a, i]`` are broadcast (m - 1 scalars per agent);
5. hand-down cascade from agent m-1 to agent 0: agent a re-clusters what it
   holds plus what higher agents handed it, tests contested features against
   lower agents, hands every unit with a contested feature to the lowest such
   agent (the receiver checks on arrival that it is that agent), tells the
   lower agents which cells' features went where, and re-clusters the rest:
   its final clusters. Default mode adds the follow rule: a feature contested
   with a cell whose features were handed further down follows them.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import numpy as np

from . import boundary, contested, pairs
from .clustering import DEFAULT_RHO, QuickMatchResult, distinctiveness, quickmatch

DQM_MODES = ("default", "paper")


@dataclass
class Shard:
    """Features held by one agent: global ids, image ids, descriptors, sigma, cell, unit."""

    ids: np.ndarray
    image_ids: np.ndarray
    descriptors: np.ndarray
    sigma: np.ndarray
    cells: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)

    @classmethod
    def empty(cls, dim: int, dtype=np.uint8) -> "Shard":
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, dim), dtype),
                   np.zeros(0), np.zeros(0, np.int64))

    def take(self, idx: np.ndarray) -> "Shard":
        return Shard(self.ids[idx], self.image_ids[idx], self.descriptors[idx], self.sigma[idx], self.cells[idx])

    @staticmethod
    def concat(parts) -> "Shard":
        parts = [p for p in parts if p is not None]
        out = Shard(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                      ("ids", "image_ids", "descriptors", "sigma", "cells")))
        order = np.argsort(out.ids, kind="stable")  # canonical order: results independent of arrival order
        return out.take(order)


def source_sigma(descriptors: np.ndarray, image_ids: np.ndarray) -> np.ndarray:
    """Exact sigma of features of whole images (what a source agent can compute)."""
    X = np.asarray(descriptors, dtype=np.float64)
    if len(X) == 0:
        return np.zeros(0)
    _, img = np.unique(image_ids, return_inverse=True)
    img = img.ravel()
    return distinctiveness(pairs.Augmented(X), img, int(img.max()) + 1)


def cluster_shard(shard: Shard, mode: str, rho: float = DEFAULT_RHO, kernel: str = "quadratic",
                  n_threads: Optional[int] = None) -> Tuple[Optional[QuickMatchResult], np.ndarray]:
    """Local QuickMatch of a shard; returns (result, sigma used). Empty shards give (None, [])."""
    if len(shard) == 0:
        return None, np.zeros(0)
    sigma = None if mode == "paper" else shard.sigma
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a cell holding one image is fine here
        r = quickmatch(shard.descriptors, shard.image_ids, rho=rho, kernel=kernel, sigma=sigma,
                       n_threads=n_threads)
    return r, r.sigma


def reach(sigma: np.ndarray, mode: str, rho: float, halo: float = 1.0) -> np.ndarray:
    """Interaction radius of every feature for the contested test.

    Paper: ``sigma`` (the paper's sigma_p). Default: ``halo * max(rho, 1) * sigma``:
    with ``halo = 1`` it covers both the longest edge that can merge
    (``rho * sigma``) and the quadratic kernel's support (``sigma``), so no
    feature that could change x's density or merge with x is missed by the
    test; smaller values trade fidelity for traffic (docs/distributed.md).
    """
    sigma = np.asarray(sigma, dtype=np.float64)
    return sigma if mode == "paper" else sigma * (halo * max(rho, 1.0))


def boundary_distances(shard: Shard, seeds: np.ndarray, mode: str,
                       reach_values: Optional[np.ndarray] = None) -> np.ndarray:
    """(n, m) distances of held features to every cell (0 for the feature's own cell).

    Default mode: bisector bounds (closed form). Paper mode: exact cell
    distances (QP, piqp) where the bisector bound is below the reach (beyond
    it the exact distance is larger too and changes nothing).
    """
    H = boundary.hyperplane_distances(shard.descriptors, seeds, shard.cells)
    if mode == "paper" and len(shard) and len(seeds) > 1:
        need = H < (reach_values[:, None] if reach_values is not None else np.inf)
        H = boundary.cell_distances(shard.descriptors, seeds, shard.cells, need=need, hyper=H)
    return H


def minima_for_broadcast(H: np.ndarray, me: int, m: int) -> np.ndarray:
    """The exchanged minima this agent publishes: e[me, a] for every a."""
    return contested.exchanged_minima(H, me, m)


def contested_with(shard: Shard, H: np.ndarray, reach_values: np.ndarray, minima: np.ndarray) -> np.ndarray:
    """(n, m) contested matrix of held features; ``minima[a, i]`` = e[a, i] from agent a.

    A feature of cell i is tested against agent a with ``e[a, i]`` (the cell it
    is geometrically in, which for handed-down features is not the holder's).
    """
    if len(shard) == 0:
        return np.zeros((0, minima.shape[0]), bool)
    E = minima[:, shard.cells].T  # (n, m): e[a, cell(x)]
    C = (H + E) < reach_values[:, None]
    C[np.arange(len(shard)), shard.cells] = False
    return C


def candidate_agents(C: np.ndarray, location: Optional[np.ndarray], mode: str) -> np.ndarray:
    """(n, m) bool: agents a feature may have to meet, from its contested cells.

    Paper mode: the contested cells' own agents. Default mode: every agent
    that holds features of a contested cell (``location[k, b]``: some features
    of cell k are at agent b), so a feature follows the features it may
    interact with when those were handed further down (the follow rule).
    """
    if mode == "paper" or location is None:
        return C
    return (C.astype(np.uint8) @ location.astype(np.uint8)) > 0


def hand_down(shard: Shard, result: QuickMatchResult, C: np.ndarray, me: int, mode: str,
              location: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray]:
    """(target agent of every held feature (``me`` = keep), unit of every feature); hand-down only."""
    if len(shard) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if mode == "paper":
        units = contested.units_from_clusters(result.labels)
    else:
        units = contested.units_from_tree(result.labels, result.parent)
    A = candidate_agents(C, location, mode)
    targets = contested.unit_targets(units, A, me, below=me)
    return targets[units], units


def record_moves(location: np.ndarray, cells: np.ndarray, targets: np.ndarray) -> None:
    """Mark in ``location`` that features of ``cells[k]`` are now held by ``targets[k]``."""
    location[np.asarray(cells, dtype=np.int64), np.asarray(targets, dtype=np.int64)] = True


def arrival_check(units_in: np.ndarray, C_in: np.ndarray, me: int, sender: int,
                  location: Optional[np.ndarray] = None, mode: str = "default") -> int:
    """Number of arrived units that should not have come to ``me``.

    The sender hands a unit to the lowest agent below itself that any member
    is contested with; the receiver recomputes that target from the same seeds,
    minima and the sigma sent along. A non-zero count means inconsistent state
    or a bad sender; the caller counts it and keeps the features (nothing is lost).
    """
    if len(units_in) == 0:
        return 0
    _, u = np.unique(units_in, return_inverse=True)
    targets = contested.unit_targets(u.ravel(), candidate_agents(C_in, location, mode), sender, below=sender)
    return int((targets != me).sum())


def timed(fn, *args, **kwargs):
    t = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t


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
    seed_norm: float = 512.0
    job: str = "job"

    def validated(self, n_features: Optional[int] = None) -> "DQMConfig":
        from ..validation import InputError, check_choice, check_positive
        from . import partition
        from .clustering import KERNELS

        partition.check_agents(self.agents, n_features)
        partition.check_seed(self.seed)
        check_choice(self.partition, "partition", partition.PARTITION_MODES)
        check_choice(self.mode, "mode", DQM_MODES)
        check_choice(self.kernel, "kernel", KERNELS)
        check_positive(self.rho, "rho")
        check_positive(self.halo, "halo")
        check_positive(self.seed_norm, "seed_norm")
        if isinstance(self.samples_per_agent, bool) or not isinstance(self.samples_per_agent, int) \
                or self.samples_per_agent < 1:
            raise InputError(f"samples_per_agent must be a positive integer, got {self.samples_per_agent!r}")
        return self


@dataclass
class CascadeOutcome:
    """What agent ``me`` decides at its turn of the hand-down cascade."""

    sends: Dict[int, Tuple[Shard, np.ndarray]]  # target agent -> (features, their units)
    moved: np.ndarray  # flattened (cell, target) pairs (dqm.protocol.moved_pairs)
    final: Shard  # what the agent keeps
    final_result: Optional[QuickMatchResult]  # its final clusters
    arrival_failures: int = 0


class AgentCore:
    """One agent's algorithm state: what it holds and what it decided. No I/O.

    The simulator drives m of these in one process; the runtime drives one per
    process from messages. Call order: :meth:`route` (source side),
    :meth:`set_shard`, :meth:`local_step`, then :meth:`cascade` with the
    hand-downs and moves of the higher agents.
    """

    def __init__(self, me: int, cfg: DQMConfig):
        self.me = me
        self.cfg = cfg
        self.m = cfg.agents
        self.shard: Optional[Shard] = None
        self.first: Optional[QuickMatchResult] = None
        self.seeds: Optional[np.ndarray] = None
        self.minima: Optional[np.ndarray] = None
        self.time_cluster = 0.0
        self.time_boundary = 0.0
        self._H: Dict[int, np.ndarray] = {}
        self._Hreach: Dict[int, float] = {}

    # -- source side ---------------------------------------------------------------
    def route(self, ids, image_ids, descriptors, seeds: np.ndarray) -> Dict[int, Shard]:
        """Split this agent's source features by cell; default mode computes exact sigma first."""
        from . import partition

        X = np.asarray(descriptors)
        Xf = X.astype(np.float64)
        cells = partition.route(Xf, seeds)
        sigma = source_sigma(Xf, image_ids) if self.cfg.mode == "default" else np.zeros(len(X))
        whole = Shard(np.asarray(ids, np.int64), np.asarray(image_ids, np.int64), X, sigma, cells)
        return {b: whole.take(np.flatnonzero(cells == b)) for b in range(self.m)}

    # -- cell side -----------------------------------------------------------------
    def set_shard(self, parts, seeds: np.ndarray) -> None:
        self.seeds = np.asarray(seeds, dtype=np.float64)
        self.shard = Shard.concat(parts)

    def bounds(self, shard: Shard, rch: np.ndarray) -> np.ndarray:
        """Boundary distances, kept per feature (they depend on the descriptor and seeds only)."""
        todo = [k for k, i in enumerate(shard.ids.tolist()) if self._Hreach.get(i, -1.0) < rch[k]]
        if todo:
            sub = shard.take(np.array(todo))
            H, tb = timed(boundary_distances, sub, self.seeds, self.cfg.mode, rch[todo])
            self.time_boundary += tb
            for k, i in enumerate(sub.ids.tolist()):
                self._H[i] = H[k]
                self._Hreach[i] = float(rch[todo[k]])
        if len(shard) == 0:
            return np.zeros((0, self.m))
        return np.stack([self._H[i] for i in shard.ids.tolist()])

    def _cluster(self, shard: Shard) -> Optional[QuickMatchResult]:
        (res, sig), tc = timed(cluster_shard, shard, self.cfg.mode, self.cfg.rho, self.cfg.kernel)
        self.time_cluster += tc
        if self.cfg.mode == "paper" and len(shard):
            shard.sigma = sig
        return res

    def _reach(self, shard: Shard) -> np.ndarray:
        return reach(shard.sigma, self.cfg.mode, self.cfg.rho, self.cfg.halo)

    def local_step(self) -> np.ndarray:
        """Cluster the cell, compute boundary distances; returns the minima to broadcast."""
        self.first = self._cluster(self.shard)
        H = self.bounds(self.shard, self._reach(self.shard))
        return minima_for_broadcast(H, self.me, self.m)

    def set_minima(self, minima: np.ndarray) -> None:
        self.minima = np.asarray(minima, dtype=np.float64)

    def contested_now(self) -> np.ndarray:
        """Initial contested flag of every held feature (for statistics and pictures)."""
        rch = self._reach(self.shard)
        return contested_with(self.shard, self.bounds(self.shard, rch), rch, self.minima).any(axis=1)

    @staticmethod
    def location_from(moves_by_agent: Dict[int, np.ndarray], m: int, above: int) -> np.ndarray:
        """Location map from the moves reported by agents with index > ``above``."""
        loc = np.eye(m, dtype=bool)
        for a, flat in moves_by_agent.items():
            if a > above and len(flat):
                pairs = np.asarray(flat, np.int64).reshape(2, -1)
                record_moves(loc, pairs[0], pairs[1])
        return loc

    def cascade(self, received, moves_by_agent: Dict[int, np.ndarray]) -> CascadeOutcome:
        """This agent's turn: ``received`` is [(sender, Shard, units)] from higher agents,
        ``moves_by_agent`` the (cell, target) moves every higher agent reported."""
        a = self.me
        failures = 0
        for sender, s_in, u_in in received:
            rch_in = self._reach(s_in)
            C_in = contested_with(s_in, self.bounds(s_in, rch_in), rch_in, self.minima)
            failures += arrival_check(u_in, C_in, a, sender,
                                      self.location_from(moves_by_agent, self.m, sender), self.cfg.mode)
        parts = [s for _, s, _ in received]
        cur = Shard.concat([self.shard] + parts) if parts else self.shard
        res = self._cluster(cur) if parts else self.first
        sends: Dict[int, Tuple[Shard, np.ndarray]] = {}
        moved = np.zeros(0, np.int64)
        if a > 0 and len(cur):
            from .. import protocol

            rch = self._reach(cur)
            C = contested_with(cur, self.bounds(cur, rch), rch, self.minima)
            location = self.location_from(moves_by_agent, self.m, a)
            target, units = hand_down(cur, res, C, a, self.cfg.mode, location)
            for b in np.unique(target[target != a]).tolist():
                sel = np.flatnonzero(target == b)
                sends[b] = (cur.take(sel), units[sel])
            out = target != a
            moved = protocol.moved_pairs(cur.cells[out], target[out])
            if out.any():  # final re-clustering of what stays
                cur = cur.take(np.flatnonzero(~out))
                res = self._cluster(cur) if len(cur) else None
        return CascadeOutcome(sends=sends, moved=moved, final=cur, final_result=res, arrival_failures=failures)
