"""Geometry-guided cluster growth: QuickMatch's clusters made more complete by the image pairs' geometry.

QuickMatch's clusters are precise but incomplete: a feature whose true match lies a little beyond
``rho * sigma``, or behind a density-tree decision, stays apart. Two-view geometry tells which of
those near misses are real. :func:`grow_clusters` does, deterministically:

1. **Verify** (as ``dqm match --verify``, :mod:`dqm.vision.verify`): per image pair, the matches the
   clusters imply are fitted with USAC (a fundamental matrix and a homography; the configuration
   and the inliers chosen as COLMAP chooses them); a pair with at least 15 inliers is *verified*;
   members that the verified pairs reject are split off.
2. **Propose links**, per verified pair (a, b): only features of a whose cluster has no member in
   b, and of b whose cluster has no member in a, take part. A feature's *candidates* are the
   other image's features that fit the pair's geometry (:meth:`PairModel.guide`: the homography
   of a planar-or-panoramic pair, else the model whose inliers count) within ``link_threshold``
   (2 px, half the verification's 4 px: forward transfer error for a homography, Sampson error
   for a fundamental matrix, as COLMAP measures them). Link (i, j) is proposed when, among the
   candidates, j is i's nearest descriptor and i is j's (mutual), each by Lowe's ratio ``ratio`` (0.8, COLMAP's default)
   against the second nearest candidate on each side, and their distance is at most
   ``max_sigma`` (1.5) times the larger of the two features' sigma (QuickMatch's distance from a
   feature to the nearest other feature of its own image). The geometry narrows a feature's
   rivals from the whole image to a band a few pixels wide, so the ratio test can pass for true
   matches that the global test rejects (repeated structure), and the sigma bound keeps a lone
   candidate in an empty band from being taken whatever its descriptor.
   **Rectified** (where the images are given, as ``dqm match`` on images and ``dqm evaluate`` give them):
   a planar-or-panoramic pair compares its candidates' descriptors made again in one frame, the image
   that appears smaller warped up by the homography into the other's, each feature described upright
   at its own position and scale (:mod:`dqm.vision.rectify`; sigma taken to their scale). A tilted
   plane's true matches then compare like with like: on graf, wall, boat and bikes 22-46% more links
   under the true homographies and 15-48% fewer under shifted ones, where every link is chance
   (``python scripts/truth_chance.py graf wall boat bikes --links``). Keypoints at one location with
   several orientations take part once, and the others at two linked locations are paired by their own
   descriptors (mutually nearest). Compared so, features that no link takes may then link out to the
   verification's own 4 px by the same test at 1.0 sigma (:data:`RING_MAX_SIGMA`): stricter appearance
   for a looser position. On the four sets that ring adds 231-1,223 links under the true homographies
   and 2-8 under shifted ones.
3. **Merge**, links in order of increasing descriptor distance (ties by feature index): two
   clusters join when the union still has at most one feature per image (C2) and no member
   pair of a verified image pair contradicts the model whose inliers it counts (residual above
   the 4 px).

The settings were chosen on sacre_coeur's SfM and the homography sets together (docs/sfm.md):
links at 4 px gave the best F1 on the homography sets but a reprojection error more than
0.1 px above COLMAP's; 1 px the reverse; 2 px meets both. Two variants were measured and left out: a
second round (re-fit, propose, merge again) and completing clusters in the images they lack
from the meeting point of their members' epipolar lines. Both added 3-D points but shortened
the mean track and raised the reprojection error on sacre_coeur.

Candidates are found without forming every feature pair: a k-d tree around the transferred
points for a homography; for a fundamental matrix, the points sorted by angle around the
epipole in rings of distance (:func:`_line_windows`), so the work follows the number of
candidates. Descriptor distances are exact for integer descriptors. For a fundamental matrix
and uint8 descriptors the native kernel (``dqm_epipolar_scan``) runs the candidate test, the
distances and each feature's two nearest in one pass, without listing the candidates (about 4x
faster on DTU's 13k features per image); the numpy path gives the same numbers (a test checks
it at every SIMD level).

Only whole clusters join and only split-off members leave, so the result is a partition (C1)
with at most one feature per image per cluster (C2). Same inputs and seed, same labels.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Optional, Sequence, Tuple

import numpy as np

from ..core import native
from ..core.pairs import default_threads, exact_sq_distances
from ..validation import InputError
from .baselines import canonical
from .verify import DEFAULT_THRESHOLD, MIN_INLIERS, PairModel, VerifyStats, check_geometry_inputs, fit_and_split

#: a proposed link fits the pair's model within this many pixels (half the verification's 4 px)
DEFAULT_LINK_THRESHOLD = 2.0
#: Lowe's ratio among the geometry's candidates (COLMAP's SiftMatchingOptions.max_ratio)
DEFAULT_RATIO = 0.8
#: a proposed link's descriptor distance is at most this times the larger sigma of its two features
DEFAULT_MAX_SIGMA = 1.5
#: compared rectified, a link may lie as far as the verification's threshold when its distance is at most this
#: times the larger sigma (stricter appearance for a looser position: module docstring, step 2)
RING_MAX_SIGMA = 1.0


@dataclass
class GuidedStats:
    """What :func:`grow_clusters` did."""

    verify: VerifyStats
    n_proposed: int  # links proposed by the verified pairs
    n_merged: int  # links that joined two clusters
    n_refused_images: int  # refused: the union would hold two features of one image (C2)
    n_refused_geometry: int  # refused: a verified pair's model contradicts a member pair
    time_verify: float
    time_propose: float
    time_merge: float
    n_rectified: int = 0  # verified pairs whose links compared rectified descriptors (dqm.vision.rectify)
    not_rectified: str = ""  # why images were given but not used (empty: used, or none given)

    def summary(self) -> str:
        v = self.verify
        return (f"guided growth: {v.n_verified} of {v.n_pairs} image pairs verified ({v.n_planar} planar or "
                f"panoramic), {v.n_split} features split off; {self.n_proposed} links proposed by the geometry"
                f"{f' ({self.n_rectified} pairs rectified)' if self.n_rectified else ''}"
                f"{f' (not rectified: {self.not_rectified})' if self.not_rectified else ''}, "
                f"{self.n_merged} joined clusters ({self.n_refused_images} refused as two features of one image, "
                f"{self.n_refused_geometry} contradicted by a verified pair)")


def _expand(starts: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(owner, position) of every element of the ranges ``starts[k] .. starts[k] + counts[k] - 1``."""
    owner = np.repeat(np.arange(len(counts)), counts)
    offset = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
    return owner, starts[owner] + offset


@dataclass
class _LineWindows:
    """Where the candidates of lines that meet in one point lie among sorted points (:func:`_line_windows`).

    The points are in groups; within a group, ``key[group_start[g]:group_start[g + 1]]`` is sorted and
    ``point`` gives the point at each sorted position. Line k's candidates in group g are the points
    whose key lies within ``center[k] -+ width[g]`` (modulo ``period`` when it is positive; a negative
    width: every point of the group)."""

    center: np.ndarray
    group_start: np.ndarray
    width: np.ndarray
    key: np.ndarray
    point: np.ndarray
    period: float


def _line_windows(lines: np.ndarray, pts: np.ndarray, tol: float) -> _LineWindows:
    """The windows that hold every point within ``tol`` px of each line (all lines meet in one point).

    Epipolar lines of one image all pass through its epipole e. A point at distance r from e and
    angle theta lies within ``tol`` of the line through e at angle phi iff r |sin(theta - phi)| <=
    tol. Points are grouped in rings of r (powers of two); within a ring sorted by theta (mod pi),
    each line's candidates are one window of half-width asin(tol / ring's smallest r), so the
    work is the output plus a log, not lines x points. Lines through an epipole at infinity are
    parallel: one group sorted by the offset along their common normal, windows of half-width tol.
    A superset within rounding: the exact test is the caller's.
    """
    n = lines / np.maximum(np.hypot(lines[:, 0], lines[:, 1]), 1e-300)[:, None]
    # the epipole: the common point of the lines (least-squares, exact for a rank-2 F)
    _, _, vt = np.linalg.svd(n[: min(len(n), 4096)], full_matrices=False)
    e = vt[-1]
    if abs(e[2]) < 1e-12 * np.abs(e[:2]).max():  # at infinity: parallel lines, the offset decides
        normal = n[0, :2]
        sgn = np.sign(n[:, :2] @ normal)
        off = -n[:, 2] * np.where(sgn == 0, 1, sgn)
        proj = pts @ normal
        o = np.argsort(proj, kind="stable")
        return _LineWindows(off, np.array([0, len(o)], np.int64), np.array([float(tol)]), proj[o], o, 0.0)
    e = e[:2] / e[2]
    phi = np.mod(np.arctan2(n[:, 0], -n[:, 1]), np.pi)  # the lines' directions (perpendicular to the normal)
    v = pts - e
    r = np.hypot(v[:, 0], v[:, 1])
    theta = np.mod(np.arctan2(v[:, 1], v[:, 0]), np.pi)
    ring = np.floor(np.log2(np.maximum(r, tol))).astype(np.int64)
    o = np.lexsort((np.arange(len(r)), theta, ring))  # by ring, then angle (ties by point index)
    _, first = np.unique(ring[o], return_index=True)
    start = np.r_[first, len(o)].astype(np.int64)
    r_min = np.minimum.reduceat(r[o], first) if len(o) else np.zeros(0)
    width = np.empty(len(first))
    for g, rm in enumerate(r_min):
        # the epipole's neighbourhood (every line may pass near): the whole ring
        width[g] = -1.0 if rm <= tol * 1.0000001 else np.arcsin(min(1.0, tol / rm)) * (1 + 1e-9) + 1e-12
    return _LineWindows(phi, start, width, theta[o], o, float(np.pi))


def _near_lines(lines: np.ndarray, pts: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (line k, point c) with point c within ``tol`` px of line k, where all lines meet in one
    point: the windows of :func:`_line_windows` expanded (a superset within rounding)."""
    w = _line_windows(lines, pts, tol)
    ks, cs = [], []
    for g in range(len(w.width)):
        s, t = int(w.group_start[g]), int(w.group_start[g + 1])
        members = w.point[s:t]
        if w.width[g] < 0:
            k, pos = _expand(np.zeros(len(w.center), np.int64), np.full(len(w.center), len(members)))
            ks.append(k)
            cs.append(members[pos])
            continue
        key = w.key[s:t]
        if w.period > 0:  # wrap-around; a window is narrower than the period
            key = np.r_[key - w.period, key, key + w.period]
        lo = np.searchsorted(key, w.center - w.width[g], "left")
        hi = np.searchsorted(key, w.center + w.width[g], "right")
        k, pos = _expand(lo, hi - lo)
        ks.append(k)
        cs.append(members[pos % len(members)])
    if not ks:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(ks), np.concatenate(cs)


class _Epipolar:
    """A fundamental matrix's two searches for the pairs within ``t`` px (Sampson) of its epipolar geometry.

    Sampson <= t implies that one of the two one-sided epipolar distances is <= sqrt(2) t: the pairs
    near a's lines in b (the first search), then those near b's lines in a that the first did not
    find (the second)."""

    def __init__(self, model: PairModel, xa: np.ndarray, xb: np.ndarray, t: float):
        self.xb = xb
        self.tol = np.sqrt(2.0) * t * (1 + 1e-9) + 1e-9
        self.lines_b = xa @ model.matrix[:, :2].T + model.matrix[:, 2]  # F x: a's epipolar lines in b
        self.lines_a = xb @ model.matrix[:2, :] + model.matrix[2, :]  # F^T y: b's epipolar lines in a
        self.norm_b = self.lines_b[:, 0] ** 2 + self.lines_b[:, 1] ** 2
        self.norm_a = self.lines_a[:, 0] ** 2 + self.lines_a[:, 1] ** 2

    def algebraic(self, r: np.ndarray, c: np.ndarray) -> np.ndarray:
        """y^T F x of the pairs (r in a, c in b)."""
        lb = self.lines_b[r]
        return lb[:, 0] * self.xb[c, 0] + lb[:, 1] * self.xb[c, 1] + lb[:, 2]


def consistent_pairs(model: PairModel, xa: np.ndarray, xb: np.ndarray, threshold: float):
    """Every pair (r, c) with ``xa[r]`` (image a) and ``xb[c]`` (image b) fitting the model within
    ``threshold`` px (COLMAP's residuals: forward transfer error for H, Sampson error for F)."""
    t = float(threshold)
    if len(xa) == 0 or len(xb) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if model.kind == "H":
        from scipy.spatial import cKDTree

        p = np.c_[xa, np.ones(len(xa))] @ model.matrix.T
        with np.errstate(divide="ignore", invalid="ignore"):
            p = p[:, :2] / p[:, 2:3]
        fine = np.flatnonzero(np.isfinite(p).all(axis=1))
        found = cKDTree(xb).query_ball_point(p[fine], t * (1 + 1e-9) + 1e-9)
        counts = np.fromiter((len(f) for f in found), np.int64, len(found))
        r = np.repeat(fine, counts)
        c = np.fromiter((x for f in found for x in f), np.int64, int(counts.sum()))
    else:
        ep = _Epipolar(model, xa, xb, t)
        r1, c1 = _near_lines(ep.lines_b, xb, ep.tol)
        c2, r2 = _near_lines(ep.lines_a, xa, ep.tol)
        # disjoint: the first search's pairs within tol of a's lines, the second's beyond it
        e1, e2 = ep.algebraic(r1, c1), ep.algebraic(r2, c2)
        near1 = np.abs(e1) <= ep.tol * np.sqrt(ep.norm_b[r1])
        far2 = ~(np.abs(e2) <= ep.tol * np.sqrt(ep.norm_b[r2]))
        r, c, e = np.r_[r1[near1], r2[far2]], np.r_[c1[near1], c2[far2]], np.r_[e1[near1], e2[far2]]
        with np.errstate(divide="ignore", invalid="ignore"):
            ok = e * e <= t * t * (ep.norm_b[r] + ep.norm_a[c])  # Sampson error (as PairModel.sq_residuals)
        return r[ok], c[ok]
    ok = model.sq_residuals(xa[r], xb[c]) <= t * t
    return r[ok], c[ok]


def _best_two(key: np.ndarray, other: np.ndarray, d: np.ndarray, n_keys: int):
    """Per key 0..n_keys-1, among its entries (key, other, d) (no two with the same key and other): the
    best entry's other (lowest d, ties to the lowest other; -1 if none), its d and the second lowest d
    (inf if none). Linear passes, no sort."""
    best_d = np.full(n_keys, np.inf)
    np.minimum.at(best_d, key, d)
    at_best = d == best_d[key]
    none = np.iinfo(np.int64).max
    best = np.full(n_keys, none, np.int64)
    np.minimum.at(best, key[at_best], other[at_best])
    rest = ~(at_best & (other == best[key]))
    second = np.full(n_keys, np.inf)
    np.minimum.at(second, key[rest], d[rest])
    best[best == none] = -1
    return best, best_d, second


def _nearest_two(model: PairModel, rows: np.ndarray, cols: np.ndarray, X: np.ndarray, kp: np.ndarray,
                 threshold: float):
    """Per row (feature ``rows[r]`` of image a) and per column (``cols[c]`` of image b), among the pairs
    that fit the model within ``threshold`` (:func:`consistent_pairs`): the other side's nearest
    descriptor (-1 if none), its exact distance and the second nearest distance (:func:`_best_two`).
    For a fundamental matrix and uint8 descriptors the native kernel does it in one pass (the same
    numbers); otherwise numpy."""
    xa, xb = kp[rows, :2], kp[cols, :2]
    if model.kind == "F" and native.epipolar_scan_takes(X):
        t = float(threshold)
        ep = _Epipolar(model, xa, xb, t)
        nr, nc = len(rows), len(cols)
        out = (np.full(nr, -1, np.int64), np.full(nr, np.inf), np.full(nr, np.inf),
               np.full(nc, -1, np.int64), np.full(nc, np.inf), np.full(nc, np.inf))
        with np.errstate(divide="ignore", invalid="ignore"):
            native.epipolar_scan(_line_windows(ep.lines_b, xb, ep.tol), True, ep.lines_b, ep.norm_b, ep.norm_a,
                                 xb, ep.tol, t * t, X, rows, cols, *out)
            native.epipolar_scan(_line_windows(ep.lines_a, xa, ep.tol), False, ep.lines_b, ep.norm_b, ep.norm_a,
                                 xb, ep.tol, t * t, X, cols, rows, *out)
        return out
    r, c = consistent_pairs(model, xa, xb, threshold)
    d = np.sqrt(exact_sq_distances(X, rows[r], cols[c]))  # exact for integer descriptors (uint8 SIFT)
    return _best_two(r, c, d, len(rows)) + _best_two(c, r, d, len(cols))


def _links(model: PairModel, rows: np.ndarray, cols: np.ndarray, X: np.ndarray, kp: np.ndarray, sigma: np.ndarray,
           threshold: float, ratio: float, max_sigma: float) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 2's test on the features ``rows`` (image a) and ``cols`` (image b), indices into X, kp and sigma."""
    best_c, bd_r, sd_r, best_r, _, sd_c = _nearest_two(model, rows, cols, X, kp, threshold)
    r = np.flatnonzero(best_c >= 0)
    c = best_c[r]
    mutual = best_r[c] == r  # the pair is its row's nearest and its column's
    r, c = r[mutual], c[mutual]
    d = bd_r[r]
    ok = d < ratio * np.minimum(sd_r[r], sd_c[c])
    i, j = rows[r], cols[c]
    ok &= d <= max_sigma * np.maximum(sigma[i], sigma[j])
    return i[ok], j[ok], d[ok]


def _locations(kp: np.ndarray, features: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """The distinct locations (x, y, size) of ``features``: each location's first position among them, and each
    feature's location. SIFT gives a location one keypoint per dominant orientation."""
    _, first, loc = np.unique(np.asarray(kp[features, :3], np.float64), axis=0, return_index=True,
                              return_inverse=True)
    return first, loc.ravel()


def first_at_location(kp: np.ndarray, features: np.ndarray) -> np.ndarray:
    """Per feature of ``features``: is it the first of them at its location (:func:`_locations`)? Upright, the
    keypoints of one location have one descriptor."""
    first = np.zeros(len(features), bool)
    if len(features):
        first[_locations(kp, features)[0]] = True
    return first


def _orientation_links(li: np.ndarray, lj: np.ndarray, ld: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                       X: np.ndarray, kp: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The links of the other orientations at two linked locations: where location link (i, j) has more keypoints
    at i's location among ``rows`` and at j's among ``cols``, each pair of them that are mutually nearest by
    their own (oriented) descriptors, with the location link's distance."""
    def groups(features):
        loc = _locations(kp, features)[1]
        order = np.argsort(loc, kind="stable")
        starts = np.r_[0, np.flatnonzero(np.diff(loc[order])) + 1, len(loc)]
        out = {}
        for s, e in zip(starts[:-1], starts[1:]):
            if e - s > 1:
                members = features[order[s:e]]
                for f in members.tolist():
                    out[f] = members
        return out

    at_a, at_b = groups(rows), groups(cols)
    found = [(li, lj, ld)]
    for i, j, d in zip(li.tolist(), lj.tolist(), ld.tolist()):
        sa, sb = at_a.get(i), at_b.get(j)
        if sa is None or sb is None:
            continue
        sa, sb = sa[sa != i], sb[sb != j]
        D = exact_sq_distances(X, np.repeat(sa, len(sb)), np.tile(sb, len(sa))).reshape(len(sa), len(sb))
        near_b, near_a = D.argmin(axis=1), D.argmin(axis=0)
        mutual = np.flatnonzero(near_a[near_b] == np.arange(len(sa)))
        found.append((sa[mutual], sb[near_b[mutual]], np.full(len(mutual), d)))
    return tuple(np.concatenate(x) for x in zip(*found))


def propose_links(model: PairModel, rows: np.ndarray, cols: np.ndarray, X: np.ndarray,
                  kp: np.ndarray, sigma: np.ndarray, *, threshold: float, ratio: float,
                  max_sigma: float, rectifier=None, image_ids: Optional[np.ndarray] = None,
                  ring: float = 0.0) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The links one verified pair proposes (module docstring, step 2), searched along ``model.guide()``:
    features (i in a, j in b), distance; the merge orders them.

    With a ``rectifier`` (:class:`dqm.vision.rectify.Rectifier`; ``image_ids`` then given) a pair searched along
    its homography compares upright descriptors in one frame (step 2's rectified comparison): one keypoint per
    location, its other orientations paired afterwards (:func:`_orientation_links`); the rectifier's
    ``sigma_scale`` takes sigma to those descriptors' scale; features that no link within ``threshold`` takes
    may then link within ``ring`` px (> threshold; 0: not) by the same test at :data:`RING_MAX_SIGMA`."""
    empty = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    if len(rows) == 0 or len(cols) == 0:
        return empty
    guide = model.guide()
    if rectifier is None or guide.kind != "H":
        return _links(guide, rows, cols, X, kp, sigma, threshold, ratio, max_sigma)
    r, c = consistent_pairs(guide, kp[rows, :2], kp[cols, :2], max(threshold, ring))
    rows, cols = rows[np.unique(r)], cols[np.unique(c)]  # only features with a candidate are described again
    if len(rows) == 0:
        return empty
    rectified = rectifier.pair(model.a, model.b, guide.matrix, rows, cols, kp, image_ids)
    if rectified is None:  # an image that cannot serve (rectifier.skipped says why)
        return _links(guide, rows, cols, X, kp, sigma, threshold, ratio, max_sigma)
    Da, oka, Db, okb = rectified
    ra, cb = oka & first_at_location(kp, rows), okb & first_at_location(kp, cols)
    r_at, c_at = rows[ra], cols[cb]
    if len(r_at) == 0 or len(c_at) == 0:
        return empty
    nr = len(r_at)
    local = np.arange(nr + len(c_at))
    operands = (local[:nr], local[nr:], np.concatenate([Da[ra], Db[cb]]), np.concatenate([kp[r_at], kp[c_at]]),
                rectifier.sigma_scale * np.concatenate([sigma[r_at], sigma[c_at]]))
    i, j, d = _links(guide, *operands, threshold, ratio, max_sigma)
    if ring > threshold:
        oi, oj, od = _links(guide, *operands, ring, ratio, RING_MAX_SIGMA)
        free = ~np.isin(oi, i) & ~np.isin(oj, j)
        i, j, d = np.r_[i, oi[free]], np.r_[j, oj[free]], np.r_[d, od[free]]
    return _orientation_links(r_at[i], c_at[j - nr], d, rows, cols, X, kp)


def _residual_ok(kind: str, M: tuple, xu: tuple, xv: tuple, t2: float) -> bool:
    """Whether the point pair (xu in a, xv in b) fits the model within the threshold (scalar code)."""
    x, y = xu
    u, v = xv
    if kind == "H":
        w = M[6] * x + M[7] * y + M[8]
        if w == 0:
            return False
        du = (M[0] * x + M[1] * y + M[2]) / w - u
        dv = (M[3] * x + M[4] * y + M[5]) / w - v
        return du * du + dv * dv <= t2
    l0, l1, l2 = M[0] * x + M[1] * y + M[2], M[3] * x + M[4] * y + M[5], M[6] * x + M[7] * y + M[8]
    m0, m1 = M[0] * u + M[3] * v + M[6], M[1] * u + M[4] * v + M[7]
    e = u * l0 + v * l1 + l2
    den = l0 * l0 + l1 * l1 + m0 * m0 + m1 * m1
    return den > 0 and e * e <= t2 * den


def grow_clusters(labels, image_ids, keypoints, descriptors, sigma=None, *, threshold: float = DEFAULT_THRESHOLD,
                  ratio: float = DEFAULT_RATIO, max_sigma: float = DEFAULT_MAX_SIGMA, confidence: float = 0.999,
                  min_inliers: int = MIN_INLIERS, seed: int = 0, link_threshold: float = DEFAULT_LINK_THRESHOLD,
                  n_threads: Optional[int] = None, images: Optional[Sequence] = None,
                  progress: Optional[Callable[[int, int], None]] = None) -> Tuple[np.ndarray, GuidedStats]:
    """Clusters verified and grown by the image pairs' geometry (module docstring), and what was done.

    ``labels``: QuickMatch's (or any partition with at most one feature per image per cluster);
    ``keypoints``: (n, >= 2) pixel coordinates; ``descriptors``: (n, d), the ones clustered;
    ``sigma``: QuickMatch's per-feature sigma (``QuickMatchResult.sigma``; computed when None);
    ``threshold``: the verification's residual in pixels (COLMAP's 4 px); ``link_threshold``: a
    proposed link's; ``ratio``: Lowe's ratio among the geometry's candidates; ``max_sigma``: the
    distance bound in units of sigma; ``seed``: USAC's;
    ``n_threads``: image pairs handled at once (default: all cores; the result does not depend on it);
    ``images``: per image id, its path or array, where the features came from: planar-or-panoramic pairs then
    compare their links' descriptors rectified (:mod:`dqm.vision.rectify`); None: the clustered descriptors;
    ``progress(done, total)``: image pairs done, twice (verification, then the links; ``done`` restarts at 0).
    Returns labels numbered by each cluster's lowest feature index, as quickmatch numbers them.
    """
    labels, ids, kp = check_geometry_inputs(labels, image_ids, keypoints, threshold, confidence, min_inliers,
                                            "guided growth")
    n = len(labels)
    X = np.asarray(descriptors)
    if X.ndim != 2 or len(X) != n:
        raise InputError(f"guided growth needs descriptors (n, d) for the {n} labels; got shape {X.shape}")
    if not 0 < ratio <= 1 or not max_sigma > 0 or not link_threshold > 0:
        raise InputError(f"guided growth: ratio must be in (0, 1], max_sigma and link_threshold > 0; got {ratio}, "
                         f"{max_sigma}, {link_threshold}")
    if not np.issubdtype(X.dtype, np.integer):
        X = X.astype(np.float64)
        if not np.isfinite(X).all():
            raise InputError("guided growth: descriptors contain NaN or inf")
    if sigma is None:
        from ..core import pairs
        from ..core.clustering import distinctiveness

        uniq, index = np.unique(ids, return_inverse=True)
        sigma = distinctiveness(pairs.Augmented(X), index.ravel().astype(np.int64), len(uniq))
    sigma = np.asarray(sigma, np.float64)
    if sigma.shape != (n,):
        raise InputError(f"guided growth: sigma must have one value per feature ({n}), got shape {sigma.shape}")
    sigma = np.where(np.isfinite(sigma), sigma, np.inf)  # a feature alone in its image: no bound from it

    t0 = time.perf_counter()
    labels, models, vstats = fit_and_split(labels, ids, kp, threshold=threshold, confidence=confidence,
                                           min_inliers=min_inliers, seed=seed, progress=progress)
    t1 = time.perf_counter()
    by_image = {int(k): np.flatnonzero(ids == k) for k in np.unique(ids)}
    workers = max(1, default_threads() if n_threads is None else int(n_threads))
    rect, why = None, ""
    if images is not None:
        from .rectify import rectifier_for

        rect, why = rectifier_for(images, kp, X, ids)
    li, lj, ld = _propose_all(labels, by_image, models, X, kp, sigma, float(link_threshold), ratio, max_sigma,
                              workers, progress, rect, ids, float(threshold))
    t2 = time.perf_counter()
    labels, merged, refused_c2, refused_geo = _merge(labels, ids, kp, models, li, lj, ld, float(threshold) ** 2)
    n_rect, why = (0, why) if rect is None else (rect.rectified, rect.skipped)
    stats = GuidedStats(vstats, len(li), merged, refused_c2, refused_geo, t1 - t0, t2 - t1, time.perf_counter() - t2,
                        n_rect, why)
    return labels, stats


def _propose_all(labels, by_image, models, X, kp, sigma, threshold, ratio, max_sigma, workers, progress=None,
                 rectified=None, ids=None, ring=0.0):
    """The links of every verified pair (features whose cluster lacks the other image), in pair order."""
    from concurrent.futures import ThreadPoolExecutor

    n_labels = int(labels.max()) + 1 if len(labels) else 0

    def links_of(pair):
        a, b = pair
        A, B = by_image[a], by_image[b]
        in_b = np.zeros(n_labels, bool)
        in_b[labels[B]] = True
        in_a = np.zeros(n_labels, bool)
        in_a[labels[A]] = True
        return propose_links(models[pair], A[~in_b[labels[A]]], B[~in_a[labels[B]]], X, kp, sigma,
                             threshold=threshold, ratio=ratio, max_sigma=max_sigma,
                             rectifier=rectified, image_ids=ids, ring=ring)

    found = []
    with ThreadPoolExecutor(workers) as pool:
        for links in pool.map(links_of, sorted(models)):  # in pair order whatever the threads do
            if progress is not None:
                progress(len(found), len(models))
            found.append(links)
    if progress is not None:
        progress(len(found), len(models))
    if not found:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    return tuple(np.concatenate(x) for x in zip(*found))


def _merge(labels, ids, kp, models, li, lj, ld, t2) -> Tuple[np.ndarray, int, int, int]:
    """Join clusters along the links, nearest first, where C2 and every verified pair allow it."""
    order = np.lexsort((lj, li, ld))
    parent = list(range(int(labels.max()) + 1 if len(labels) else 0))
    members: dict[int, list[int]] = {}
    for f, lab in enumerate(labels.tolist()):
        members.setdefault(lab, []).append(f)
    images = {lab: {int(ids[f]) for f in fs} for lab, fs in members.items()}
    mats = {key: (m.kind, tuple(m.matrix.ravel().tolist())) for key, m in models.items()}
    img = ids.tolist()
    xy = [(float(x), float(y)) for x, y in kp[:, :2]]

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    merged = refused_c2 = refused_geo = 0
    for e in order.tolist():
        ri, rj = root(int(labels[li[e]])), root(int(labels[lj[e]]))
        if ri == rj:
            continue
        if not images[ri].isdisjoint(images[rj]):
            refused_c2 += 1
            continue
        ok = True
        for u in members[ri]:
            for v in members[rj]:
                a, b = img[u], img[v]
                key = (a, b) if a < b else (b, a)
                model = mats.get(key)
                if model is None:
                    continue
                pu, pv = (xy[u], xy[v]) if a < b else (xy[v], xy[u])
                if not _residual_ok(model[0], model[1], pu, pv, t2):
                    ok = False
                    break
            if not ok:
                break
        if not ok:
            refused_geo += 1
            continue
        if len(members[ri]) < len(members[rj]):
            ri, rj = rj, ri
        parent[rj] = ri
        members[ri] += members.pop(rj)
        images[ri] |= images.pop(rj)
        merged += 1
    new = np.array([root(int(lab)) for lab in labels.tolist()], np.int64) if len(labels) else labels
    return canonical(new), merged, refused_c2, refused_geo


def guided_labels(result, keypoints, descriptors, **options) -> Tuple[np.ndarray, GuidedStats]:
    """:func:`grow_clusters` on a :class:`dqm.core.QuickMatchResult` (its labels, image ids and sigma)."""
    return grow_clusters(result.labels, result.image_ids, keypoints, descriptors, result.sigma, **options)


__all__ = ["DEFAULT_MAX_SIGMA", "DEFAULT_RATIO", "RING_MAX_SIGMA", "GuidedStats", "grow_clusters", "guided_labels",
           "propose_links"]

