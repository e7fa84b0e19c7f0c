"""Scoring clusters (or pairwise matches) against ground truth.

Definitions used everywhere in dqm:

* A cluster implies a match for every pair of its features (in two different
  images). Pairwise matchers give their pairs directly.
* **Landmark truth** (every feature has a point id, -1 = unknown point): a
  predicted pair is correct iff both have the same id >= 0. Recall is against
  all same-id pairs.
* **Homography truth** (planar scenes): a pair (a in image i, b in image j) is
  correct iff ``||H_ij x_a - x_b|| <= tol`` pixels. Recall is against the
  one-to-one ground truth: per image pair, the greedy (smallest error first)
  one-to-one matching among all feature pairs within ``tol``. Recall is the
  fraction of those correspondences that were predicted (a correct predicted
  pair outside the one-to-one matching, e.g. a second keypoint at the same
  spot, counts for precision only).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, Tuple

import numpy as np


@dataclass(frozen=True)
class Scores:
    precision: float
    recall: float
    f1: float
    n_predicted: int
    n_correct: int
    n_truth: int

    def as_dict(self) -> Dict[str, float]:
        return dict(precision=self.precision, recall=self.recall, f1=self.f1,
                    n_predicted=self.n_predicted, n_correct=self.n_correct, n_truth=self.n_truth)


def _scores(n_pred: int, n_correct: int, n_truth: int, n_correct_for_recall: int | None = None) -> Scores:
    p = n_correct / n_pred if n_pred else 1.0
    rc = (n_correct if n_correct_for_recall is None else n_correct_for_recall) / n_truth if n_truth else 1.0
    rc = min(rc, 1.0)
    f = 2 * p * rc / (p + rc) if p + rc > 0 else 0.0
    return Scores(p, rc, f, int(n_pred), int(n_correct), int(n_truth))


def cluster_pairs(labels: np.ndarray, image_ids: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """All pairs (a, b), a < b, of features in one cluster and different images."""
    labels = np.asarray(labels)
    image_ids = np.asarray(image_ids)
    order = np.argsort(labels, kind="stable")
    lab = labels[order]
    starts = np.flatnonzero(np.r_[True, lab[1:] != lab[:-1]])
    ends = np.r_[starts[1:], len(lab)]
    big = np.flatnonzero(ends - starts > 1)
    A, B = [], []
    for s, e in zip(starts[big], ends[big]):
        m = np.sort(order[s:e])
        a, b = np.triu_indices(len(m), 1)
        A.append(m[a])
        B.append(m[b])
    if not A:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    a, b = np.concatenate(A), np.concatenate(B)
    keep = image_ids[a] != image_ids[b]
    return a[keep], b[keep]


def landmark_scores(a: np.ndarray, b: np.ndarray, point_ids: np.ndarray, image_ids: np.ndarray) -> Scores:
    """Pairwise precision/recall of predicted pairs against point ids (-1 = unknown)."""
    point_ids = np.asarray(point_ids)
    image_ids = np.asarray(image_ids)
    correct = (point_ids[a] == point_ids[b]) & (point_ids[a] >= 0)
    # truth: pairs with the same point id in different images
    known = point_ids >= 0
    n_truth = 0
    pid, img = point_ids[known], image_ids[known]
    if len(pid):
        keys = np.unique(np.stack([pid, img]), axis=1)  # one feature per (point, image) counts
        counts = np.bincount(np.unique(keys[0], return_inverse=True)[1].ravel())
        n_truth = int((counts * (counts - 1) // 2).sum())
    return _scores(len(a), int(correct.sum()), n_truth)


def cluster_scores_landmarks(labels, point_ids, image_ids) -> Scores:
    a, b = cluster_pairs(labels, image_ids)
    return landmark_scores(a, b, point_ids, image_ids)


def reprojection_error(H: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """||H xa - xb|| for (n, 2) point arrays."""
    p = np.c_[xa, np.ones(len(xa))] @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        q = p[:, :2] / p[:, 2:3]
    e = np.linalg.norm(q - xb, axis=1)
    return np.where(np.isfinite(e), e, np.inf)


def one_to_one_truth(H: np.ndarray, xa: np.ndarray, xb: np.ndarray, tol: float) -> Tuple[np.ndarray, np.ndarray]:
    """Greedy one-to-one ground-truth correspondences between two keypoint sets."""
    from scipy.spatial import cKDTree

    if len(xa) == 0 or len(xb) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    p = np.c_[xa, np.ones(len(xa))] @ H.T
    proj = p[:, :2] / p[:, 2:3]
    ok = np.isfinite(proj).all(axis=1)
    tree = cKDTree(xb)
    pairs = tree.query_ball_point(proj[ok], r=tol)
    ia, ib, err = [], [], []
    src = np.flatnonzero(ok)
    for k, lst in enumerate(pairs):
        for j in lst:
            ia.append(src[k])
            ib.append(j)
            err.append(np.linalg.norm(proj[src[k]] - xb[j]))
    if not ia:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ia, ib, err = np.array(ia), np.array(ib), np.array(err)
    order = np.lexsort((ib, ia, err))
    used_a, used_b, A, B = set(), set(), [], []
    for k in order:
        if ia[k] not in used_a and ib[k] not in used_b:
            used_a.add(ia[k])
            used_b.add(ib[k])
            A.append(ia[k])
            B.append(ib[k])
    return np.array(A, np.int64), np.array(B, np.int64)


def homography_scores(a, b, keypoints_xy, image_ids, homography: Callable[[int, int], np.ndarray],
                      tol: float = 5.0) -> Scores:
    """Pairwise precision/recall of predicted pairs on a planar scene (see module doc)."""
    a = np.asarray(a)
    b = np.asarray(b)
    xy = np.asarray(keypoints_xy, dtype=np.float64)[:, :2]
    image_ids = np.asarray(image_ids)
    imgs = np.unique(image_ids)
    n_correct = 0
    n_correct_recall = 0
    n_truth = 0
    idx_of = {i: np.flatnonzero(image_ids == i) for i in imgs}
    ia_all, ib_all = image_ids[a], image_ids[b]
    for x, i in enumerate(imgs):
        for j in imgs[x + 1:]:
            H = homography(int(i), int(j))
            ga, gb = one_to_one_truth(H, xy[idx_of[i]], xy[idx_of[j]], tol)
            truth = set(zip(idx_of[i][ga].tolist(), idx_of[j][gb].tolist()))
            n_truth += len(truth)
            # predicted pairs between i and j, oriented (feature in i, feature in j)
            m1 = (ia_all == i) & (ib_all == j)
            m2 = (ia_all == j) & (ib_all == i)
            pa = np.r_[a[m1], b[m2]]
            pb = np.r_[b[m1], a[m2]]
            if len(pa) == 0:
                continue
            err = reprojection_error(H, xy[pa], xy[pb])
            good = err <= tol
            n_correct += int(good.sum())
            in_truth = np.array([(u, v) in truth for u, v in zip(pa[good].tolist(), pb[good].tolist())], bool)
            n_correct_recall += int(in_truth.sum())
    return _scores(len(a), n_correct, n_truth, n_correct_recall)


def comembership_scores(labels: np.ndarray, reference: np.ndarray) -> Scores:
    """Pairwise co-membership precision/recall/F1 of ``labels`` against ``reference`` labels.

    A pair counts when both features share a cluster; no n x n matrix (counts
    via the contingency table).
    """
    labels = np.asarray(labels)
    reference = np.asarray(reference)
    _, li = np.unique(labels, return_inverse=True)
    _, ri = np.unique(reference, return_inverse=True)
    li, ri = li.ravel(), ri.ravel()
    pairs_of = lambda c: int((c * (c - 1) // 2).sum())  # noqa: E731
    n_pred = pairs_of(np.bincount(li))
    n_ref = pairs_of(np.bincount(ri))
    joint = np.unique(li.astype(np.int64) * (ri.max() + 1) + ri, return_counts=True)[1]
    both = pairs_of(joint)
    return _scores(n_pred, both, n_ref)
