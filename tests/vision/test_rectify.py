"""Rectified descriptors for guided growth (dqm.vision.rectify) and growth that uses them."""
import cv2
import numpy as np
import pytest
from conftest import assert_consistent

import dqm
from dqm import evaluation
from dqm.vision import features
from dqm.vision.guided import _orientation_links, first_at_location, guided_labels
from dqm.vision.rectify import Rectifier, area_scale, rectifier_for, sift_octave, upright_descriptors
from dqm.vision.scenes import generate_scene


@pytest.fixture(scope="module")
def scene():
    """A generated planar scene (known homographies), its RootSIFT features and QuickMatch."""
    sc = generate_scene(n_images=4, size=(300, 400), seed=3)
    D, ids, kp = features.extract_many(sc.images)
    return sc, D, ids, kp, dqm.quickmatch(D, ids)


def test_a_keypoint_described_again_at_its_octave_gives_its_descriptor(scene):
    sc = scene[0]
    img = features.as_gray(sc.images[0])
    sift = cv2.SIFT_create()
    kps, desc = sift.detectAndCompute(img, None)
    words = sift_octave([k.size for k in kps])
    assert (words == np.array([k.octave for k in kps])).all()  # OpenCV's packing, recovered from the size alone
    again = [cv2.KeyPoint(k.pt[0], k.pt[1], k.size, k.angle, 0.0, int(w)) for k, w in zip(kps, words)]
    _, desc2 = sift.compute(img, again)
    assert np.array_equal(desc, desc2)
    # without the octave OpenCV describes at the wrong level: not the same descriptors
    _, desc3 = sift.compute(img, [cv2.KeyPoint(k.pt[0], k.pt[1], k.size, k.angle) for k in kps])
    assert not np.array_equal(desc, desc3)


def test_area_scale_is_the_jacobian_determinant():
    H = np.array([[1.2, 0.1, 5.0], [-0.05, 0.9, 3.0], [2e-4, -1e-4, 1.0]])
    xy = np.array([[10.0, 20.0], [200.0, 150.0]])

    def f(p):
        q = H @ np.r_[p, 1.0]
        return q[:2] / q[2]
    for p in xy:
        e = 1e-4
        J = np.c_[(f(p + [e, 0]) - f(p - [e, 0])) / (2 * e), (f(p + [0, e]) - f(p - [0, e])) / (2 * e)]
        assert area_scale(H, p[None])[0] == pytest.approx(abs(np.linalg.det(J)), rel=1e-6)


def _tilted_pair(seed=0):
    """An image and its view through a strong perspective H (as graf's tilt), with each image's SIFT."""
    sc = generate_scene(n_images=2, size=(360, 480), seed=seed)
    a = features.as_gray(sc.images[0])
    h, w = a.shape
    src = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
    dst = np.float32([[60, 30], [w - 20, 0], [w - 5, h], [40, h - 40]])
    H = cv2.getPerspectiveTransform(src, dst).astype(np.float64)
    b = cv2.warpPerspective(a, H, (w, h))
    fa, fb = features.extract(a, "rootsift"), features.extract(b, "rootsift")
    return a, b, H, fa, fb


def test_rectified_upright_descriptors_bring_true_matches_together_and_keep_chance_apart():
    a, b, H, fa, fb = _tilted_pair()
    kp = np.r_[fa.keypoints, fb.keypoints].astype(np.float64)
    ids = np.r_[np.zeros(len(fa), np.int64), np.ones(len(fb), np.int64)]
    na = len(fa)
    # the true correspondences: b's keypoint nearest to H(a's), within 1 px, at a similar scale
    p = np.c_[fa.keypoints[:, :2], np.ones(na)] @ H.T
    p = p[:, :2] / p[:, 2:3]
    d = np.linalg.norm(p[:, None, :] - fb.keypoints[None, :, :2], axis=2)
    j = d.argmin(axis=1)
    true = np.flatnonzero(d[np.arange(na), j] < 1.0)
    assert len(true) > 50
    rows, cols = true, na + j[true]
    rect = Rectifier([a, b])
    Da, oka, Db, okb = rect.pair(0, 1, H, rows, cols, kp, ids)
    ok = oka & okb
    assert ok.mean() > 0.9
    X = np.r_[fa.descriptors, fb.descriptors].astype(np.float64)
    own = np.linalg.norm(X[rows] - X[cols], axis=1)[ok]
    upright = np.linalg.norm(Da.astype(float) - Db.astype(float), axis=1)[ok]
    assert np.median(upright) < 0.7 * np.median(own), (np.median(upright), np.median(own))
    # chance: under the homography shifted 40 px, each of a's features against b's keypoint that lands there
    # (another point of the scene, described in the frame that shift makes)
    T = np.array([[1.0, 0, 40.0], [0, 1.0, 0], [0, 0, 1.0]])
    q = np.c_[fa.keypoints[:, :2], np.ones(na)] @ (T @ H).T
    q = q[:, :2] / q[:, 2:3]
    e = np.linalg.norm(q[:, None, :] - fb.keypoints[None, :, :2], axis=2)
    k = e.argmin(axis=1)
    near = np.flatnonzero(e[np.arange(na), k] < 4.0)
    assert len(near) > 20, len(near)
    Sa, sa, Sb, sb = rect.pair(0, 1, T @ H, near, na + k[near], kp, ids)
    ok = sa & sb
    chance = np.linalg.norm(Sa.astype(float) - Sb.astype(float), axis=1)[ok]
    assert np.median(chance) > 2 * np.median(upright), (np.median(chance), np.median(upright))


def test_upright_descriptors_keep_their_rows_when_opencv_drops_some():
    img = np.zeros((60, 60), np.uint8)
    img[20:40, 20:40] = 255
    xy = np.array([[30.0, 30.0], [1e6, 1e6], [25.0, 28.0]])
    D, ok = upright_descriptors(img, xy, np.array([6.0, 6.0, 8.0]))
    one, _ = upright_descriptors(img, xy[[2]], np.array([8.0]))
    assert ok[0] and ok[2]
    assert np.array_equal(D[2], one[0])  # row 2 is row 2's, whatever OpenCV kept
    if not ok[1]:
        assert not D[1].any()


def test_growth_with_the_images_finds_more_true_pairs_at_the_same_precision(scene):
    sc, D, ids, kp, r = scene
    truth = evaluation.HomographyTruth(kp, ids, sc.homography)
    plain, s0 = guided_labels(r, kp, D)
    rect, s1 = guided_labels(r, kp, D, images=sc.images)
    assert_consistent(rect, ids)
    assert s0.n_rectified == 0 and 0 < s1.n_rectified <= s1.verify.n_planar and not s1.not_rectified
    p0 = truth.score(*evaluation.cluster_pairs(plain, ids))
    p1 = truth.score(*evaluation.cluster_pairs(rect, ids))
    assert p1.recall > p0.recall and p1.f1 > p0.f1, (p0, p1)
    assert p1.precision >= p0.precision - 0.005
    # the same labels whatever the threads
    again, _ = guided_labels(r, kp, D, images=list(sc.images), n_threads=1)
    assert np.array_equal(again, rect)


def test_growth_without_usable_images_says_why_and_compares_the_clustered_descriptors(scene, tmp_path):
    sc, D, ids, kp, r = scene
    plain, _ = guided_labels(r, kp, D)
    missing = [str(tmp_path / f"{k}.png") for k in range(len(sc.images))]
    labels, stats = guided_labels(r, kp, D, images=missing)
    assert np.array_equal(labels, plain)
    assert stats.n_rectified == 0 and "not found" in stats.not_rectified and "not rectified" in stats.summary()
    assert rectifier_for(sc.images, kp[:, :2], D)[0] is None  # no keypoint sizes
    with pytest.raises(dqm.InputError, match="one image per image id"):
        guided_labels(r, kp, D, images=sc.images[:-1])
    # an image smaller than its keypoints say (not the one they came from): that image's pairs compare the
    # clustered descriptors, the others are rectified
    small = list(sc.images)
    small[0] = np.asarray(small[0])[:100, :100]
    labels, stats = guided_labels(r, kp, D, images=small)
    assert "keypoints of image 0 lie outside" in stats.not_rectified
    assert 0 < stats.n_rectified < stats.verify.n_planar
    rect, _ = rectifier_for(sc.images, kp, D.astype(np.float32) / 512.0)
    assert rect.sigma_scale == pytest.approx(512.0, rel=0.01)  # unit-length descriptors: sigma scaled to RootSIFT's


def test_the_other_orientations_of_two_linked_locations_are_paired_by_their_own_descriptors():
    # image a: location A with three orientations (0, 1, 2); image b: location B with two (3, 4), and 5 alone
    kp = np.array([[10, 10, 4, 0], [10, 10, 4, 90], [10, 10, 4, 200], [50, 50, 4, 5], [50, 50, 4, 95],
                   [80, 80, 4, 0]], np.float64)
    X = np.zeros((6, 4))
    X[0], X[1], X[2] = [0, 0, 0, 0], [10, 0, 0, 0], [0, 10, 0, 0]
    X[3], X[4], X[5] = [1, 0, 0, 0], [11, 0, 0, 0], [0, 9, 0, 0]
    rows, cols = np.array([0, 1, 2]), np.array([3, 4, 5])
    assert first_at_location(kp, rows).tolist() == [True, False, False]
    i, j, d = _orientation_links(np.array([0]), np.array([3]), np.array([7.0]), rows, cols, X, kp)
    assert sorted(zip(i.tolist(), j.tolist())) == [(0, 3), (1, 4)]  # 2 has no partner left at B; 5 is elsewhere
    assert d.tolist() == [7.0, 7.0]


def test_dqm_match_rectifies_where_the_images_named_in_the_features_are_at_hand(tmp_path, capsys):
    import shutil

    from dqm import io
    from dqm.cli import main

    sc = generate_scene(n_images=4, size=(300, 400), seed=3)
    (tmp_path / "img").mkdir()
    for k, im in enumerate(sc.images):
        cv2.imwrite(str(tmp_path / "img" / f"{k}.png"), im)
    assert main(["extract", str(tmp_path / "img"), "--out", str(tmp_path / "f.npz"), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["match", str(tmp_path / "f.npz"), "--out", str(tmp_path / "c.npz"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "pairs rectified" in out and "not rectified" not in out
    fs = io.load_features(tmp_path / "f.npz")
    r = dqm.quickmatch(fs.descriptors, fs.image_ids)
    with_images, _ = guided_labels(r, fs.keypoints, fs.descriptors, images=[str(p) for p in fs.image_names])
    assert np.array_equal(io.load_clusters(tmp_path / "c.npz")["labels"], with_images)
    # the images gone: the clustered descriptors, and the summary says why
    shutil.move(tmp_path / "img", tmp_path / "elsewhere")
    assert main(["match", str(tmp_path / "f.npz"), "--out", str(tmp_path / "c2.npz"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "not rectified: image" in out and "not found" in out
    plain, _ = guided_labels(r, fs.keypoints, fs.descriptors)
    assert np.array_equal(io.load_clusters(tmp_path / "c2.npz")["labels"], plain)
    assert not np.array_equal(plain, with_images)


def test_the_ring_adds_links_out_to_the_verification_threshold_only_for_features_left_free(scene):
    from dqm.vision import guided
    from dqm.vision.verify import DEFAULT_THRESHOLD, fit_and_split

    sc, D, ids, kp, r = scene
    kp = np.asarray(kp, np.float64)
    labels, models, _ = fit_and_split(r.labels, ids, kp)
    by_image = {int(k): np.flatnonzero(ids == k) for k in np.unique(ids)}
    sigma = np.where(np.isfinite(r.sigma), r.sigma, np.inf)

    def links(ring):
        rect, _ = rectifier_for(sc.images, kp, D, ids)
        li, lj, _ = guided._propose_all(labels, by_image, models, D, kp, sigma, guided.DEFAULT_LINK_THRESHOLD,
                                        guided.DEFAULT_RATIO, guided.DEFAULT_MAX_SIGMA, 1, None, rect, ids, ring)
        return set(zip(li.tolist(), lj.tolist()))

    inner, both = links(0.0), links(DEFAULT_THRESHOLD)
    extra = both - inner
    assert inner <= both and extra
    def pair(i, j):
        return tuple(sorted((int(ids[i]), int(ids[j]))))

    taken = {(pair(i, j), f) for i, j in inner for f in (i, j)}
    assert not any((pair(i, j), f) in taken for i, j in extra for f in (i, j))  # only what no inner link took
    for i, j in extra:  # within the verification's 4 px of the pair's homography
        a, b = (i, j) if ids[i] < ids[j] else (j, i)
        m = models[(int(ids[a]), int(ids[b]))].guide()
        assert m.sq_residuals(kp[[a], :2], kp[[b], :2])[0] <= DEFAULT_THRESHOLD ** 2 + 1e-9


def test_a_rectifier_that_keeps_two_images_gives_what_one_that_keeps_all_gives(scene):
    sc, D, ids, kp, r = scene
    kp = np.asarray(kp, np.float64)
    H = {(a, b): sc.homography(a, b) for a in range(4) for b in range(a + 1, 4)}
    small, big = Rectifier(sc.images, cached=2), Rectifier(sc.images, cached=16)
    for (a, b), h in list(H.items()) + list(H.items())[::-1]:  # images evicted and made again
        rows, cols = np.flatnonzero(ids == a), np.flatnonzero(ids == b)
        for x, y in zip(small.pair(a, b, h, rows, cols, kp, ids), big.pair(a, b, h, rows, cols, kp, ids)):
            assert np.array_equal(x, y)
    assert len(small._grays) <= 2 and len(small._own) <= 2 and small.rectified == big.rectified == 12
