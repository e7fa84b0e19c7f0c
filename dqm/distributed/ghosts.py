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

The fast engine (``engine="fast"``) needs no certificate, as the centralized fast
engine needs none, and sends the copies a pair is *likely* to need
(:func:`likely_copies`): x goes to b only when ``h(x, b) < LIKELY_SHARE * max(R_x, -s[b, a])``,
at most :func:`copy_budget` copies per feature of the cell, those nearest to a
boundary (relative to their reach) first. On generated SIFT-like features nearly
every feature lies within reach of several bisectors (the bound's rule ships 3.5
copies per feature at M = 8 on 100k) although the interacting pairs need 1.5;
docs/distributed.md measures what the rule misses (co-membership F1 against the
exact engine) and what it saves.
"""
from __future__ import annotations

from typing import Dict, Sequence, Tuple

import numpy as np

#: the fast engine's copies: x travels to cell b only when its bisector distance is below this share of its reach
LIKELY_SHARE = 0.3
#: ... and a cell sends at most ``COPY_BUDGET_BASE + m * COPY_BUDGET_PER_AGENT`` copies per own feature in all
#: (m agents: more cells, more boundaries), the nearest to a boundary first. Fitted on graf, sacre_coeur's and
#: generated 100k features at m = 4 and 8 (docs/distributed.md): real SIFT needs about 0.6 copies per feature
#: at m = 4 and 1.0 at m = 8 for clusters as exact's; generated features lie near many bisectors and would take 3
COPY_BUDGET_BASE = 0.2
COPY_BUDGET_PER_AGENT = 0.125


def copy_budget(m: int) -> float:
    """The fast engine's copies per own feature at most, with ``m`` agents."""
    return COPY_BUDGET_BASE + COPY_BUDGET_PER_AGENT * m


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


def likely_copies(H: np.ndarray, R: np.ndarray, to: Sequence[int], budget: float, their_reach: np.ndarray,
                  share: float = LIKELY_SHARE) -> Dict[int, np.ndarray]:
    """The fast engine's copies: for every cell b in ``to``, the indices (ascending) of this cell's features
    whose bisector distance ``H[:, b]`` is below ``share`` of the reach that matters, ``max(R_x,
    their_reach[b])`` (``their_reach[b] = -s[b, a]``, the most any feature of b reaches past the bisector:
    under the one-way rule a pair is met only where x travels, so b's reach counts as the exact rule counts
    it), at most ``budget`` copies per feature of the cell in all, kept by the smallest ratio (ties: the
    lower cell, then the lower index). Deterministic, and a receiver can check every copy it gets against
    the first test (:func:`likely_mask`)."""
    n = len(R)
    R = np.asarray(R, np.float64)
    to = [int(b) for b in to]
    if n == 0 or not to:
        return {b: np.zeros(0, np.int64) for b in to}
    reach = np.maximum(R[:, None], np.asarray(their_reach, np.float64)[None, to])
    with np.errstate(divide="ignore", invalid="ignore"):
        score = np.asarray(H, np.float64)[:, to] / reach
    score[~(reach > 0)] = np.inf
    rows, cols = np.nonzero(score < share)
    cap = int(budget * n)
    if len(rows) > cap:
        keep = np.lexsort((rows, cols, score[rows, cols]))[:cap]
        rows, cols = rows[keep], cols[keep]
    return {b: np.sort(rows[cols == k]).astype(np.int64) for k, b in enumerate(to)}


def likely_mask(h_to_b: np.ndarray, R: np.ndarray, their_reach: float, share: float = LIKELY_SHARE) -> np.ndarray:
    """Features (bisector distances ``h_to_b`` to cell b, reach ``R``; b's ``their_reach``) that
    :func:`likely_copies` may send to b."""
    reach = np.maximum(np.asarray(R, np.float64), float(their_reach))
    return (np.asarray(h_to_b, np.float64) < share * reach) & (reach > 0)
