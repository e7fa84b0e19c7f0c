"""Geometric verification of clusters: split off members that no image-pair geometry supports.

For every image pair, the matches the clusters imply (every two members of a cluster, see
:func:`dqm.vision.colmap.cluster_pairs`) are fitted with OpenCV's USAC (MAGSAC++) twice: a
fundamental matrix and a homography. The model is chosen the way COLMAP chooses: when the
homography explains more than ``max_h_inlier_ratio`` (0.8) of the fundamental matrix's
inliers, the pair is planar or a pure rotation and the homography's inliers count; otherwise
the fundamental matrix's. A pair is *verified* when it has at least ``min_inliers`` (15,
COLMAP's ``min_num_inliers``) inliers; the matches of unverified pairs carry no evidence.

Then, cluster by cluster, a member whose verified matches are more often outliers than inliers
is split off into a cluster of its own, the worst first, recounting after each split. Only
splitting happens, so the result is still a partition (C1) with at most one feature per image
per cluster (C2).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

import numpy as np

from ..validation import InputError
from .baselines import canonical
from .colmap import cluster_pairs

#: COLMAP's defaults (TwoViewGeometryOptions): min_num_inliers, max_H_inlier_ratio
MIN_INLIERS = 15
MAX_H_INLIER_RATIO = 0.8


@dataclass
class VerifyStats:
    n_pairs: int  # image pairs with cluster matches
    n_verified: int  # pairs with >= min_inliers inliers
    n_planar: int  # verified pairs decided by the homography
    n_matches: int
    n_inliers: int  # inlier matches of verified pairs
    n_outliers: int  # outlier matches of verified pairs
    n_split: int  # features split off into clusters of their own


def _fit_pair(p: np.ndarray, q: np.ndarray, threshold: float, confidence: float) -> Tuple[np.ndarray, bool]:
    """Inlier mask of the chosen two-view model and whether it was the homography."""
    import cv2

    n = len(p)
    if n < 8:
        return np.zeros(n, bool), False
    F, mf = cv2.findFundamentalMat(p, q, cv2.USAC_MAGSAC, threshold, confidence, 10000)
    inl_f = mf.ravel().astype(bool) if F is not None and mf is not None else np.zeros(n, bool)
    H, mh = cv2.findHomography(p, q, cv2.USAC_MAGSAC, threshold, None, 10000, confidence)
    inl_h = mh.ravel().astype(bool) if H is not None and mh is not None else np.zeros(n, bool)
    if inl_h.sum() > MAX_H_INLIER_RATIO * max(inl_f.sum(), 1):
        return inl_h, True
    return inl_f, False


def verify_clusters(labels, image_ids, keypoints, *, threshold: float = 4.0, confidence: float = 0.999,
                    min_inliers: int = MIN_INLIERS, seed: int = 0) -> Tuple[np.ndarray, VerifyStats]:
    """Labels with geometrically unsupported members split off, and what was done (module docstring).

    ``keypoints``: (n, >= 2) pixel coordinates; ``threshold``: the RANSAC residual in pixels
    (COLMAP's ``max_error`` is 4 px); ``seed`` seeds OpenCV's RNG so the result repeats.
    """
    import cv2

    labels = np.asarray(labels, np.int64)
    ids = np.asarray(image_ids, np.int64)
    kp = np.asarray(keypoints, np.float64)
    n = len(labels)
    if ids.shape != (n,) or kp.ndim != 2 or kp.shape[0] != n or kp.shape[1] < 2:
        raise InputError(f"verify needs keypoints (n, 2..) and image ids (n,) for the {n} labels; "
                         f"got {kp.shape} and {ids.shape}")
    if not np.isfinite(kp[:, :2]).all():
        raise InputError("verify: keypoints contain NaN or inf")
    if threshold <= 0 or not 0 < confidence < 1 or min_inliers < 8:
        raise InputError("verify: threshold must be > 0, confidence in (0, 1), min_inliers >= 8")
    cv2.setRNGSeed(int(seed))
    pairs = cluster_pairs(labels, ids)
    edges_in, edges_out = [], []
    n_ver = n_planar = n_matches = 0
    for (_a, _b), m in sorted(pairs.items()):
        n_matches += len(m)
        inl, planar = _fit_pair(kp[m[:, 0], :2].astype(np.float32), kp[m[:, 1], :2].astype(np.float32),
                                threshold, confidence)
        if inl.sum() < min_inliers:
            continue
        n_ver += 1
        n_planar += planar
        edges_in.append(m[inl])
        edges_out.append(m[~inl])
    e_in = np.concatenate(edges_in) if edges_in else np.zeros((0, 2), np.int64)
    e_out = np.concatenate(edges_out) if edges_out else np.zeros((0, 2), np.int64)
    new = labels.copy()
    alive = np.ones(n, bool)
    next_label = int(labels.max()) + 1 if n else 0
    n_split = 0
    while True:
        ok_in = alive[e_in[:, 0]] & alive[e_in[:, 1]]
        ok_out = alive[e_out[:, 0]] & alive[e_out[:, 1]]
        good = np.bincount(e_in[ok_in].ravel(), minlength=n)
        bad = np.bincount(e_out[ok_out].ravel(), minlength=n)
        score = bad - good
        cand = np.flatnonzero(alive & (score > 0))
        if len(cand) == 0:
            break
        # the worst member of each cluster (highest score, then lowest index) is split off
        o = cand[np.lexsort((cand, -score[cand], new[cand]))]
        first = np.r_[True, new[o][1:] != new[o][:-1]]
        worst = o[first]
        new[worst] = next_label + np.arange(len(worst))  # each into a cluster of its own
        next_label += len(worst)
        alive[worst] = False
        n_split += len(worst)
    out = canonical(new)  # numbered by each cluster's lowest feature index, as quickmatch does
    stats = VerifyStats(len(pairs), n_ver, n_planar, n_matches, len(e_in), len(e_out), n_split)
    return out, stats
