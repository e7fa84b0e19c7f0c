"""Online QuickMatch's densities: the pairs a feature reaches, and exact sums kept up to date.

* :func:`reach_pairs`: every pair within ``max(1, rho) * sigma`` of an end, by
  one float32 GEMM per block with the engine's rigorous error bound, then exact
  squared distances of the survivors.
* :func:`add_terms`: add or subtract contributors' quadratic-kernel terms to
  their targets' exact integer sums (:mod:`dqm.core.density`), so the result
  has the same bits as summing from scratch.
* :func:`group_value`: a density value as batch computes it (duplicates take
  their group's first member's value).
"""
from __future__ import annotations

from typing import Tuple

import numpy as np

from . import density, native, pairs
from .clustering import kernel_weights
from .online_store import MARGIN, DuplicateGroups, FeatureStore
from .params import FINITE_KERNEL


def reach_pairs(s: FeatureStore, rows: np.ndarray, cols: np.ndarray, *, rho: float, max_norm2: float,
                n_threads: int, triangle: bool, rows_only: bool) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs (row, col) within ``max(1, rho) * sigma`` (with a margin) of the row's end, or of
    either end unless ``rows_only``, with exact squared distances. ``triangle``: ``rows`` also
    take part as columns, each unordered pair among them once. ``max_norm2``: the largest
    squared norm of a stored (centred) row, for the float32 error bound."""
    n = s.n
    reach = max(1.0, rho) * s.sigma[:n] * MARGIN
    slack = pairs.error_gamma(s.dim) * (s.norm2[:n] + max_norm2) + 1e-30  # as Augmented.d2_slack
    rad2 = (reach ** 2 + slack).astype(np.float32)
    rad2c = np.full(n, -np.inf, np.float32) if rows_only else rad2
    a, b = _gemm_candidates(s, rows, cols, rad2, rad2c, n_threads, triangle)
    d2 = pairs.exact_sq_distances(s.X, a, b)
    far = reach[a] if rows_only else np.maximum(reach[a], reach[b])
    keep = (d2 < far * far) | (d2 == 0)
    return a[keep], b[keep], d2[keep]


def _gemm_candidates(s: FeatureStore, rows: np.ndarray, cols: np.ndarray, rad2: np.ndarray, rad2c: np.ndarray,
                     n_threads: int, triangle: bool) -> Tuple[np.ndarray, np.ndarray]:
    """Pairs whose float32 squared distance is within the row's ``rad2`` or the column's ``rad2c``,
    block by block on the tile pool."""
    B = pairs.BLOCK
    row_blocks = [rows[i:i + B] for i in range(0, len(rows), B)]
    tasks = [(r, cols[j:j + B], False) for r in row_blocks for j in range(0, len(cols), B)]
    if triangle:
        tasks += [(row_blocks[i], row_blocks[j], i == j) for i in range(len(row_blocks))
                  for j in range(i, len(row_blocks))]
    zeros = np.zeros(max(B, 1), np.float32)

    def work(task):
        rb, cb, diagonal = task
        G = np.ascontiguousarray(s.left[rb] @ s.right[cb].T)
        dr, er, dc, ec = np.zeros(len(rb)), np.zeros(len(rb)), np.zeros(len(cb)), np.zeros(len(cb))
        r, c = native.tile_sym(G, zeros[:len(cb)], zeros[:len(cb)], zeros[:len(rb)], zeros[:len(rb)],
                               FINITE_KERNEL, rad2[rb], rad2c[cb], dr, er, dc, ec)
        if diagonal:
            keep = c > r
            r, c = r[keep], c[keep]
        return rb[r], cb[c]

    ra, ca = [], []
    with pairs.tile_pool(n_threads) as run:
        for r, c in run(work, tasks):
            ra.append(r)
            ca.append(c)
    a = np.concatenate(ra) if ra else np.zeros(0, np.int64)
    b = np.concatenate(ca) if ca else np.zeros(0, np.int64)
    return a, b


def add_terms(s: FeatureStore, contrib: np.ndarray, target: np.ndarray, d2: np.ndarray, sign: int,
              ratio_density: float) -> None:
    """Add (sign 1) or subtract (-1) contributor terms to targets' exact sums."""
    act = s.sigma[contrib] > 0
    contrib, target, d2 = contrib[act], target[act], d2[act]
    if len(contrib) == 0:
        return
    w, _ = kernel_weights(s.sigma[contrib], FINITE_KERNEL, ratio_density)
    terms = density.quadratic_terms(d2, w)
    pos = terms > 0
    hi, lo = density.term_parts(terms[pos])
    t = target[pos]
    # integer part sums (density.ExactSums' representation), exact in float64 in any order
    s.hi[:s.n] += sign * np.bincount(t, weights=hi, minlength=s.n)
    s.lo[:s.n] += sign * np.bincount(t, weights=lo, minlength=s.n)


def group_value(s: FeatureStore, groups: DuplicateGroups, slots: np.ndarray) -> np.ndarray:
    """Density value (1 + others) of slots, computed as batch computes it: duplicates take their
    group's first member's value, with zero-sigma duplicates added as integers after the exact sum."""
    out = 1.0 + density.parts_value(s.hi[slots], s.lo[slots])
    for k in np.flatnonzero(s.dup[slots]).tolist():
        members = groups.members_of(int(slots[k]))
        first = min(members, key=lambda m: s.key[m])
        b = density.parts_value(s.hi[first], s.lo[first])
        zc = sum(1 for m in members if s.sigma[m] == 0)
        out[k] = 1.0 + ((b + zc) - (1 if s.sigma[first] == 0 else 0))
    return out
