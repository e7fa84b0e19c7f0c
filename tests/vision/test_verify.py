"""Two-view model selection as COLMAP makes it (dqm.vision.verify), on point matches projected by known cameras."""
import numpy as np
import pytest

from dqm.vision.verify import PLANAR, UNCALIBRATED, fit_pairs, verify_clusters

pytest.importorskip("cv2")


def _pair(n_plane: int, n_off: int, n_wrong: int, seed: int = 0):
    """Keypoints of two views of ``n_plane`` points on the plane z = 6 and ``n_off`` points 2-4 units in
    front of it (640 x 480, focal 500, the second camera 1 unit to the side and turned 5 degrees), with
    0.3 px noise, then ``n_wrong`` matches to random points. As QuickMatch's output: feature k of image 0
    and feature k of image 1 share cluster k. Returns labels, image ids, keypoints and which are off-plane."""
    rng = np.random.default_rng(seed)
    plane = np.c_[rng.uniform(-4, 4, (n_plane, 2)), np.full(n_plane, 6.0)]
    off = np.c_[rng.uniform(-2, 2, (n_off, 2)), rng.uniform(2, 4, n_off)]
    X = np.r_[plane, off]
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    a = np.deg2rad(5)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    t = np.array([-1.0, 0, 0])

    def project(P):
        p = P @ K.T
        return p[:, :2] / p[:, 2:] + rng.normal(0, 0.3, (len(P), 2))

    x0, x1 = project(X), project(X @ R.T + t)
    wrong0 = rng.uniform((0, 0), (640, 480), (n_wrong, 2))
    wrong1 = rng.uniform((0, 0), (640, 480), (n_wrong, 2))
    x0, x1 = np.r_[x0, wrong0], np.r_[x1, wrong1]
    m = len(x0)
    labels = np.r_[np.arange(m), np.arange(m)]
    ids = np.r_[np.zeros(m, np.int64), np.ones(m, np.int64)]
    off_plane = np.zeros(m, bool)
    off_plane[n_plane:n_plane + n_off] = True
    return labels, ids, np.r_[x0, x1], off_plane


def _inlier_rows(model, n):
    inl = np.zeros(n, bool)
    inl[model.inliers[:, 0]] = True
    return inl


def test_a_dominant_plane_counts_the_fundamental_matrix_inliers_and_guides_along_the_homography():
    """A 3-D pair with a dominant plane (85% of the points): planar-or-panoramic, as COLMAP names it, but the
    inliers are the fundamental matrix's, which has more, so the correct matches off the plane count (the rule
    before counted the homography's and rejected them); growth searches along the homography."""
    labels, ids, kp, off = _pair(170, 30, 20)
    models, n_pairs, n_matches = fit_pairs(labels, ids, kp)
    assert n_pairs == 1 and n_matches == 220
    m = models[(0, 1)]
    assert m.config == PLANAR and m.kind == "F" and m.homography is not None
    inl = _inlier_rows(m, 220)
    assert inl[:170].mean() > 0.95 and inl[off].mean() > 0.9  # off-plane points: inliers
    assert inl[200:].mean() < 0.3
    g = m.guide()
    assert g.kind == "H" and np.array_equal(g.matrix, m.homography) and np.array_equal(g.inliers, m.inliers)
    # the homography rejects the off-plane points: what the rule before split off
    assert (np.sqrt(g.sq_residuals(kp[:220][off], kp[220:][off])) > 4).mean() > 0.9


def test_general_and_purely_planar_pairs():
    labels, ids, kp, off = _pair(60, 140, 20, seed=1)  # most points off the plane: general 3-D
    m = fit_pairs(labels, ids, kp)[0][(0, 1)]
    assert m.config == UNCALIBRATED and m.kind == "F" and m.homography is None and m.guide() is m
    assert _inlier_rows(m, 220)[:200].mean() > 0.95
    labels, ids, kp, _ = _pair(200, 0, 20, seed=2)  # a plane only: planar; the homography's inliers when more
    m = fit_pairs(labels, ids, kp)[0][(0, 1)]
    assert m.config == PLANAR and m.homography is not None
    assert m.guide().kind == "H" and _inlier_rows(m, 220)[:200].mean() > 0.95


def test_verification_keeps_correct_members_off_the_dominant_plane():
    """Three views of the dominant-plane scene as clusters of three (the third: the second shifted by a few
    pixels): the members off the plane stay (the rule before split them off as outliers of the homography
    between the first view and each other), and most wrong members are split off."""
    labels, ids, kp, off = _pair(170, 30, 0, seed=3)
    l2, i2, k2, _ = _pair(170, 30, 0, seed=3)  # the same points: view 1 again as a third image, shifted
    n = len(off)
    labels3 = np.r_[labels, np.arange(n)]
    ids3 = np.r_[ids, np.full(n, 2)]
    kp3 = np.r_[kp, k2[n:] + [3.0, 1.0]]  # a pure translation of view 1: the same geometry
    rng = np.random.default_rng(4)
    wrong = rng.choice(np.flatnonzero(~off), 20, replace=False)
    kp3[2 * n + wrong] = rng.uniform((0, 0), (640, 480), (20, 2))  # image 2's member of these clusters: wrong
    out, st = verify_clusters(labels3, ids3, kp3)
    assert st.n_verified == 3 and st.n_planar == 3
    kept = np.array([len(np.unique(out[[k, n + k, 2 * n + k]])) == 1 for k in range(n)])
    assert kept[off].mean() > 0.9
    alone = np.array([np.sum(out == out[2 * n + k]) == 1 for k in wrong])
    # a wrong member that falls within 4 px of its epipolar line in the pair (0, 2) is an inlier there, and
    # one inlier against one outlier keeps it (the margin): 4 of these 20
    assert alone.mean() >= 0.75
