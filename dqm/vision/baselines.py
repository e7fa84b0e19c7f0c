"""The pairwise baselines QuickMatch is compared with, as the seed paper ran them.

1. **Pairwise matching** (:func:`pairwise_candidates`, :func:`pairwise_matches`):
   for every image pair (i, j), i < j, each feature of image i is matched to
   its nearest neighbour in image j (Euclidean, OpenCV's brute-force
   ``BFMatcher(NORM_L2)`` or FLANN's randomised kd-trees, 2 nearest neighbours)
   and the match is kept iff it passes Lowe's ratio test
   ``d1 < ratio * d2`` (ratio 0.75 by default). The nearest-neighbour search
   does not depend on the ratio, so it runs once and any ratio is a filter.
2. **Tracks** (:func:`build_tracks`): the union of all pairwise matches,
   connected components by union-find; a track that holds two features of one
   image violates C2 and is treated as SfM pipelines do:

   * ``"drop-track"`` (OpenMVG's ``TracksBuilder::Filter``): the whole track is
     discarded (its features become unmatched singletons);
   * ``"drop-later"`` (Theia's ``TrackBuilder``): the track keeps, per image,
     the feature that entered the correspondence list first, and the later
     ones become singletons.

   Either way the result is a partition (labels) like QuickMatch's.

Pairwise matches themselves are not a partition: they may violate C1 and C2
(see :func:`dqm.evaluation.consistency_violations`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Dict, Optional, Tuple

import numpy as np

from ..progress import ProgressArg, resolve_progress
from ..validation import InputError, check_choice, check_descriptors, check_image_ids

MATCHERS = ("bf", "flann")
TRACK_POLICIES = ("drop-track", "drop-later")
#: Lowe's ratio as used in the seed paper's baselines
DEFAULT_RATIO = 0.75
#: FLANN kd-tree settings (OpenCV's documented example: 5 trees, 50 checks)
FLANN_INDEX_PARAMS = {"algorithm": 1, "trees": 5}
FLANN_SEARCH_PARAMS = {"checks": 50}


@dataclass(frozen=True)
class PairwiseCandidates:
    """Nearest neighbour of every feature in every later image, with its Lowe ratio.

    Row k: feature ``query[k]`` (in image i) has nearest neighbour ``train[k]``
    (in image j > i) at distance ``distance[k]``; ``ratio[k] = d1 / d2`` with d2
    the distance to the second nearest neighbour in image j (``inf`` when image j
    has a single feature: the ratio test cannot be applied and rejects it;
    ``1`` when d1 = d2 = 0). Rows are ordered by image pair (i, j), then query.
    """

    query: np.ndarray
    train: np.ndarray
    distance: np.ndarray
    ratio: np.ndarray
    matcher: str
    n_features: int
    stats: Dict[str, float] = field(default_factory=dict, compare=False)

    def select(self, ratio: float = DEFAULT_RATIO) -> Tuple[np.ndarray, np.ndarray]:
        """Matches passing the ratio test ``d1 < ratio * d2``: arrays (a, b) of feature indices."""
        if not np.isfinite(ratio) or ratio <= 0:
            raise InputError(f"ratio must be a positive finite number, got {ratio!r}")
        keep = self.ratio < ratio
        return self.query[keep], self.train[keep]


def _flann_knn(q: np.ndarray, t: np.ndarray, k: int, seed: int):
    import cv2

    cv2.setRNGSeed(seed)
    m = cv2.FlannBasedMatcher(dict(FLANN_INDEX_PARAMS), dict(FLANN_SEARCH_PARAMS))
    return m.knnMatch(q, t, k=k)


def _in_new_thread(fn, *args):
    """``fn(*args, stop)`` run in a new thread; an interrupt here sets ``stop`` and waits for it to end.

    FLANN runs this way. OpenCV's kd-tree search takes its branch heap from a pool kept per
    thread, whose capacity only grows. After a search on a larger index, a search on a small one
    drops fewer branches and can return other neighbours: on CMU hotel (30 features per image)
    3 of 115,365 ratio-test matches changed after FLANN had run on the Oxford sets in the same
    process. A new thread starts with a new pool entry, as a fresh process does, so the result
    depends only on the input and the seed. OpenCV's RNG, which draws the trees, is per thread
    too: seeding it there leaves the caller's RNG alone.
    """
    import threading

    stop = threading.Event()
    box: dict = {}

    def work():
        try:
            fn(*args, stop)
        except BaseException as e:  # noqa: BLE001 - re-raised in the caller's thread
            box["err"] = e

    th = threading.Thread(target=work, name="dqm-flann", daemon=True)
    th.start()
    try:
        while th.is_alive():
            th.join(0.1)
    finally:
        stop.set()
        th.join()
    if "err" in box:
        raise box["err"]


def _knn2(matcher: str, q: np.ndarray, t: np.ndarray, seed: int):
    """Two nearest neighbours in ``t`` of every row of ``q``: (idx1, d1, d2) arrays."""
    k = 2 if len(t) >= 2 else 1
    if matcher == "bf":
        import cv2

        res = cv2.BFMatcher(cv2.NORM_L2).knnMatch(q, t, k=k)
    else:
        res = _flann_knn(q, t, k, seed)
    idx = np.full(len(q), -1, np.int64)
    d1 = np.full(len(q), np.inf)
    d2 = np.full(len(q), np.inf)
    for r in res:
        if not r:
            continue
        qi = r[0].queryIdx
        idx[qi] = r[0].trainIdx
        d1[qi] = r[0].distance
        if len(r) > 1:
            d2[qi] = r[1].distance
    return idx, d1, d2


def _match_pairs(matcher, X, members, pairs, seed, bar, out, stop=None) -> None:
    """Two-nearest-neighbour search of every image pair, appended to ``out`` = (Q, T, D, R) lists."""
    Q, T, D, R = out
    for k, (x, y) in enumerate(pairs):
        if stop is not None and stop.is_set():
            return
        qa, ta = members[x], members[y]
        if len(qa) and len(ta):
            idx, d1, d2 = _knn2(matcher, X[qa], X[ta], seed)
            ok = idx >= 0
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(d2 > 0, d1 / d2, np.where(d1 > 0, np.inf, 1.0))
            ratio[np.isinf(d2)] = np.inf  # no second neighbour: the test cannot be applied
            Q.append(qa[ok])
            T.append(ta[idx[ok]])
            D.append(d1[ok])
            R.append(ratio[ok])
        if bar is not None:
            bar(k + 1, len(pairs))


def pairwise_candidates(descriptors, image_ids, matcher: str = "bf", *, seed: int = 0,
                        progress: ProgressArg = None) -> PairwiseCandidates:
    """Two-nearest-neighbour search for every image pair (i < j, queries from image i).

    ``matcher``: ``"bf"`` (exact, OpenCV brute force) or ``"flann"`` (OpenCV
    FLANN kd-trees, approximate; the searches of one call run in a new thread with
    OpenCV's RNG seeded from ``seed`` before each index, so the result depends only
    on the input and the seed, not on what ran before in the process).
    """
    check_choice(matcher, "matcher", MATCHERS)
    X = check_descriptors(descriptors).astype(np.float32)
    ids = check_image_ids(image_ids, len(X))
    t0 = time.perf_counter()
    images = np.unique(ids)
    members = [np.flatnonzero(ids == i) for i in images]
    pairs = [(x, y) for x in range(len(images)) for y in range(x + 1, len(images))]
    bar = resolve_progress(progress, f"{matcher} matching")
    Q, T, D, R = [], [], [], []
    if matcher == "flann":
        _in_new_thread(_match_pairs, matcher, X, members, pairs, seed, bar, (Q, T, D, R))
    else:
        _match_pairs(matcher, X, members, pairs, seed, bar, (Q, T, D, R))
    cat = (lambda v, dt: np.concatenate(v).astype(dt)) if Q else (lambda v, dt: np.zeros(0, dt))
    return PairwiseCandidates(
        query=cat(Q, np.int64), train=cat(T, np.int64), distance=cat(D, np.float64),
        ratio=cat(R, np.float64), matcher=matcher, n_features=len(X),
        stats={"time_knn": time.perf_counter() - t0, "n_image_pairs": float(len(pairs))},
    )


def pairwise_matches(descriptors, image_ids, matcher: str = "bf", ratio: float = DEFAULT_RATIO,
                     *, seed: int = 0) -> Tuple[np.ndarray, np.ndarray]:
    """Ratio-test matches of every image pair: arrays (a, b) of feature indices."""
    return pairwise_candidates(descriptors, image_ids, matcher, seed=seed).select(ratio)


def canonical(labels: np.ndarray) -> np.ndarray:
    """Renumber labels 0, 1, ... in order of each cluster's lowest feature index."""
    labels = np.asarray(labels)
    if labels.size == 0:
        return np.zeros(0, np.int64)
    _, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
    rank = np.empty(len(first), np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    return rank[inverse.ravel()]


def connected_tracks(a, b, n: int) -> np.ndarray:
    """Union-find of the matches (a[k], b[k]) over n features: component label of every feature."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    a = np.asarray(a, np.int64)
    b = np.asarray(b, np.int64)
    if len(a) != len(b):
        raise InputError(f"match arrays differ in length ({len(a)} vs {len(b)})")
    if len(a) and (min(a.min(), b.min()) < 0 or max(a.max(), b.max()) >= n):
        raise InputError(f"match indices must lie in 0..{n - 1}")
    g = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n, n)).tocsr()
    _, comp = connected_components(g, directed=False)
    return canonical(comp)


def build_tracks(a, b, image_ids, policy: str = "drop-track") -> np.ndarray:
    """Multi-image tracks (labels, one per feature) from pairwise matches (a, b).

    ``policy`` says what happens to a track holding two features of one image
    (module doc): ``"drop-track"`` (OpenMVG) or ``"drop-later"`` (Theia, the
    order being first appearance in the interleaved list a[0], b[0], a[1], ...).
    """
    check_choice(policy, "policy", TRACK_POLICIES)
    ids = check_image_ids(image_ids, len(np.asarray(image_ids)))
    n = len(ids)
    comp = connected_tracks(a, b, n)
    if n == 0:
        return comp
    _, img = np.unique(ids, return_inverse=True)
    img = img.ravel().astype(np.int64)
    key = comp * (img.max() + 1) + img
    _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    dup = cnt[inv.ravel()] > 1  # feature shares its track with another of its image
    labels = comp.copy()
    singleton = np.arange(n) + comp.max() + 1  # fresh labels
    if policy == "drop-track":
        bad = np.zeros(comp.max() + 1, bool)
        bad[comp[dup]] = True
        drop = bad[comp]
    else:
        inter = np.empty(2 * len(a), np.int64)
        inter[0::2] = np.asarray(a, np.int64)
        inter[1::2] = np.asarray(b, np.int64)
        first = np.full(n, np.iinfo(np.int64).max)
        np.minimum.at(first, inter, np.arange(len(inter)))
        drop = np.zeros(n, bool)
        cand = np.flatnonzero(dup)
        if len(cand):
            # within each (track, image) group keep the feature that appeared first
            order = cand[np.lexsort((first[cand], key[cand]))]
            keep_first = np.r_[True, key[order][1:] != key[order][:-1]]
            drop[order[~keep_first]] = True
    labels[drop] = singleton[drop]
    return canonical(labels)


def match_tracks(descriptors, image_ids, matcher: str = "bf", policy: str = "drop-track",
                 ratio: float = DEFAULT_RATIO, *, seed: int = 0,
                 candidates: Optional[PairwiseCandidates] = None) -> np.ndarray:
    """Pairwise ratio-test matching followed by track building: labels of every feature."""
    if candidates is None:
        candidates = pairwise_candidates(descriptors, image_ids, matcher, seed=seed)
    a, b = candidates.select(ratio)
    return build_tracks(a, b, image_ids, policy)
