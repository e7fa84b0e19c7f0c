"""The features an agent holds, and what a source agent computes before routing."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict

import numpy as np

from ..core import pairs
from ..core.clustering import lonely_sigma


@dataclass
class Shard:
    """Features held by one agent: global ids, image ids, descriptors, sigma, cell."""

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
        """One shard of the parts, in increasing id order (results do not depend on arrival order)."""
        parts = [p for p in parts if p is not None]
        out = Shard(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                      ("ids", "image_ids", "descriptors", "sigma", "cells")))
        return out.take(np.argsort(out.ids, kind="stable"))


def source_sigma(descriptors: np.ndarray, image_ids: np.ndarray) -> np.ndarray:
    """Exact sigma of features of whole images (what a source agent can compute).

    Features alone in their image get NaN: their sigma is the median over all
    agents' features (:func:`fill_lonely`), agreed at set-up.
    """
    X = np.asarray(descriptors, dtype=np.float64)
    if len(X) == 0:
        return np.zeros(0)
    _, img = np.unique(image_ids, return_inverse=True)
    img = img.ravel()
    return pairs.nearest_same_image(pairs.Augmented(X), img, int(img.max()) + 1)


def fill_lonely(sigma: np.ndarray, value: float) -> np.ndarray:
    """sigma with the NaN entries (single-feature images) set to ``value``."""
    out = np.array(sigma, dtype=np.float64)
    out[np.isnan(out)] = value
    return out


def median_fill(finite_sigmas) -> float:
    """The centralized engine's rule (:func:`dqm.core.clustering.lonely_sigma`) over every agent's finite sigmas."""
    vals = np.concatenate([np.asarray(v, np.float64).ravel() for v in finite_sigmas]) if finite_sigmas else np.zeros(0)
    return lonely_sigma(vals)


def split_by_cell(ids, image_ids, descriptors, sigma, cells, m: int) -> Dict[int, Shard]:
    """A source agent's features, one shard per destination cell."""
    whole = Shard(np.asarray(ids, np.int64), np.asarray(image_ids, np.int64), descriptors,
                  np.asarray(sigma, np.float64), np.asarray(cells, np.int64))
    return {b: whole.take(np.flatnonzero(whole.cells == b)) for b in range(m)}
