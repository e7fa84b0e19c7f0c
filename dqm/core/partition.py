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
"""
from __future__ import annotations


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


def route(X: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Cell (agent index) of every row: nearest seed, ties to the lower index."""
    X = np.asarray(X, dtype=np.float64)
    seeds = np.asarray(seeds, dtype=np.float64)
    if len(X) == 0:
        return np.zeros(0, np.int64)
    d2 = (seeds ** 2).sum(1)[None, :] - 2.0 * X @ seeds.T  # |x|^2 is common to all cells
    return np.argmin(d2, axis=1).astype(np.int64)  # argmin returns the first (lowest) index on ties
