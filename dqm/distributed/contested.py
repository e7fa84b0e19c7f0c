"""Contested features and hand-down decisions of Distributed QuickMatch.

Notation: agent i holds features x of its cell; ``h(x, a)`` is x's bisector
distance to cell a (dqm.core.boundary). Every agent a publishes, for every
other agent i, the *exchanged minimum* ``e[a, i] = min_{y held by a} h(y, i)``
(O(m^2) scalars in all). For x in cell i and any y in cell a the bisector
separates them, so ``|x - y| >= h(x, a) + h(y, i) >= h(x, a) + e[a, i]``.

The paper's test: x is **contested** with a iff ``h(x, a) + e[a, i] < reach(x)``.
Then x may interact with some feature of a; otherwise it provably cannot
within ``reach(x)``. ``reach`` is the interaction radius:

* paper mode: ``sigma_x`` (the paper's sigma_p);
* lean mode: ``halo * max(rho, 1) * sigma_x``: the longest tree edge of x
  that can merge (``rho * min(scale) <= rho * sigma_x``) and the support of
  x's quadratic kernel (``sigma_x``); ``halo = 1`` is safe.

A *unit* (what is handed down whole) is a local cluster (paper) or a local
tree component: clusters joined by any candidate tree edge, merged or not
(lean), because the merge decisions inside a component depend on each
other. A unit with a contested feature goes to the lowest index among its
holder and the agents its features are contested with.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..core import tree

HAND_DOWN_MODES = ("paper", "lean")


def exchanged_minima(H: np.ndarray, me: int, m: int) -> np.ndarray:
    """(m,) minimum bisector distance of the held features to every other cell (inf if none)."""
    out = np.full(m, np.inf)
    if len(H):
        mins = H.min(axis=0)
        out[:] = mins
    out[me] = np.inf
    return out


def units_from_clusters(labels: np.ndarray) -> np.ndarray:
    """Paper mode: a unit is a local cluster."""
    return np.asarray(labels, dtype=np.int64).copy()


def units_from_tree(labels: np.ndarray, parent: np.ndarray) -> np.ndarray:
    """Lean mode: clusters joined by any reported tree edge (merged or not)."""
    n = len(labels)
    root = np.arange(n)

    def find(i):
        while root[i] != i:
            root[i] = root[root[i]]
            i = root[i]
        return i

    # clusters first
    first = {}
    for k, lab in enumerate(labels.tolist()):
        if lab in first:
            root[find(k)] = find(first[lab])
        else:
            first[lab] = k
    for k in np.flatnonzero(parent >= 0).tolist():
        a, b = find(k), find(int(parent[k]))
        if a != b:
            root[max(a, b)] = min(a, b)
    return tree.canonical_labels(np.array([find(k) for k in range(n)], dtype=np.int64))


def unit_targets(units: np.ndarray, contested: np.ndarray, me: int, below: Optional[int] = None) -> np.ndarray:
    """Target agent of every unit: the lowest of ``me`` and the agents any member is contested with.

    ``below``: only agents with index < below count (the cascade hands down
    only). Returns an array indexed by unit id.
    """
    n_units = int(units.max()) + 1 if len(units) else 0
    target = np.full(n_units, me, dtype=np.int64)
    if len(units) == 0:
        return target
    C = contested.copy()
    if below is not None:
        C[:, below:] = False
    m = C.shape[1]
    first = np.where(C.any(axis=1), np.argmax(C, axis=1), m)  # lowest contested agent of each feature
    best = np.full(n_units, m, dtype=np.int64)
    np.minimum.at(best, units, first)
    return np.minimum(target, best)
