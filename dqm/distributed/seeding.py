"""The set-up before routing, shared by every mode: seeds, cell weights, sketch basis, sigma fill.

Everything follows from the one integer the coordinator broadcasts:

1. Every agent computes the exact sigma of its own features (it holds whole
   images) and sends agent 0 (the leader) a deterministic sample of its
   descriptors (chosen by a hash of the integer and the feature ids) and the
   number of its features that are alone in their image.
2. The leader computes the seeds (k-means on the pooled sample, or from the
   integer alone), the power weights that balance the cells on the sample,
   and the sketch basis (principal directions of the sample), and broadcasts
   them.
3. Only if some image has a single feature: every agent sends its finite
   sigmas, the leader broadcasts their median (the centralized engine's value
   for such features), so sigma is exact everywhere.
4. Only with cell weights: rounds of exact cell counts (m integers per agent)
   and refined weights (dqm.distributed.partition.refine_weights) until the
   largest cell is within 10% of n/m or ``balance_rounds`` are spent; the best
   weights seen are final.

The agent side is :class:`SourceSide`, the leader's is :class:`Leader`; the
simulator and the runtime call the same methods with the same payloads.
"""
from __future__ import annotations

from typing import Dict, Optional

import numpy as np

from . import partition, sketch
from .config import DQMConfig
from .shard import Shard, fill_lonely, median_fill, source_sigma, split_by_cell

#: the agent that leads the set-up and the balanced mode's leader rounds (one definition for both)
LEADER = 0
#: weight refinement stops once the largest cell holds at most this times n/m
BALANCE_TOLERANCE = 1.10


class SourceSide:
    """An agent's own features (whole images) before routing, and the set-up it receives."""

    def __init__(self, me: int, cfg: DQMConfig, ids: np.ndarray, image_ids: np.ndarray, descriptors: np.ndarray):
        self.me = me
        self.cfg = cfg
        self.m = cfg.agents
        self.ids = np.asarray(ids, np.int64)
        self.image_ids = np.asarray(image_ids, np.int64)
        self.descriptors = descriptors
        self.X = np.asarray(descriptors, dtype=np.float64)
        self.sigma = source_sigma(self.X, self.image_ids) if cfg.source_sigma else np.zeros(len(self.ids))
        self.seeds: Optional[np.ndarray] = None
        self.weights: Optional[np.ndarray] = None
        self.basis = np.zeros((0, self.X.shape[1] if self.X.ndim == 2 else 0), np.int8)
        self.final = False
        self.need_fill = False

    # --------------------------------------------------------------- messages out
    def sample_payload(self) -> dict:
        if self.cfg.needs_sample:
            # at least m each, so that k-means always has m samples when there are m features at all
            per = max(self.cfg.samples_per_agent, self.m)
            pick = partition.sample_for_seeds(self.X, self.ids, self.cfg.seed, per)
        else:
            pick = np.zeros(0, np.int64)
        return {"descriptors": np.ascontiguousarray(self.descriptors[pick]),
                "lonely": int(np.isnan(self.sigma).sum())}

    def sigmas_payload(self) -> dict:
        return {"values": np.sort(self.sigma[~np.isnan(self.sigma)])}

    def counts_payload(self) -> dict:
        cells = partition.route(self.X, self.seeds, self.weights)
        return {"counts": np.bincount(cells, minlength=self.m).astype(np.int64)}

    # --------------------------------------------------------------- messages in
    def on_seeds(self, p: dict) -> None:
        seeds = np.asarray(p["seeds"], np.float64)
        if len(seeds) == 0:
            seeds = partition.seeded_seeds(self.cfg.seed, self.m, self.X.shape[1], norm=self.cfg.seed_norm)
        self.seeds = seeds
        self.weights = np.asarray(p["weights"], np.float64) if self.cfg.weighted else None
        self.basis = np.asarray(p["basis"])
        self.final = bool(p["final"])
        self.need_fill = bool(p["fill"])

    def on_fill(self, value: float) -> None:
        self.sigma = fill_lonely(self.sigma, value)
        self.need_fill = False

    def on_weights(self, p: dict) -> None:
        self.weights = np.asarray(p["weights"], np.float64)
        self.final = bool(p["final"])

    # --------------------------------------------------------------- routing
    def sketch_space(self) -> Optional[sketch.SketchSpace]:
        if self.cfg.mode != "balanced" or len(self.basis) == 0:
            return None
        return sketch.SketchSpace(self.basis, self.seeds.mean(axis=0))

    def route(self) -> Dict[int, Shard]:
        """Own features split by cell (sigma filled where needed)."""
        cells = partition.route(self.X, self.seeds, self.weights)
        sigma = fill_lonely(self.sigma, 0.0) if np.isnan(self.sigma).any() else self.sigma
        return split_by_cell(self.ids, self.image_ids, self.descriptors, sigma, cells, self.m)


class Leader:
    """Agent 0's part of the set-up."""

    def __init__(self, cfg: DQMConfig, dim: int):
        self.cfg = cfg
        self.m = cfg.agents
        self.dim = dim
        self.rounds = 0
        self.best = None

    def seeds_payload(self, samples: Dict[int, dict]) -> dict:
        cfg = self.cfg
        pooled = [np.asarray(samples[a]["descriptors"], np.float64) for a in sorted(samples)]
        pooled = np.concatenate(pooled) if pooled else np.zeros((0, self.dim))
        self.sample = pooled
        if cfg.partition == "kmeans":
            seeds = partition.kmeans_seeds(pooled, self.m, cfg.seed)
            wire_seeds = seeds
        else:
            seeds = partition.seeded_seeds(cfg.seed, self.m, self.dim, norm=cfg.seed_norm)
            wire_seeds = np.zeros((0, self.dim))
        self.seeds = seeds
        weights = partition.fit_weights(pooled, seeds) if cfg.weighted else np.zeros(self.m)
        self.weights = weights
        self.step = np.full(self.m, 0.25 * partition.margin_scale(pooled, seeds))
        self.sign = np.zeros(self.m)
        if cfg.sketches:
            basis = sketch.basis_from_sample(pooled, seeds.mean(axis=0), cfg.sketch_dims)
        else:
            basis = np.zeros((0, self.dim), np.int8)
        lonely = sum(int(samples[a]["lonely"]) for a in samples)
        final = not (cfg.weighted and cfg.balance_rounds > 0 and self.m > 1)
        return {"seeds": wire_seeds, "weights": weights, "basis": basis, "final": int(final),
                "fill": int(lonely > 0 and cfg.source_sigma)}

    def fill_value(self, sigmas: Dict[int, dict]) -> float:
        return median_fill([sigmas[a]["values"] for a in sorted(sigmas)])

    def weights_payload(self, counts: Dict[int, dict]) -> dict:
        """Refined weights from the exact counts under the current weights."""
        c = np.sum([np.asarray(counts[a]["counts"], np.int64) for a in sorted(counts)], axis=0)
        n = int(c.sum())
        largest = int(c.max()) if len(c) else 0
        if self.best is None or largest < self.best[0]:
            self.best = (largest, self.weights.copy())
        self.rounds += 1
        if largest <= BALANCE_TOLERANCE * n / self.m or self.rounds >= self.cfg.balance_rounds:
            return {"weights": self.best[1], "final": 1}
        self.weights, self.step, self.sign = partition.refine_weights(self.weights, self.step, self.sign, c)
        return {"weights": self.weights, "final": 0}
