"""QuickMatch's tree: parents from candidate edges, then break/merge into clusters.

Small and separate from the API on purpose (as HDBSCAN keeps its tree code): it
takes plain arrays and returns plain arrays.

Order of features ("i ranks above j"): higher density, and for equal densities
the lower feature index. This total order replaces the original code's 1e-6
random noise, so the tree is deterministic and every feature but the top one has
a higher-ranked feature.

Parent of j: the nearest feature that ranks above j (optionally: from another
image); among equally near ones the lowest index.

Break/merge: edges in increasing distance (ties: lower child index first); the
clusters of child and parent merge iff ``d < rho * min(scale_child, scale_parent)``
(a cluster's scale is the minimum sigma of its members) and their image sets are
disjoint.
"""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np

from . import native


def ranks_above(density: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Boolean array: does feature ``a[k]`` rank above feature ``b[k]``?"""
    return rank_order(density[a], density[b], a, b)


def rank_order(da: np.ndarray, db: np.ndarray, ida: np.ndarray, idb: np.ndarray) -> np.ndarray:
    """The rank rule on values: higher density, then the lower index (or global id)."""
    return (da > db) | ((da == db) & (ida < idb))


def select_parents(
    n: int,
    child: np.ndarray,
    cand: np.ndarray,
    dist: np.ndarray,
    density: np.ndarray,
    use_native: bool = True,
) -> Tuple[np.ndarray, np.ndarray]:
    """Parent of every feature among candidate edges ``child[k] -> cand[k]`` at ``dist[k]``.

    The candidates must contain, for every child, every feature that ranks above
    it within the child's search radius (and may contain more). Features without
    a higher-ranked candidate get parent -1 and distance inf.
    """
    fast = native.nearest_above(n, child, cand, dist, density=density) if use_native else None
    if fast is not None:  # one pass, no temporary the size of the edges
        return fast[0], fast[1]
    keep = ranks_above(density, cand, child)
    parent, pdist, _ = nearest_candidates(child[keep], cand[keep], dist[keep], n, use_native=False)
    return parent, pdist


def nearest_candidates(child: np.ndarray, cand: np.ndarray, dist: np.ndarray,
                       n: int, tie: Optional[np.ndarray] = None,
                       use_native: bool = True) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The nearest candidate of every child (ties: the lowest candidate index or id, or the lowest
    ``tie[k]`` when given: e.g. arrival order where ``cand`` are storage slots; then the first edge).

    Returns ``(parent, distance, row)``, arrays of length n: -1, inf and -1
    where a child has no candidate; ``row`` is the chosen edge's position in
    the inputs. Natively in one pass where the kernel is built, else by grouping the edges by child.
    """
    fast = native.nearest_above(n, child, cand, dist, key=tie) if use_native and len(child) else None
    if fast is not None:
        return fast
    parent = np.full(n, -1, dtype=np.int64)
    pdist = np.full(n, np.inf)
    row = np.full(n, -1, dtype=np.int64)
    if len(child):
        sel = _first_nearest(np.asarray(child), np.asarray(dist), np.asarray(cand if tie is None else tie))
        parent[child[sel]] = cand[sel]
        pdist[child[sel]] = dist[sel]
        row[child[sel]] = sel
    return parent, pdist, row


def _first_nearest(child: np.ndarray, dist: np.ndarray, key: np.ndarray) -> np.ndarray:
    """Position of every child's first edge in (distance, key, position) order: what the first of each
    child in ``np.lexsort((key, dist, child))`` is, without sorting by distance and key. The edges are
    grouped by child with one stable sort (none when they already come child by child, as the fast
    engine gives them), then each group's smallest distance, among those its smallest key, among those the
    first position."""
    starts = np.flatnonzero(np.concatenate(([True], child[1:] != child[:-1])))
    if len(np.unique(child[starts])) == len(starts):  # already child by child (in any order of children)
        order = np.arange(len(child))
        c, d, k = child, dist, key
    else:
        order = np.argsort(child, kind="stable")
        c, d, k = child[order], dist[order], key[order]
        starts = np.flatnonzero(np.concatenate(([True], c[1:] != c[:-1])))
    group = np.repeat(np.arange(len(starts)), np.diff(np.append(starts, len(c))))
    at_min = d == np.minimum.reduceat(d, starts)[group]
    kk = np.where(at_min, k, k.max())  # off the minimum: a key no smaller than any (the keys' own dtype)
    best = at_min & (kk == np.minimum.reduceat(kk, starts)[group])
    # the first position of each group among its best (stable: positions rise within a group)
    pos = np.where(best, np.arange(len(c)), len(c))
    return order[np.minimum.reduceat(pos, starts)]


def merge_clusters(
    parent: np.ndarray,
    pdist: np.ndarray,
    sigma: np.ndarray,
    image_index: np.ndarray,
    rho: float,
    use_native: bool = True,
) -> np.ndarray:
    """Break/merge along tree edges; returns labels numbered by first member (0, 1, ...).

    Natively when the kernel is built (:func:`dqm.core.native.merge_roots`), else the Python loop
    (``use_native=False``); both decide every merge with the same doubles, so the labels are the same."""
    n = len(parent)
    edges = np.flatnonzero(parent >= 0)
    order = edges[np.lexsort((edges, pdist[edges]))]
    if use_native:
        roots = native.merge_roots(n, order, parent[order], pdist[order], sigma, image_index, rho)
        if roots is not None:
            return canonical_labels(roots)
    # the loop runs on Python lists (scalar access to numpy arrays costs several times more); the values,
    # float64 distances and scales, are the same doubles
    root = list(range(n))
    scale = sigma.astype(np.float64).tolist()
    image_of = np.asarray(image_index).tolist()
    images = [None] * n  # lazily created sets; None means {image_of[i]}

    def find(i: int) -> int:
        r = i
        while root[r] != r:
            r = root[r]
        while root[i] != r:  # path compression
            nxt = root[i]
            root[i] = r
            i = nxt
        return r

    for j, p, d in zip(order.tolist(), parent[order].tolist(), pdist[order].astype(np.float64).tolist()):
        rj, rp = find(j), find(p)
        if rj == rp:
            continue
        if not d < rho * min(scale[rj], scale[rp]):
            continue
        sj = images[rj] if images[rj] is not None else {image_of[rj]}
        sp = images[rp] if images[rp] is not None else {image_of[rp]}
        if len(sj) > len(sp):
            sj, sp = sp, sj
            rj, rp = rp, rj
        if not sj.isdisjoint(sp):
            continue
        sp |= sj
        root[rj] = rp
        images[rp] = sp
        images[rj] = None
        scale[rp] = min(scale[rp], scale[rj])
    roots = np.array([find(i) for i in range(n)], dtype=np.int64) if n else np.zeros(0, np.int64)
    return canonical_labels(roots)


def canonical_labels(labels: np.ndarray) -> np.ndarray:
    """Renumber labels 0, 1, ... in order of each cluster's lowest feature index."""
    labels = np.asarray(labels)
    if labels.size == 0:
        return np.zeros(0, dtype=np.int64)
    _, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    return rank[inverse.ravel()]


def member_pairs(labels: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Every two members ``(i, j)``, ``i < j``, of every cluster of ``labels``: cluster by cluster in label
    order, each cluster's pairs in row order. Clusters of one size are expanded at once (a table of their
    members), so the cost is in the pairs, not in a loop over clusters."""
    labels = np.asarray(labels).ravel()
    empty = np.zeros(0, np.int64)
    if len(labels) < 2:
        return empty, empty
    order = np.argsort(labels, kind="stable")  # members of a cluster in row order
    lab = labels[order]
    starts = np.flatnonzero(np.r_[True, lab[1:] != lab[:-1]])
    sizes = np.diff(np.r_[starts, len(lab)])
    first, second, cluster = [], [], []
    for size in np.unique(sizes[sizes >= 2]).tolist():
        which = np.flatnonzero(sizes == size)
        members = order[starts[which][:, None] + np.arange(size)]
        i, j = np.triu_indices(size, 1)
        first.append(members[:, i].ravel())
        second.append(members[:, j].ravel())
        cluster.append(np.repeat(which, len(i)))
    if not first:
        return empty, empty
    o = np.argsort(np.concatenate(cluster), kind="stable")
    return np.concatenate(first)[o].astype(np.int64), np.concatenate(second)[o].astype(np.int64)
