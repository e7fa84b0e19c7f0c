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
  spot, counts for precision only). Being positional, this truth also pairs
  keypoints that merely lie within ``tol`` of each other by chance where the
  keypoints are dense; :func:`chance_truth_pairs` and :func:`real_truth_pairs`
  estimate how many.
* **Consistency** of a set of matches (:func:`consistency_violations`): the
  tracks are the connected components of the match graph. C1 (every feature in
  exactly one cluster) holds iff matching is transitive: any two features of
  different images in one track are matched. C2 holds iff no track holds two
  features of one image. Clusters (QuickMatch, tracks) satisfy both by
  construction; raw pairwise matches need not.
* **PR curve** (:class:`PRCurve`): precision and recall at each value of a
  method's threshold; its area (:func:`pr_auc`) is the trapezoid integral of
  precision over recall, extended from the lowest recall reached down to
  recall 0 at that point's precision (and 0 beyond the highest recall), so a
  method that reaches more recall gains area.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, Sequence, Tuple

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
    from .core.tree import member_pairs

    image_ids = np.asarray(image_ids)
    a, b = member_pairs(labels)
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


#: translations (px) applied after the true homography by :func:`chance_truth_pairs`: far beyond the truth's
#: tolerance and any keypoint's localisation error, small against the images
CHANCE_SHIFTS = ((40.0, 0.0), (0.0, 40.0), (-50.0, 30.0), (30.0, -60.0))


def chance_truth_pairs(H: np.ndarray, xa: np.ndarray, xb: np.ndarray, tol: float,
                       shifts: Sequence[Tuple[float, float]] = CHANCE_SHIFTS) -> float:
    """How many one-to-one pairs :func:`one_to_one_truth` finds by keypoint density alone: the mean number of its
    pairs under the true ``H`` followed by each translation in ``shifts``, which breaks every real
    correspondence and keeps the keypoints' density."""
    counts = []
    for dx, dy in shifts:
        T = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])
        counts.append(len(one_to_one_truth(T @ np.asarray(H, np.float64), xa, xb, tol)[0]))
    return float(np.mean(counts)) if counts else 0.0


def real_truth_pairs(n_truth: int, chance: float, n_a: int, n_b: int) -> Tuple[float, float]:
    """Bounds on how many of an image pair's ``n_truth`` one-to-one truth pairs are real correspondences, from
    the pairs chance gives (:func:`chance_truth_pairs`) among ``n_a`` and ``n_b`` keypoints: at least
    ``n_truth - chance`` (as if chance paired every keypoint, real ones included); at most the ``R`` with
    ``R = n_truth - chance (1 - R / n_a) (1 - R / n_b)`` (chance pairing only keypoints that no real
    correspondence holds, each image's share apart)."""
    lo = max(0.0, n_truth - chance)
    hi = lo
    for _ in range(100):  # rises to the least such R above the lower bound (the right side grows with R)
        nxt = n_truth - chance * max(0.0, 1 - hi / max(n_a, 1)) * max(0.0, 1 - hi / max(n_b, 1))
        if abs(nxt - hi) < 1e-9:
            break
        hi = nxt
    return lo, min(float(n_truth), hi)


class HomographyTruth:
    """Ground truth of a planar scene, computed once and reused to score many match sets.

    ``keypoints_xy``: (n, >=2) pixel positions; ``homography(i, j)``: 3x3 map
    from image ``i`` pixels to image ``j`` pixels; ``tol``: pixels. See the
    module doc for the definitions of correct pairs and of recall.
    """

    def __init__(self, keypoints_xy, image_ids, homography: Callable[[int, int], np.ndarray], tol: float = 5.0):
        xy = np.asarray(keypoints_xy, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] < 2:
            raise ValueError(f"keypoints must be (n, 2..4), got shape {xy.shape}")
        self.xy = xy[:, :2]
        self.image_ids = np.asarray(image_ids)
        if self.image_ids.shape != (len(xy),):
            raise ValueError(f"image_ids must have one entry per keypoint ({len(xy)})")
        if not tol > 0:
            raise ValueError(f"tol must be positive, got {tol}")
        self.tol = float(tol)
        self.n = len(xy)
        imgs = np.unique(self.image_ids)
        idx_of = {int(i): np.flatnonzero(self.image_ids == i) for i in imgs}
        self.H: Dict[Tuple[int, int], np.ndarray] = {}
        keys = []
        for x, i in enumerate(imgs):
            for j in imgs[x + 1:]:
                H = np.asarray(homography(int(i), int(j)), dtype=np.float64)
                self.H[(int(i), int(j))] = H
                ga, gb = one_to_one_truth(H, self.xy[idx_of[int(i)]], self.xy[idx_of[int(j)]], self.tol)
                keys.append(idx_of[int(i)][ga] * self.n + idx_of[int(j)][gb])
        self.truth_keys = np.sort(np.concatenate(keys)) if keys else np.zeros(0, np.int64)

    @property
    def n_truth(self) -> int:
        return int(len(self.truth_keys))

    def correct(self, a, b) -> Tuple[np.ndarray, np.ndarray]:
        """Per predicted pair: (correct within tol, one of the one-to-one truth pairs)."""
        a = np.asarray(a, np.int64)
        b = np.asarray(b, np.int64)
        ia, ib = self.image_ids[a], self.image_ids[b]
        swap = ia > ib
        u, v = np.where(swap, b, a), np.where(swap, a, b)  # u in the lower image
        iu, iv = self.image_ids[u], self.image_ids[v]
        good = np.zeros(len(a), bool)
        for (i, j), H in self.H.items():
            m = np.flatnonzero((iu == i) & (iv == j))
            if len(m):
                good[m] = reprojection_error(H, self.xy[u[m]], self.xy[v[m]]) <= self.tol
        key = u * self.n + v
        pos = np.searchsorted(self.truth_keys, key)
        pos = np.minimum(pos, max(len(self.truth_keys) - 1, 0))
        in_truth = good & (self.truth_keys[pos] == key) if len(self.truth_keys) else np.zeros(len(a), bool)
        return good, in_truth

    def score(self, a, b) -> Scores:
        a = np.asarray(a, np.int64)
        if len(a) != len(np.asarray(b)):
            raise ValueError("a and b must have equal length")
        good, in_truth = self.correct(a, b)
        return _scores(len(a), int(good.sum()), self.n_truth, int(in_truth.sum()))


def homography_scores(a, b, keypoints_xy, image_ids, homography: Callable[[int, int], np.ndarray],
                      tol: float = 5.0) -> Scores:
    """Pairwise precision/recall of predicted pairs on a planar scene (see module doc).

    To score many match sets on one scene, build a :class:`HomographyTruth` once.
    """
    return HomographyTruth(keypoints_xy, image_ids, homography, tol).score(a, b)


@dataclass(frozen=True)
class Violations:
    """C1/C2 violations of a set of matches (see module doc).

    ``n_tracks``: connected components with two or more features;
    ``c1_features``: features not matched to every feature of another image in
    their track; ``c1_pairs``: such missing (transitively implied) pairs;
    ``c2_tracks``: tracks holding two features of one image; ``c2_features``:
    features sharing their track with another feature of their image.
    """

    n_matches: int
    n_tracks: int
    c1_features: int
    c1_pairs: int
    c2_tracks: int
    c2_features: int

    def as_dict(self) -> Dict[str, int]:
        return dict(n_matches=self.n_matches, n_tracks=self.n_tracks, c1_features=self.c1_features,
                    c1_pairs=self.c1_pairs, c2_tracks=self.c2_tracks, c2_features=self.c2_features)


def consistency_violations(a, b, image_ids) -> Violations:
    """Count C1 and C2 violations of the matches (a[k], b[k]) (duplicates and self-pairs ignored)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    image_ids = np.asarray(image_ids)
    n = len(image_ids)
    a = np.asarray(a, np.int64)
    b = np.asarray(b, np.int64)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f"a and b must be 1-D of equal length, got {a.shape} and {b.shape}")
    if len(a) and (min(a.min(), b.min()) < 0 or max(a.max(), b.max()) >= n):
        raise ValueError(f"match indices must lie in 0..{n - 1}")
    if n == 0:
        return Violations(0, 0, 0, 0, 0, 0)
    keep = (a != b) & (image_ids[a] != image_ids[b])
    lo, hi = np.minimum(a[keep], b[keep]), np.maximum(a[keep], b[keep])
    pair = np.unique(lo * n + hi)  # one key per pair: the rows of np.unique(..., axis=1), in its order, 20x faster
    edges = np.stack([pair // n, pair % n])
    g = coo_matrix((np.ones(edges.shape[1], np.int8), (edges[0], edges[1])), shape=(n, n))
    _, comp = connected_components(g, directed=False)
    _, img = np.unique(image_ids, return_inverse=True)
    img = img.ravel().astype(np.int64)
    size = np.bincount(comp)
    key = comp * (img.max() + 1) + img
    ukey, kinv, kcnt = np.unique(key, return_inverse=True, return_counts=True)
    same_img = kcnt[kinv.ravel()]  # features of my image in my track, me included
    degree = np.bincount(edges[0], minlength=n) + np.bincount(edges[1], minlength=n)
    should = size[comp] - same_img  # features of other images in my track
    c1_feat = int((degree < should).sum())
    c1_pairs = int((should - degree).sum() // 2)
    c2_tracks = len(np.unique(ukey[kcnt > 1] // (img.max() + 1)))
    return Violations(
        n_matches=int(edges.shape[1]), n_tracks=int((size > 1).sum()), c1_features=c1_feat,
        c1_pairs=c1_pairs, c2_tracks=int(c2_tracks), c2_features=int((same_img > 1).sum()),
    )


def pr_auc(recall: Sequence[float], precision: Sequence[float]) -> float:
    """Area under a precision-recall curve given as points (see module doc)."""
    r = np.asarray(recall, dtype=np.float64)
    p = np.asarray(precision, dtype=np.float64)
    if r.shape != p.shape or r.ndim != 1:
        raise ValueError(f"recall and precision must be 1-D of equal length, got {r.shape} and {p.shape}")
    if len(r) == 0:
        return 0.0
    if not (np.isfinite(r).all() and np.isfinite(p).all()) or (r < 0).any() or (r > 1).any() \
            or (p < 0).any() or (p > 1).any():
        raise ValueError("recall and precision must lie in [0, 1]")
    order = np.lexsort((-p, r))
    r, p = r[order], p[order]
    r = np.r_[0.0, r]
    p = np.r_[p[0], p]
    return float(np.sum(np.diff(r) * (p[1:] + p[:-1]) / 2.0))


@dataclass(frozen=True)
class PRCurve:
    """Precision and recall of one method at each value of its threshold."""

    method: str
    threshold_name: str
    thresholds: np.ndarray
    precision: np.ndarray
    recall: np.ndarray

    @property
    def f1(self) -> np.ndarray:
        s = self.precision + self.recall
        return np.where(s > 0, 2 * self.precision * self.recall / np.where(s > 0, s, 1), 0.0)

    def auc(self) -> float:
        return pr_auc(self.recall, self.precision)

    def best_f1(self) -> Tuple[float, float]:
        """Highest F1 along the curve and the threshold that gives it (the lowest one on ties)."""
        if len(self.thresholds) == 0:
            return 0.0, float("nan")
        f1 = self.f1
        order = np.argsort(self.thresholds, kind="stable")
        k = order[int(np.argmax(f1[order]))]
        return float(f1[k]), float(self.thresholds[k])

    def as_dict(self) -> Dict[str, object]:
        return dict(method=self.method, threshold_name=self.threshold_name,
                    thresholds=[float(t) for t in self.thresholds],
                    precision=[float(v) for v in self.precision], recall=[float(v) for v in self.recall],
                    auc=self.auc())

    @classmethod
    def from_dict(cls, d: Dict[str, object]) -> "PRCurve":
        return cls(str(d["method"]), str(d["threshold_name"]), np.asarray(d["thresholds"], float),
                   np.asarray(d["precision"], float), np.asarray(d["recall"], float))


def pr_curve(method: str, threshold_name: str, thresholds: Sequence[float], scores: Sequence[Scores]) -> PRCurve:
    """Build a :class:`PRCurve` from the scores at each threshold."""
    if len(thresholds) != len(scores):
        raise ValueError("one Scores per threshold needed")
    return PRCurve(method, threshold_name, np.asarray(thresholds, float),
                   np.array([s.precision for s in scores], float), np.array([s.recall for s in scores], float))


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
