"""The parent forest across cells: fragments, crossing components, and their replay.

After the balanced mode's parent step every owner knows each of its features'
parent (the nearest higher-ranked feature within rho sigma, or none) and the
parent's owner. Only these edges can merge (dqm.core.tree), and the merge
decisions of one tree component depend only on that component's edges, in the
engine's global order (distance, then child index).

* A **fragment** is a connected piece of an owner's features under its local
  parent edges; its key is the global id of its root (the member whose parent
  is foreign or absent).
* A **crossing edge** joins a fragment root to a parent owned elsewhere. The
  parent's owner learns of it (notify round) and reports, per crossing edge,
  ``(child fragment key, child's agent, parent fragment key)`` to the leader.
* The leader joins fragments along these edges (connected components) and
  assigns every component that spans agents to the lowest agent involved.
* Fragments that touch no crossing edge are whole components: their owner
  replays them at once. Assigned components travel as edge lists (ids, image
  ids, sigma, parent, distance; no descriptors) and are replayed there.
"""
from __future__ import annotations

from typing import Tuple

import numpy as np

from ..core import tree


def fragment_roots(local_parent: np.ndarray) -> np.ndarray:
    """Index of every feature's fragment root, following local parent pointers (-1: none)."""
    n = len(local_parent)
    up = np.where(local_parent >= 0, local_parent, np.arange(n))
    root = up.copy()
    while True:  # pointer jumping: O(log depth) passes
        nxt = root[root]
        if np.array_equal(nxt, root):
            return root
        root = nxt


def components(k: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Connected components of ``k`` nodes joined by the edges ``(u, v)``: every node's label, the lowest node
    of its component. Min-label propagation along the edges with pointer jumping, in numpy (scipy.sparse's
    import alone took the leader 0.3 s of a job); passes grow with the components' depth, which the parent
    forest keeps small."""
    label = np.arange(k, dtype=np.int64)
    u = np.asarray(u, np.int64)
    v = np.asarray(v, np.int64)
    while True:
        before = label.copy()
        low = np.minimum(label[u], label[v])
        np.minimum.at(label, label[u], low)  # a root takes the lowest label its edges reach
        np.minimum.at(label, label[v], low)
        label = fragment_roots(label)  # every node points at its root (a root points at itself)
        if np.array_equal(label, before):
            return label


def assign_components(child_key: np.ndarray, child_agent: np.ndarray, parent_key: np.ndarray,
                      parent_agent: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The leader's step: ``(keys, agents, targets)`` of every fragment on a crossing edge.

    Fragments joined by crossing edges form components; each component goes
    to the lowest agent among its fragments' owners.
    """
    keys_all = np.concatenate([child_key, parent_key]).astype(np.int64)
    agents_all = np.concatenate([child_agent, parent_agent]).astype(np.int64)
    if len(keys_all) == 0:
        z = np.zeros(0, np.int64)
        return z, z, z
    keys, first, inv = np.unique(keys_all, return_index=True, return_inverse=True)
    inv = inv.ravel()
    agents = agents_all[first]
    e = len(child_key)
    comp = components(len(keys), inv[:e], inv[e:])
    lowest = np.full(len(keys), np.iinfo(np.int64).max)
    np.minimum.at(lowest, comp, agents)
    return keys, agents, lowest[comp]


def replay(ids: np.ndarray, image_ids: np.ndarray, sigma: np.ndarray, parent_ids: np.ndarray,
           parent_distance: np.ndarray, rho: float) -> Tuple[np.ndarray, int]:
    """Break/merge of whole components given as edge lists; ``(labels, missing parents)``.

    ``ids`` sorted increasingly (they play the role of the engine's feature
    indices in its tie rule); ``parent_ids`` global (-1: none). A parent that is
    not in the set is counted and treated as none (an inconsistent input).
    """
    n = len(ids)
    if n == 0:
        return np.zeros(0, np.int64), 0
    pos = np.searchsorted(ids, parent_ids)
    pos = np.minimum(pos, n - 1)
    found = (parent_ids >= 0) & (ids[pos] == parent_ids)
    missing = int(((parent_ids >= 0) & ~found).sum())
    local_parent = np.where(found, pos, -1)
    pdist = np.where(found, parent_distance, np.inf)
    _, img = np.unique(image_ids, return_inverse=True)
    return tree.merge_clusters(local_parent, pdist, np.asarray(sigma, np.float64), img.ravel(), rho), missing
