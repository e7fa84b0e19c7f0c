"""Geometric verification of clusters: split off members that no image-pair geometry supports.

For every image pair, the matches the clusters imply (every two members of a cluster, see
:func:`dqm.vision.colmap.cluster_pairs`) are fitted with OpenCV's USAC (MAGSAC++) twice: a
fundamental matrix and a homography. The pair's configuration and its inliers follow COLMAP's
two-view model selection (``EstimateUncalibratedTwoViewGeometry``; dqm's features carry no
intrinsics, so the calibrated case is not tried): when the homography explains more than
``max_H_inlier_ratio`` (0.8) of the fundamental matrix's inliers, the pair is *planar or
panoramic* (a dominant plane, or a pure rotation), otherwise *uncalibrated* (general 3-D); either
way the inliers are those of the model that has more of them (the homography's only when it has
more than the fundamental matrix's). A pair is *verified* when it has at least ``min_inliers``
(15, COLMAP's ``min_num_inliers``) inliers; the matches of unverified pairs carry no evidence.
Before this rule, a planar-or-panoramic pair counted the homography's inliers, fewer than the
fundamental matrix's on a 3-D scene with a dominant plane (39 of entry-P10's 45 pairs): correct
members off the plane were split off.

Then, cluster by cluster, a member whose verified matches are outliers more than twice as often
as inliers (``MARGIN``) is split off into a cluster of its own, the worst first (highest
outliers - 2 x inliers), recounting after each split. The margin keeps members that the
geometry judges ambiguously: on CMU hotel, whose hand-labelled points sit 4-8 px off the fitted
models, a simple majority split 11 correct members and lowered F1; at margin 2 F1 moved by at
most 0.003 on the other image sets (docs/sfm.md). Only
splitting happens, so the result is still a partition (C1) with at most one feature per image
per cluster (C2).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Callable, Optional, Tuple

import numpy as np

from ..validation import InputError
from .baselines import canonical
from .colmap import cluster_pairs

LOG = logging.getLogger("dqm.vision")

#: COLMAP's defaults (TwoViewGeometryOptions): min_num_inliers, max_H_inlier_ratio, and its RANSAC's max_error
#: (px): the residual within which a match is an inlier
MIN_INLIERS = 15
DEFAULT_THRESHOLD = 4.0
MAX_H_INLIER_RATIO = 0.8
#: COLMAP's names of the two configurations dqm tells apart (TwoViewGeometry::ConfigurationType)
PLANAR = "planar_or_panoramic"
UNCALIBRATED = "uncalibrated"
#: a member is split off when its verified matches are outliers more than MARGIN times as often as inliers
MARGIN = 2


@dataclass(frozen=True)
class PairModel:
    """The two-view model of a verified image pair ``a < b``.

    ``kind`` "H": ``matrix`` maps image a's points to image b's (``y ~ H x``); "F": the
    fundamental matrix with ``y^T F x = 0`` (x in a, y in b); the model whose inliers count
    (module docstring). Pixel coordinates. ``inliers`` / ``outliers``: the implied matches
    (m, 2: feature in a, feature in b) that model accepted and rejected. ``config``:
    :data:`PLANAR` or :data:`UNCALIBRATED`; ``homography``: the fitted homography (a to b) of a
    planar-or-panoramic pair, None otherwise.
    """

    a: int
    b: int
    kind: str
    matrix: np.ndarray
    inliers: np.ndarray
    outliers: np.ndarray
    config: str = UNCALIBRATED
    homography: Optional[np.ndarray] = None

    def guide(self) -> "PairModel":
        """The model to search for new matches along: the homography of a planar-or-panoramic pair (a point
        transfer: a disc of candidates, where the fundamental matrix leaves a band), else this one."""
        if self.config == PLANAR and self.homography is not None and self.kind != "H":
            return replace(self, kind="H", matrix=self.homography)
        return self

    def sq_residuals(self, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
        """Squared residuals in px^2 of point pairs (xa in a, xb in b): the forward transfer error
        for a homography, the Sampson error for a fundamental matrix (COLMAP's residuals)."""
        return sq_residuals(self.kind, self.matrix, xa, xb)


def sq_residuals(kind: str, M: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Squared transfer error (``kind`` "H") or squared Sampson error ("F") of point pairs, px^2."""
    xa = np.asarray(xa, np.float64)[:, :2]
    xb = np.asarray(xb, np.float64)[:, :2]
    ha = np.c_[xa, np.ones(len(xa))]
    if kind == "H":
        p = ha @ M.T
        with np.errstate(divide="ignore", invalid="ignore"):
            d = p[:, :2] / p[:, 2:3] - xb
            out = (d * d).sum(axis=1)
        return np.where(np.isfinite(out), out, np.inf)
    hb = np.c_[xb, np.ones(len(xb))]
    fx = ha @ M.T  # epipolar lines in b
    fty = hb @ M  # epipolar lines in a
    num = (hb * fx).sum(axis=1) ** 2
    den = fx[:, 0] ** 2 + fx[:, 1] ** 2 + fty[:, 0] ** 2 + fty[:, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        out = num / den
    return np.where(np.isfinite(out), out, np.inf)


@dataclass
class VerifyStats:
    n_pairs: int  # image pairs with cluster matches
    n_verified: int  # pairs with >= min_inliers inliers
    n_planar: int  # verified pairs in the planar-or-panoramic configuration
    n_matches: int
    n_inliers: int  # inlier matches of verified pairs
    n_outliers: int  # outlier matches of verified pairs
    n_split: int  # features split off into clusters of their own


def _usac(estimate, *args):
    """``(model, mask)`` of an OpenCV USAC estimator, ``(None, None)`` where it finds no model. OpenCV 4 returns
    None then; OpenCV 5.1's MAGSAC++ instead fails an internal assertion (``!model.empty()`` in
    ``setModelParameters``) on some point sets it cannot fit (47 matches of two tiny generated images, several
    keypoints at one location: tests/vision/test_colmap.py): the same answer, no model. The points are checked
    before (finite float pixel coordinates), so an error here is the fit's."""
    import cv2

    try:
        return estimate(*args)
    except cv2.error as exc:
        LOG.debug("USAC found no model (%s)", str(exc).strip().splitlines()[-1] if str(exc).strip() else exc)
        return None, None


def _fit_pair(p: np.ndarray, q: np.ndarray, threshold: float, confidence: float):
    """COLMAP's two-view model selection (module docstring): the inlier mask, the kind ("H" or "F") and
    matrix of the model with more inliers (None: no fit), the configuration and the homography."""
    import cv2

    n = len(p)
    if n < 8:
        return np.zeros(n, bool), "F", None, UNCALIBRATED, None
    F, mf = _usac(cv2.findFundamentalMat, p, q, cv2.USAC_MAGSAC, threshold, confidence, 10000)
    if F is None or mf is None or F.shape != (3, 3):  # OpenCV may stack several solutions
        F, inl_f = None, np.zeros(n, bool)
    else:
        inl_f = mf.ravel().astype(bool)
    H, mh = _usac(cv2.findHomography, p, q, cv2.USAC_MAGSAC, threshold, None, 10000, confidence)
    inl_h = mh.ravel().astype(bool) if H is not None and mh is not None else np.zeros(n, bool)
    n_f, n_h = int(inl_f.sum()), int(inl_h.sum())
    planar = n_h > MAX_H_INLIER_RATIO * max(n_f, 1)
    config, homography = (PLANAR, np.asarray(H, np.float64)) if planar else (UNCALIBRATED, None)
    if n_h > n_f or F is None:
        return inl_h, "H", H, config, homography
    return inl_f, "F", F, config, homography


def check_geometry_inputs(labels, image_ids, keypoints, threshold: float, confidence: float, min_inliers: int,
                          what: str = "verify"):
    """The labels, image ids and keypoints as arrays, checked (one line naming the problem)."""
    labels = np.asarray(labels, np.int64)
    ids = np.asarray(image_ids, np.int64)
    kp = np.asarray(keypoints, np.float64)
    n = len(labels)
    if ids.shape != (n,) or kp.ndim != 2 or kp.shape[0] != n or kp.shape[1] < 2:
        raise InputError(f"{what} needs keypoints (n, 2..) and image ids (n,) for the {n} labels; "
                         f"got {kp.shape} and {ids.shape}")
    if not np.isfinite(kp[:, :2]).all():
        raise InputError(f"{what}: keypoints contain NaN or inf")
    if threshold <= 0 or not 0 < confidence < 1 or min_inliers < 8:
        raise InputError(f"{what}: threshold must be > 0, confidence in (0, 1), min_inliers >= 8")
    return labels, ids, kp


def fit_pairs(labels, image_ids, keypoints, *, threshold: float = DEFAULT_THRESHOLD, confidence: float = 0.999,
              min_inliers: int = MIN_INLIERS, seed: int = 0,
              progress: Optional[Callable[[int, int], None]] = None) -> Tuple[dict, int, int]:
    """The verified image pairs' models, ``{(a, b): PairModel}``, from the matches the clusters imply.

    Also returns the number of image pairs with matches and of matches. Inputs as in
    :func:`verify_clusters` (already checked arrays); ``progress(done, total)`` after each image pair.
    """
    import cv2

    cv2.setRNGSeed(int(seed))
    pairs = cluster_pairs(labels, image_ids)
    kp = keypoints
    models = {}
    n_matches = 0
    for k, ((a, b), m) in enumerate(sorted(pairs.items())):
        if progress is not None:
            progress(k, len(pairs))
        n_matches += len(m)
        inl, kind, M, config, H = _fit_pair(kp[m[:, 0], :2].astype(np.float32), kp[m[:, 1], :2].astype(np.float32),
                                 threshold, confidence)
        if M is None or inl.sum() < min_inliers:
            continue
        models[(a, b)] = PairModel(a, b, kind, np.asarray(M, np.float64), m[inl], m[~inl], config, H)
    if progress is not None:
        progress(len(pairs), len(pairs))
    return models, len(pairs), n_matches


def split_contradicted(labels: np.ndarray, models: dict) -> Tuple[np.ndarray, int]:
    """Split off, cluster by cluster and worst first, the members the verified pairs reject
    (module docstring); the labels numbered as quickmatch numbers them, and how many were split."""
    n = len(labels)
    e_in = np.concatenate([m.inliers for m in models.values()]) if models else np.zeros((0, 2), np.int64)
    e_out = np.concatenate([m.outliers for m in models.values()]) if models else np.zeros((0, 2), np.int64)
    new = labels.copy()
    alive = np.ones(n, bool)
    next_label = int(labels.max()) + 1 if n else 0
    n_split = 0
    while True:
        ok_in = alive[e_in[:, 0]] & alive[e_in[:, 1]]
        ok_out = alive[e_out[:, 0]] & alive[e_out[:, 1]]
        good = np.bincount(e_in[ok_in].ravel(), minlength=n)
        bad = np.bincount(e_out[ok_out].ravel(), minlength=n)
        score = bad - MARGIN * good
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
    return canonical(new), n_split  # numbered by each cluster's lowest feature index, as quickmatch does


def verify_stats(models: dict, n_pairs: int, n_matches: int, n_split: int) -> VerifyStats:
    """The counts of a verification from its fitted models."""
    return VerifyStats(n_pairs, len(models), sum(m.config == PLANAR for m in models.values()), n_matches,
                       sum(len(m.inliers) for m in models.values()), sum(len(m.outliers) for m in models.values()),
                       n_split)


def fit_and_split(labels, image_ids, keypoints, *, threshold: float = DEFAULT_THRESHOLD, confidence: float = 0.999,
                  min_inliers: int = MIN_INLIERS, seed: int = 0,
                  progress: Optional[Callable[[int, int], None]] = None) -> Tuple[np.ndarray, dict, VerifyStats]:
    """:func:`fit_pairs` then :func:`split_contradicted` on checked arrays: the split labels, the
    verified pairs' models and the counts (what :func:`verify_clusters` and guided growth share)."""
    models, n_pairs, n_matches = fit_pairs(labels, image_ids, keypoints, threshold=threshold, confidence=confidence,
                                           min_inliers=min_inliers, seed=seed, progress=progress)
    out, n_split = split_contradicted(labels, models)
    return out, models, verify_stats(models, n_pairs, n_matches, n_split)


def verify_clusters(labels, image_ids, keypoints, *, threshold: float = DEFAULT_THRESHOLD, confidence: float = 0.999,
                    min_inliers: int = MIN_INLIERS, seed: int = 0,
                    progress: Optional[Callable[[int, int], None]] = None) -> Tuple[np.ndarray, VerifyStats]:
    """Labels with geometrically unsupported members split off, and what was done (module docstring).

    ``keypoints``: (n, >= 2) pixel coordinates; ``threshold``: the RANSAC residual in pixels
    (COLMAP's ``max_error`` is 4 px); ``seed`` seeds OpenCV's RNG so the result repeats;
    ``progress(done, total)``: after each image pair fitted.
    """
    labels, ids, kp = check_geometry_inputs(labels, image_ids, keypoints, threshold, confidence, min_inliers)
    out, _, stats = fit_and_split(labels, ids, kp, threshold=threshold, confidence=confidence,
                                  min_inliers=min_inliers, seed=seed, progress=progress)
    return out, stats
