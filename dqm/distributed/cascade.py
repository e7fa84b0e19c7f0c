"""The hand-down cascade (lean and paper modes): the steps one agent runs on its own data.

Pure functions on a :class:`~dqm.distributed.shard.Shard` (the features an
agent holds); no I/O. The in-process simulator and the zenoh runtime call
exactly these, so they cannot drift apart.

Protocol (m agents, agent i owns cell i of the seeds), after the set-up and
routing shared with the balanced mode (dqm.distributed.protocol):

1. every agent clusters its cell with the finite (quadratic) kernel. Lean mode
   uses the exact sigma computed at the source (which holds whole images);
   paper mode recomputes sigma inside each cell (``per-agent sigma``);
2. boundary distances: bisector distances of held features to all cells; the
   exchanged minima ``e[a, i]`` are broadcast (m - 1 scalars per agent);
3. hand-down cascade from agent m-1 to agent 0: agent a re-clusters what it
   holds plus what higher agents handed it, tests contested features against
   lower agents, hands every unit with a contested feature to the lowest such
   agent (the receiver checks on arrival that it is that agent), tells the
   lower agents which cells' features went where, and re-clusters the rest:
   its final clusters. Lean mode adds the follow rule: a feature contested
   with a cell whose features were handed further down follows them.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import numpy as np

from ..core.clustering import DEFAULT_RHO, QuickMatchResult, quickmatch
from . import boundary, contested
from .config import DQMConfig
from .shard import Shard


def cluster_shard(shard: Shard, mode: str, rho: float = DEFAULT_RHO, kernel: str = "quadratic",
                  n_threads: Optional[int] = None,
                  engine: str = "exact") -> Tuple[Optional[QuickMatchResult], np.ndarray]:
    """Local QuickMatch of a shard with ``engine`` (dqm.quickmatch's); returns (result, sigma used). Empty
    shards give (None, [])."""
    if len(shard) == 0:
        return None, np.zeros(0)
    sigma = None if mode == "paper" else shard.sigma
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a cell holding one image is fine here
        r = quickmatch(shard.descriptors, shard.image_ids, rho=rho, kernel=kernel, sigma=sigma,
                       n_threads=n_threads, engine=engine)
    return r, r.sigma


def reach(sigma: np.ndarray, mode: str, rho: float, halo: float = 1.0) -> np.ndarray:
    """Interaction radius of every feature for the contested test.

    Paper: ``sigma`` (the paper's sigma_p). Lean: ``halo * max(rho, 1) * sigma``:
    with ``halo = 1`` it covers both the longest edge that can merge
    (``rho * sigma``) and the quadratic kernel's support (``sigma``), so no
    feature that could change x's density or merge with x is missed by the
    test; smaller values trade fidelity for traffic (docs/distributed.md).
    """
    sigma = np.asarray(sigma, dtype=np.float64)
    return sigma if mode == "paper" else sigma * (halo * max(rho, 1.0))


def boundary_distances(shard: Shard, seeds: np.ndarray, mode: str,
                       reach_values: Optional[np.ndarray] = None,
                       weights: Optional[np.ndarray] = None) -> np.ndarray:
    """(n, m) distances of held features to every cell (0 for the feature's own cell).

    Lean mode: bisector bounds (closed form). Paper mode: exact cell
    distances (QP, piqp) where the bisector bound is below the reach (beyond
    it the exact distance is larger too and changes nothing).
    """
    H = boundary.hyperplane_distances(shard.descriptors, seeds, shard.cells, weights)
    if mode == "paper" and len(shard) and len(seeds) > 1:
        need = H < (reach_values[:, None] if reach_values is not None else np.inf)
        H = boundary.cell_distances(shard.descriptors, seeds, shard.cells, need=need, hyper=H, weights=weights)
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

    Paper mode: the contested cells' own agents. Lean mode: every agent
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
                  location: Optional[np.ndarray] = None, mode: str = "lean") -> int:
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


@dataclass
class CascadeOutcome:
    """What agent ``me`` decides at its turn of the hand-down cascade."""

    sends: Dict[int, Tuple[Shard, np.ndarray]]  # target agent -> (features, their units)
    moved: np.ndarray  # flattened (cell, target) pairs (dqm.protocol.moved_pairs)
    final: Shard  # what the agent keeps
    final_result: Optional[QuickMatchResult]  # its final clusters
    arrival_failures: int = 0


class CascadeCore:
    """One agent's state in the lean and paper modes: what it holds and decided. No I/O.

    The simulator drives m of these in one process; the runtime drives one per
    process from messages. Call order: :meth:`set_shard` (after routing),
    :meth:`local_step`, :meth:`set_minima`, then :meth:`cascade` with the
    hand-downs and moves of the higher agents.
    """

    def __init__(self, me: int, cfg: DQMConfig):
        self.me = me
        self.cfg = cfg
        self.m = cfg.agents
        self.shard: Optional[Shard] = None
        self.first: Optional[QuickMatchResult] = None
        self.seeds: Optional[np.ndarray] = None
        self.weights: Optional[np.ndarray] = None
        self.pairs_computed = 0  # pairs of all local QuickMatch runs (the busiest agent's pair work)
        self.max_held = 0
        self.minima: Optional[np.ndarray] = None
        self.time_cluster = 0.0
        self.time_boundary = 0.0
        self._H: Dict[int, np.ndarray] = {}
        self._Hreach: Dict[int, float] = {}

    # -- cell side -----------------------------------------------------------------
    def set_shard(self, parts, seeds: np.ndarray, weights: Optional[np.ndarray] = None) -> None:
        self.seeds = np.asarray(seeds, dtype=np.float64)
        self.weights = None if weights is None else np.asarray(weights, dtype=np.float64)
        self.shard = Shard.concat(parts)
        self.max_held = len(self.shard)

    def bounds(self, shard: Shard, rch: np.ndarray) -> np.ndarray:
        """Boundary distances, kept per feature (they depend on the descriptor and seeds only)."""
        todo = [k for k, i in enumerate(shard.ids.tolist()) if self._Hreach.get(i, -1.0) < rch[k]]
        if todo:
            sub = shard.take(np.array(todo))
            H, tb = timed(boundary_distances, sub, self.seeds, self.cfg.mode, rch[todo], self.weights)
            self.time_boundary += tb
            for k, i in enumerate(sub.ids.tolist()):
                self._H[i] = H[k]
                self._Hreach[i] = float(rch[todo[k]])
        if len(shard) == 0:
            return np.zeros((0, self.m))
        return np.stack([self._H[i] for i in shard.ids.tolist()])

    def _cluster(self, shard: Shard) -> Optional[QuickMatchResult]:
        (res, sig), tc = timed(cluster_shard, shard, self.cfg.mode, self.cfg.rho, self.cfg.kernel,
                                 engine=self.cfg.engine)
        self.time_cluster += tc
        self.pairs_computed += len(shard) * (len(shard) - 1) // 2
        self.max_held = max(self.max_held, len(shard))
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
            from . import protocol

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

    def outcome_stats(self, out: CascadeOutcome) -> Dict[str, float]:
        """This agent's statistics after its turn (the same keys in the simulator and the runtime)."""
        return {
            "features_routed": float(len(self.shard)), "features_final": float(len(out.final)),
            "time_cluster": self.time_cluster, "time_boundary": self.time_boundary,
            "pairs": float(self.pairs_computed), "max_held": float(self.max_held),
            "arrival_check_failures": float(out.arrival_failures),
            "handed_down": float(sum(len(v[0]) for v in out.sends.values())),
        }
