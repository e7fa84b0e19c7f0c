"""A small, obviously correct dense QuickMatch used as the oracle in tests.

Straight from the reference semantics, with full n x n float64 matrices (scipy
cdist), no truncation, no candidate lists; only usable for a few thousand
features. It shares no code with dqm.core.
"""
import numpy as np
from scipy.spatial.distance import cdist


def dense_quickmatch(X, image_ids, rho, ratio_density=0.25, kernel="gaussian", parent_mode="any"):
    X = np.asarray(X, dtype=np.float64)
    ids = np.asarray(image_ids)
    n = len(X)
    D = cdist(X, X)
    same = ids[:, None] == ids[None, :]
    # 1. sigma: nearest other feature of the same image
    Ds = np.where(same, D, np.inf)
    np.fill_diagonal(Ds, np.inf)
    sigma = Ds.min(axis=1)
    lonely = ~np.isfinite(sigma)
    if lonely.any():
        finite = sigma[~lonely]
        sigma[lonely] = np.median(finite) if len(finite) else 0.0
    # 2. density, self term included; zero sigma -> indicator of distance 0
    K = np.zeros((n, n))
    for i in range(n):  # contributor i, row of K
        if sigma[i] > 0:
            if kernel == "gaussian":
                K[i] = np.exp(-D[i] ** 2 / (2 * (ratio_density * sigma[i]) ** 2))
            else:
                K[i] = np.maximum(0.0, 1.0 - D[i] ** 2 / sigma[i] ** 2)
        else:
            K[i] = (D[i] == 0).astype(float)
    density = K.sum(axis=0)
    # exact duplicates have equal densities by definition; remove rounding noise
    for i in range(n):
        dup = np.flatnonzero(D[i] == 0)
        density[dup] = density[dup.min()]
    # 3. parent: nearest feature ranking above (higher density, then lower index)
    parent = np.full(n, -1)
    pdist = np.full(n, np.inf)
    for j in range(n):
        above = (density > density[j]) | ((density == density[j]) & (np.arange(n) < j))
        if parent_mode == "other-image":
            above &= ids != ids[j]
        cand = np.flatnonzero(above)
        if len(cand):
            dj = D[j, cand]
            best = cand[dj == dj.min()].min()
            parent[j] = best
            pdist[j] = D[j, best]
    # 4. break/merge, shortest edge first (ties: lower child index)
    label = np.arange(n)
    scale = sigma.copy()
    images = {i: {ids[i]} for i in range(n)}
    for j in sorted(np.flatnonzero(parent >= 0), key=lambda j: (pdist[j], j)):
        a, b = label[j], label[parent[j]]
        if a == b:
            continue
        if pdist[j] < rho * min(scale[a], scale[b]) and not (images[a] & images[b]):
            label[label == b] = a
            images[a] = images[a] | images[b]
            scale[a] = min(scale[a], scale[b])
    return label, sigma, density, parent, pdist


def same_partition(a, b):
    """True if two label vectors define the same partition (identical up to renaming)."""
    a = np.asarray(a)
    b = np.asarray(b)
    if a.shape != b.shape:
        return False
    pairs = set(zip(a.tolist(), b.tolist()))
    return len(pairs) == len(set(a.tolist())) == len(set(b.tolist()))
