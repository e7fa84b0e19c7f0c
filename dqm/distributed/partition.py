"""Partition seeds and Voronoi routing for Distributed QuickMatch.

Agents own the cells of a Voronoi tessellation of descriptor space by seeds
``P_0 .. P_{m-1}``; a feature belongs to the agent of its nearest seed (ties:
the lower agent index) -- the labelling l(x, 0) of the paper.

Two ways to get the seeds, both from one integer broadcast by the coordinator:

* ``seeded``: derived from the integer alone, no data exchanged. Seeds are
  drawn from a descriptor *domain* model: for SIFT-like data (the default
  domain) non-negative, heavy-tailed components normalised like SIFT to a
  given norm (512 for OpenCV's uint8 SIFT). Cells are less balanced than with
  k-means (as the paper notes).
* ``kmeans``: Lloyd iterations (the paper). No agent sees all features, so the
  agents send a small deterministic sample of their own descriptors to the
  leader (agent 0), which runs k-means++ and Lloyd on the pooled sample seeded
  by the integer and broadcasts the m seeds. Bytes: the sample plus m x dim
  seeds to each agent (metered by the simulator and the runtime).

Balanced cells (power diagram): k-means cells of real descriptors are
unbalanced (the largest graf cell holds 1.5 n/m at m = 8). Optional weights
``w`` move the boundaries: a feature goes to ``argmin_a |x - P_a|^2 - w_a``.
The cells stay convex polytopes, each pair separated by one hyperplane, so the
bisector distance stays closed form and additive (dqm.distributed.boundary).
Agent 0 fits the weights on the pooled sample (:func:`fit_weights`), then
refines them on the exact cell counts of all features, which every agent
reports for its own features (:func:`refine_weights`, rounds of m integers per
agent until the largest cell is within 10% of n/m); all from the same integer.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..validation import InputError

PARTITION_MODES = ("kmeans", "seeded")


def check_agents(m, n_features: int | None = None) -> int:
    if isinstance(m, bool) or not isinstance(m, (int, np.integer)):
        raise InputError(f"number of agents must be an integer >= 1, got {m!r}")
    m = int(m)
    if m < 1:
        raise InputError(f"number of agents must be >= 1, got {m}")
    if n_features is not None and m > max(1, n_features):
        raise InputError(f"more agents ({m}) than features ({n_features}): every agent needs a cell")
    return m


def check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise InputError(f"partition seed must be an integer, got {seed!r}")
    seed = int(seed)
    if not 0 <= seed < 2 ** 63:
        raise InputError(f"partition seed must be in [0, 2^63), got {seed}")
    return seed


def seeded_seeds(seed: int, m: int, dim: int, norm: float = 512.0) -> np.ndarray:
    """m SIFT-like seeds from the integer alone (float64, (m, dim))."""
    seed = check_seed(seed)
    m = check_agents(m)
    rng = np.random.default_rng([seed, 0x5EED])
    v = rng.gamma(0.5, 1.0, size=(m, dim))
    v /= np.linalg.norm(v, axis=1, keepdims=True) + 1e-12
    np.minimum(v, 0.2, out=v)
    v /= np.linalg.norm(v, axis=1, keepdims=True) + 1e-12
    return v * norm


def sample_for_seeds(descriptors: np.ndarray, feature_ids: np.ndarray, seed: int, per_agent: int) -> np.ndarray:
    """Indices of the deterministic sample an agent sends to the leader.

    The choice depends only on the integer and the global feature ids, so it is
    the same whichever process computes it.
    """
    n = len(descriptors)
    if n <= per_agent:
        return np.arange(n)
    # hash of (seed, feature id): a per-feature pseudo-random key
    key = (np.asarray(feature_ids, dtype=np.uint64) * np.uint64(0x9E3779B97F4A7C15)
           ^ np.uint64(check_seed(seed) * 0xBF58476D1CE4E5B9 % 2 ** 64))
    key ^= key >> np.uint64(31)
    return np.sort(np.argsort(key, kind="stable")[:per_agent])


def kmeans_seeds(sample: np.ndarray, m: int, seed: int, iterations: int = 20) -> np.ndarray:
    """k-means++ then Lloyd on the pooled sample, deterministic for the integer."""
    seed = check_seed(seed)
    m = check_agents(m)
    X = np.asarray(sample, dtype=np.float64)
    if len(X) < m:
        raise InputError(f"k-means needs at least m = {m} sample descriptors, got {len(X)}")
    rng = np.random.default_rng([seed, 0x3EA5])
    centers = [X[rng.integers(len(X))]]
    d2 = ((X - centers[0]) ** 2).sum(1)
    for _ in range(1, m):
        p = d2 / d2.sum() if d2.sum() > 0 else np.full(len(X), 1.0 / len(X))
        c = X[rng.choice(len(X), p=p)]
        centers.append(c)
        d2 = np.minimum(d2, ((X - c) ** 2).sum(1))
    C = np.array(centers)
    for _ in range(iterations):
        lab = route(X, C)
        newC = C.copy()
        for a in range(m):
            sel = lab == a
            if sel.any():
                newC[a] = X[sel].mean(0)
        if np.allclose(newC, C):
            break
        C = newC
    return C


def route(X: np.ndarray, seeds: np.ndarray, weights: Optional[np.ndarray] = None) -> np.ndarray:
    """Cell (agent index) of every row: least power ``|x - P_a|^2 - w_a``, ties to the lower index.

    The answer depends on the row alone, never on the batch it is routed in:
    a BLAS product's last bits do, so where the two best powers are closer
    than a bound of their rounding errors the row is decided in exact
    rational arithmetic. Identical descriptors therefore always share a cell
    (the balanced mode's exactness needs it: duplicates meet only there).
    """
    if len(X) == 0:
        return np.zeros(0, np.int64)
    X = np.asarray(X, dtype=np.float64)
    P = np.asarray(seeds, dtype=np.float64)
    d = power(X, P, weights)
    cells = np.argmin(d, axis=1).astype(np.int64)
    if len(P) < 2:
        return cells
    # |rounding error| of each power: dot products of length dim plus the sums around them
    u = float(np.finfo(np.float64).eps)
    w = np.zeros(len(P)) if weights is None else np.abs(np.asarray(weights, dtype=np.float64))
    pnorm = np.sqrt((P ** 2).sum(1))
    err = 4.0 * (X.shape[1] + 4) * u * ((pnorm ** 2)[None, :] + 2.0 * np.sqrt((X ** 2).sum(1))[:, None]
                                         * pnorm[None, :] + w[None, :])
    best = d[np.arange(len(X)), cells]
    near = d - err <= (best + err[np.arange(len(X)), cells])[:, None]
    for r in np.flatnonzero(near.sum(axis=1) > 1).tolist():
        cells[r] = _exact_route(X[r], P, None if weights is None else np.asarray(weights, np.float64),
                                np.flatnonzero(near[r]))
    return cells


def _exact_route(x: np.ndarray, P: np.ndarray, weights: Optional[np.ndarray], candidates: np.ndarray) -> int:
    """The least exact power among the candidate cells, ties to the lower index. Every float is a
    dyadic rational: scaled by the largest denominator D (a power of two) among the values involved,
    the descriptor and seed coordinates are integers and so is ``D^2`` times every power (and weight), so
    Python's integers compare them exactly (as rational arithmetic would, about 20x faster: 22 -> 1 ms a row
    of 128 dimensions against six seeds)."""
    cand = candidates.tolist()
    rows = [x.tolist()] + [P[a].tolist() for a in cand]
    wts = [0.0] * len(cand) if weights is None else [float(weights[a]) for a in cand]
    ratios = [[v.as_integer_ratio() for v in r] for r in rows]
    w_ratios = [v.as_integer_ratio() for v in wts]
    D = max([d for r in ratios for _, d in r] + [d for _, d in w_ratios])  # powers of two: the others divide it
    xs = [n * (D // d) for n, d in ratios[0]]
    best, best_a = None, -1
    for a, r, (wn, wd) in zip(cand, ratios[1:], w_ratios):
        cs = [n * (D // d) for n, d in r]
        p = sum(c * (c - 2 * xv) for c, xv in zip(cs, xs)) - wn * (D // wd) * D
        if best is None or p < best:
            best, best_a = p, a
    return best_a


def power(X: np.ndarray, seeds: np.ndarray, weights: Optional[np.ndarray] = None) -> np.ndarray:
    """(n, m) power of every row to every seed, without the common ``|x|^2`` term."""
    X = np.asarray(X, dtype=np.float64)
    seeds = np.asarray(seeds, dtype=np.float64)
    d2 = (seeds ** 2).sum(1)[None, :] - 2.0 * X @ seeds.T
    if weights is not None:
        d2 -= np.asarray(weights, dtype=np.float64)[None, :]
    return d2


def _margin_scale(sample: np.ndarray, seeds: np.ndarray) -> float:
    """Typical gap between a sample point's best and second-best power (weight units)."""
    if len(seeds) < 2 or len(sample) == 0:
        return 1.0
    d = np.sort(power(sample, seeds), axis=1)
    gap = float(np.median(d[:, 1] - d[:, 0]))
    return gap if gap > 0 else 1.0


def fit_weights(sample: np.ndarray, seeds: np.ndarray, iterations: int = 500) -> np.ndarray:
    """Power weights that split the pooled sample evenly (deterministic).

    Each step raises the weight of cells below their share and lowers those
    above it; the best weights seen (smallest largest cell) are returned.
    """
    S = np.asarray(sample, dtype=np.float64)
    m = len(seeds)
    w = np.zeros(m)
    if m < 2 or len(S) < m:
        return w
    target = len(S) / m
    scale = _margin_scale(S, seeds)
    d = power(S, seeds)
    best_max, best_w = None, w.copy()
    for _ in range(iterations):
        c = np.bincount(np.argmin(d - w[None, :], axis=1), minlength=m)
        if best_max is None or c.max() < best_max:
            best_max, best_w = int(c.max()), w.copy()
        if c.max() <= np.ceil(target):
            break
        w = w + 0.2 * scale * (target - c) / target
    return best_w


def margin_scale(sample: np.ndarray, seeds: np.ndarray) -> float:
    """Typical gap between a sample point's best and second-best power (the weights' unit)."""
    return _margin_scale(np.asarray(sample, np.float64), seeds)


def refine_weights(weights: np.ndarray, step: np.ndarray, previous: np.ndarray, counts: np.ndarray):
    """One round of weight refinement on the exact cell counts of all features (Rprop).

    Counts are piecewise constant in the weights, so gradients say little;
    each cell moves its weight by its own step toward its share n/m, the step
    growing (x1.2) while the cell stays on the same side and halving when it
    crosses. Returns ``(weights, step, sign)``; deterministic.
    """
    counts = np.asarray(counts, dtype=np.float64)
    sign = np.sign(counts.sum() / len(counts) - counts)
    step = np.where(sign * previous < 0, 0.5 * step, np.where(sign * previous > 0, 1.2 * step, step))
    return np.asarray(weights, np.float64) + step * sign, step, sign
