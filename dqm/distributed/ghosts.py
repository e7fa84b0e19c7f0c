"""Which features of a cell travel as copies (ghosts) to which other cells.

Notation: feature x of cell a, ``R_x = max(1, rho) * sigma_x`` its *reach*
(the quadratic kernel's support sigma and the longest edge that can merge,
rho sigma), ``h(x, b)`` its bisector distance to cell b (dqm.distributed.boundary).
A pair (x, y), y in cell b, *interacts* when ``|x - y| < max(R_x, R_y)``: then y
may add to x's density or x to y's, or one may be the other's parent. Every
interacting pair must be met by an agent that holds both features.

The bisector separates the two cells, so ``|x - y| >= h(x, b) + h(y, a)``.
Each agent publishes two numbers per other cell (:func:`cell_summaries`):
``e[b, a] = min_{y in b} h(y, a)`` and ``s[b, a] = min_{y in b} (h(y, a) - R_y)``.

Rules (``ghost_rule``):

* ``"one-way"`` (default): for every pair of cells one direction is chosen
  (:func:`orientation`, a round-robin tournament, so every agent receives from
  about half of the others and the pair work stays even), and all pairs
  between the two cells are met at the receiver. Cell a ships x to b iff some
  y of b could interact with x, by the bound:
  ``h(x, b) < max(R_x - e[b, a], -s[b, a])``. Nothing travels back.
* ``"two-way"``: the plain bisector halo, ``h(x, b) < R_x`` in both
  directions; a pair both of whose features travel is met twice and counted
  once (at the lower agent). Kept to measure what the one-way rule saves.

The lower-bound sketch (dqm.distributed.sketch) then drops the copies that no
sketched feature of the receiver can reach.
"""
from __future__ import annotations

from typing import Tuple

import numpy as np


def orientation(m: int, rule: str) -> np.ndarray:
    """(m, m) bool: does cell a ship copies to cell b?"""
    a = np.arange(m)[:, None]
    b = np.arange(m)[None, :]
    if rule == "two-way":
        return a != b
    delta = (b - a) % m
    return ((delta >= 1) & (delta <= (m - 1) // 2)) | ((2 * delta == m) & (a < b))


def reach(sigma: np.ndarray, rho: float) -> np.ndarray:
    """Interaction radius ``max(1, rho) * sigma`` of every feature."""
    return np.asarray(sigma, dtype=np.float64) * max(1.0, float(rho))


def cell_summaries(H: np.ndarray, R: np.ndarray, me: int) -> Tuple[np.ndarray, np.ndarray]:
    """``(minima, slack)`` this cell publishes: ``e[me, .]`` and ``s[me, .]`` (inf for itself or if empty).

    ``H``: rigorous lower bounds of the bisector distances (float rounding
    already taken off, dqm.distributed.boundary.bisector_lower_bounds), so the
    published numbers are lower bounds too and every test below stays safe.
    """
    m = H.shape[1]
    if len(H) == 0:
        return np.full(m, np.inf), np.full(m, np.inf)
    minima = H.min(axis=0)
    slack = (H - R[:, None]).min(axis=0)
    minima[me] = np.inf
    slack[me] = np.inf
    return minima, slack


def ship_mask(h_to_b: np.ndarray, R: np.ndarray, e_ba: float, s_ba: float, rule: str) -> np.ndarray:
    """Features of this cell (lower-bounded bisector distances ``h_to_b`` to cell b) that b may need.

    ``e_ba``, ``s_ba``: cell b's published summaries toward this cell.
    """
    h = np.asarray(h_to_b, np.float64)
    if rule == "two-way":
        return h < R
    return h < np.maximum(R - e_ba, -s_ba)


def sketch_mask(h_to_a: np.ndarray, R: np.ndarray, e_ab: float, s_ab: float, rule: str) -> np.ndarray:
    """Features of this cell (b) that cell a's candidate copies could interact with.

    ``e_ab``, ``s_ab``: cell a's summaries toward this cell. One-way: y could be
    within ``max(R_x, R_y)`` of some x of a; two-way: within ``R_x`` (x's reach
    alone decides whether x travels).
    """
    h = np.asarray(h_to_a, np.float64)
    if rule == "two-way":
        return h < -s_ab
    return h < np.maximum(R - e_ab, -s_ab)
