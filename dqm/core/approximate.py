"""Approximate QuickMatch for sets too large for the exact O(n^2) pass.

Exact QuickMatch visits every pair of features (100k features: 18-36 s on 2
cores, so 1M would take 30-60 min). The approximate mode replaces the
all-pairs pass by a k-nearest-neighbour graph from faiss: an inverted-file
index with sqrt(n) lists, 8-bit direct codes for uint8 SIFT, chosen over HNSW
by measurement (docs/quickmatch.md; 1M features in about 3 minutes):

* ``sigma`` stays exact (the nearest other feature of the same image: a
  blocked GEMM inside each image, which is cheap because images are small);
* the density of j sums the kernel terms of j's ``n_neighbors`` nearest
  neighbours (plus the self term); terms of farther features are dropped;
* the parent of j is the nearest of those neighbours that ranks above j and
  lies within ``rho * sigma_j``;
* break/merge is the exact one (:func:`dqm.core.tree.merge_clusters`), so C1
  and C2 hold exactly.

Where it loses (measured in scripts/bench_quickmatch.py, co-membership F1
0.993-1.000 against exact): a feature whose true parent is not among its k
nearest neighbours (in a cluster seen in more than k images, or missed by the
index) becomes a root, and the truncated densities can swap the order of two
features of nearly equal density.

Deterministic for a given input, seed and thread count (k-means training is
seeded; its parallel sums depend on the number of threads).
"""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np

from .. import validation as V

#: inverted lists per feature count: nlist = NLIST_FACTOR * sqrt(n), a power of two
NLIST_FACTOR = 1
#: lists probed per query (16 of 1024 at 1M features: 1.6% of the data scanned per query)
DEFAULT_NPROBE = 16
#: k-means training sample per list
TRAIN_PER_LIST = 40
#: below this many features the graph is exact (faiss IndexFlatL2): cheaper than training
EXACT_BELOW = 4096
#: queries per faiss search call (progress granularity)
QUERY_BATCH = 1 << 15


def require_faiss():
    """faiss, or one clear line saying how to install it."""
    try:
        import faiss
    except ImportError:
        raise V.InputError("the approximate mode needs faiss-cpu, which is not installed: "
                           "pip install 'dqm[approx]' (or pip install faiss-cpu)") from None
    return faiss


def n_lists(n: int) -> int:
    """Inverted lists for ``n`` features: about ``NLIST_FACTOR * sqrt(n)``, a power of two, at most n / 40
    (k-means wants ~40 training points per list)."""
    target = max(1.0, min(NLIST_FACTOR * np.sqrt(n), n / TRAIN_PER_LIST))
    return int(2 ** int(np.round(np.log2(target))))


def knn_graph(X: np.ndarray, k: int, *, n_threads: int, nprobe: int = DEFAULT_NPROBE, seed: int = 0,
              progress=None) -> Tuple[np.ndarray, np.ndarray]:
    """The ``k`` nearest other features of every feature (approximate).

    ``X``: uint8 descriptors (SIFT) are indexed as they are, one byte per
    component (faiss' 8-bit direct scalar quantizer: exact distances, 2.9x
    faster scans than float32 and a quarter of the memory, measured at 100k);
    any other data as float32 (``IndexIVFFlat``).

    Returns ``(neighbors, sq_distances)``, each (n, k): int64 indices (-1
    where fewer than k were found) and float32 squared distances (inf there).
    The feature itself is never among its neighbours.
    """
    faiss = require_faiss()
    threads_before = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(int(n_threads))
    try:
        return _knn_graph(faiss, X, k, nprobe, seed, progress)
    finally:
        faiss.omp_set_num_threads(threads_before)


def _knn_graph(faiss, X, k, nprobe, seed, progress):
    n, dim = X.shape
    k = int(min(k, n - 1))
    nlist = n_lists(n)
    quantizer = faiss.IndexFlatL2(dim)
    if n < EXACT_BELOW:  # small: an exact graph costs less than training an index
        index = quantizer
    elif X.dtype == np.uint8:
        index = faiss.IndexIVFScalarQuantizer(quantizer, dim, nlist, faiss.ScalarQuantizer.QT_8bit_direct,
                                              faiss.METRIC_L2, False)  # codes are the bytes, not residuals
    else:
        index = faiss.IndexIVFFlat(quantizer, dim, nlist, faiss.METRIC_L2)
    if index is not quantizer:
        index.cp.seed = int(seed)
        rng = np.random.default_rng(seed)
        sample = np.sort(rng.choice(n, size=min(n, TRAIN_PER_LIST * nlist), replace=False))
        index.train(np.ascontiguousarray(X[sample], dtype=np.float32))
        index.nprobe = int(min(nprobe, nlist))
    for s in range(0, n, QUERY_BATCH):
        index.add(np.ascontiguousarray(X[s:s + QUERY_BATCH], dtype=np.float32))
    nbr = np.empty((n, k), dtype=np.int64)
    dist = np.empty((n, k), dtype=np.float32)
    for s in range(0, n, QUERY_BATCH):
        e = min(n, s + QUERY_BATCH)
        sq, found = index.search(np.ascontiguousarray(X[s:e], dtype=np.float32), k + 1)
        nbr[s:e], dist[s:e] = _drop_self(found, sq, np.arange(s, e))
        if progress is not None:
            progress(e, n)
    return nbr, dist


def _drop_self(found: np.ndarray, sq: np.ndarray, own: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Remove each row's own index (or, when absent, its last entry) from k+1 results."""
    drop = found == own[:, None]
    first = drop & (np.cumsum(drop, axis=1) == 1)  # an index can appear only once, but be safe
    missing = ~first.any(axis=1)
    first[missing, -1] = True
    rows, kk = found.shape[0], found.shape[1] - 1
    nbr = found[~first].reshape(rows, kk)
    dist = sq[~first].reshape(rows, kk).astype(np.float32)
    dist[nbr < 0] = np.inf
    return nbr, dist


def knn_density_others(nbr: np.ndarray, sq_dist: np.ndarray, weights: np.ndarray, active: np.ndarray,
                       kernel: str) -> np.ndarray:
    """Density without the self term from the neighbour graph: the kernel terms of each
    feature's neighbours (contributor weights as in :func:`dqm.core.pairs.kernel_pass`)."""
    out = np.zeros(len(nbr))
    step = 1 << 16  # rows per chunk: the temporaries stay near 100 MiB
    for s in range(0, len(nbr), step):
        nb = nbr[s:s + step]
        valid = nb >= 0
        src = np.where(valid, nb, 0)
        arg = np.where(valid, sq_dist[s:s + step], 0.0)  # no inf * 0 where a neighbour is missing
        arg *= weights[src]
        terms = np.exp(-arg) if kernel == "gaussian" else np.maximum(0.0, 1.0 - arg)
        terms *= active[src] * valid
        out[s:s + step] = terms.sum(axis=1)
    return out


def graph_edges(nbr: np.ndarray, sq_dist: np.ndarray, radius: np.ndarray,
                image_index: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate tree edges ``(child, cand, distance)`` of the graph: neighbours within the
    child's radius (and outside its image when ``image_index`` is given)."""
    n, k = nbr.shape
    out = ([], [], [])
    step = 1 << 16
    for s in range(0, n, step):
        nb = nbr[s:s + step]
        child = np.repeat(np.arange(s, s + len(nb), dtype=np.int64), k)
        cand = nb.ravel()
        dist = np.sqrt(sq_dist[s:s + step].ravel().astype(np.float64))
        keep = (cand >= 0) & (dist < radius[child])
        if image_index is not None:
            keep &= image_index[child] != image_index[np.maximum(cand, 0)]
        for part, values in zip(out, (child, cand, dist)):
            part.append(values[keep])
    return tuple(np.concatenate(part) for part in out)
