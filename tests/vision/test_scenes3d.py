"""Generated 3-D scenes (tests/generators/scenes3d.py): exact truth, renderer agreement, SIFT and SfM usability."""
import json

import cv2
import numpy as np
import pytest
from generators.scenes3d import generate_scene3d

from dqm import InputError
from dqm.vision import features


@pytest.fixture(scope="module")
def scene():
    return generate_scene3d(seed=0)


def _grid(scene, step=8, margin=10):
    h, w = scene.size
    gx, gy = np.meshgrid(np.arange(margin, w - margin, step), np.arange(margin, h - margin, step))
    return np.c_[gx.ravel(), gy.ravel()].astype(np.float64)


def test_shapes_cameras_and_coverage(scene):
    n = len(scene)
    assert n == 8 and scene.R.shape == (n, 3, 3) and scene.t.shape == (n, 3) and scene.K.shape == (3, 3)
    assert all(im.shape == (480, 640) and im.dtype == np.uint8 for im in scene.images)
    np.testing.assert_allclose(scene.R @ scene.R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (n, 3, 3)),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(scene.R), 1.0, atol=1e-12)
    gaps = np.linalg.norm(np.diff(scene.centres, axis=0), axis=1)
    assert (gaps > 0.3).all() and (gaps < 0.7).all()
    # every pixel sees a plane; foreground planes cover a good part of each view, at several depths
    for k in range(n):
        pts, ok = scene.backproject(k, _grid(scene, step=4, margin=0))
        assert ok.all()
        depth = (pts @ scene.R[k].T + scene.t[k])[:, 2]
        assert 0.3 < np.mean(depth < 9.0) < 0.9 and depth.min() < 6.0 and depth.max() > 9.0
    # backproject then project is the identity, and the point is visible where it was seen
    xy = _grid(scene, step=37)
    X, ok = scene.backproject(3, xy)
    uv, vis = scene.project(X[ok])
    np.testing.assert_allclose(uv[3], xy[ok], atol=1e-6)
    assert vis[3].all() and vis.shape == (8, ok.sum()) and uv.shape == (8, ok.sum(), 2)


def test_deterministic_for_a_seed(scene):
    again = generate_scene3d(seed=0)
    for a, b in zip(scene.images, again.images):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(scene.R, again.R)
    np.testing.assert_array_equal(scene.t, again.t)
    other = generate_scene3d(seed=1, n_images=2)
    assert not np.array_equal(scene.images[0], other.images[0])


def test_renderer_agrees_with_projection_truth(scene):
    """Patches around pixels of view i, mapped through the truth into view j, look the same there."""
    h, w = scene.size
    rng = np.random.default_rng(1)
    r = 5
    off = np.stack(np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1)), -1).reshape(-1, 2)
    for i, j in [(0, 1), (0, 4), (6, 2)]:
        centres = np.c_[rng.integers(r, w - r, 400), rng.integers(r, h - r, 400)]
        pts = (centres[:, None, :] + off[None]).reshape(-1, 2)
        uv, ok = scene.correspondence(i, j, pts.astype(np.float64))
        ok = ok.reshape(len(centres), -1).all(1)  # whole patch visible: away from occlusion edges
        a = scene.images[i][pts[:, 1], pts[:, 0]].astype(np.float32).reshape(len(centres), -1)
        maps = uv.astype(np.float32).reshape(len(centres), -1, 2)
        b = cv2.remap(scene.images[j].astype(np.float32), maps[..., 0], maps[..., 1], cv2.INTER_LINEAR)
        keep = ok & (a.std(1) > 8)  # textured patches only
        assert keep.sum() >= 60
        a, b = a[keep] - a[keep].mean(1, keepdims=True), b[keep] - b[keep].mean(1, keepdims=True)
        ncc = (a * b).sum(1) / np.sqrt((a * a).sum(1) * (b * b).sum(1))
        assert np.median(ncc) > 0.98 and np.mean(ncc > 0.9) > 0.95, (i, j, np.median(ncc))


def test_sift_matches_agree_with_truth(scene):
    feats = [features.extract(scene.images[k]) for k in (0, 1, 4)]
    bf = cv2.BFMatcher(cv2.NORM_L2)
    for (a, b), (i, j) in [((0, 1), (0, 1)), ((0, 2), (0, 4))]:
        fa, fb = feats[a], feats[b]
        assert len(fa) > 500 and len(fb) > 500
        knn = bf.knnMatch(fa.descriptors.astype(np.float32), fb.descriptors.astype(np.float32), k=2)
        good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
        q = np.array([g.queryIdx for g in good])
        tr = np.array([g.trainIdx for g in good])
        uv, ok = scene.correspondence(i, j, fa.keypoints[q, :2].astype(np.float64))
        err = np.linalg.norm(uv - fb.keypoints[tr, :2], axis=1)
        assert len(good) > 300
        assert np.mean(ok & (err < 3.0)) >= 0.8, (i, j, np.mean(ok & (err < 3.0)))


def test_scene_is_not_planar(scene):
    """True correspondences fit a fundamental matrix, not one homography: SfM is well posed."""
    xy = _grid(scene)
    for i, j in [(0, 1), (2, 7)]:
        uv, ok = scene.correspondence(i, j, xy)
        assert ok.sum() > 1000
        _, inl_h = cv2.findHomography(xy[ok], uv[ok], cv2.RANSAC, 2.0)
        assert inl_h.mean() < 0.6, inl_h.mean()
        # the exact fundamental matrix from K, R, t explains every correspondence
        R = scene.R[j] @ scene.R[i].T
        t = scene.t[j] - R @ scene.t[i]
        tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
        Kinv = np.linalg.inv(scene.K)
        F = Kinv.T @ tx @ R @ Kinv
        a, b = np.c_[xy[ok], np.ones(ok.sum())], np.c_[uv[ok], np.ones(ok.sum())]
        lines = a @ F.T
        dist = np.abs((b * lines).sum(1)) / np.linalg.norm(lines[:, :2], axis=1)
        assert dist.max() < 1e-6
        _, inl_f = cv2.findFundamentalMat(xy[ok], uv[ok], cv2.FM_RANSAC, 0.5, 0.999)
        assert inl_f.mean() > 0.99


def test_occluded_points_are_not_visible(scene):
    # a point on a far plane, hidden in view j by a nearer plane, is flagged as occluded
    xy = _grid(scene, step=4)
    X, ok = scene.backproject(0, xy)
    uv, vis = scene.project(X[ok])
    hidden = ~vis & np.isfinite(uv).all(-1)
    inside = (uv[..., 0] > 0) & (uv[..., 0] < 639) & (uv[..., 1] > 0) & (uv[..., 1] < 479)
    assert (hidden & inside).sum() > 100
    k, m = np.argwhere(hidden & inside)[0]
    seen, _ = scene.backproject(int(k), uv[k, m][None])
    z_seen = (seen[0] @ scene.R[k].T + scene.t[k])[2]
    z_point = (X[ok][m] @ scene.R[k].T + scene.t[k])[2]
    assert z_seen < z_point - 0.1


@pytest.mark.parametrize("kwargs", [dict(n_images=1), dict(n_planes=1), dict(width=0), dict(height=-5),
                                    dict(n_images=2.5), dict(focal=0.0), dict(focal=float("nan"))])
def test_bad_arguments_raise(kwargs):
    with pytest.raises(InputError):
        generate_scene3d(**kwargs)


def test_bad_query_arguments_raise(scene):
    with pytest.raises(InputError):
        scene.backproject(8, np.zeros((1, 2)))
    with pytest.raises(InputError):
        scene.correspondence(0, 1, np.zeros((3, 3)))
    with pytest.raises(InputError):
        scene.project(np.full((1, 3), np.nan))


def test_save_writes_images_and_cameras_and_refuses_non_empty_folder(tmp_path):
    small = generate_scene3d(seed=3, n_images=3, width=160, height=120, n_planes=2)
    out = small.save(tmp_path / "scene")
    assert sorted(p.name for p in out.iterdir()) == ["cameras.json", "img1.png", "img2.png", "img3.png"]
    np.testing.assert_array_equal(cv2.imread(str(out / "img2.png"), cv2.IMREAD_GRAYSCALE), small.images[1])
    meta = json.loads((out / "cameras.json").read_text())
    assert (meta["width"], meta["height"]) == (160, 120)
    np.testing.assert_allclose(meta["K"], small.K)
    np.testing.assert_allclose(meta["R"], small.R)
    np.testing.assert_allclose(meta["t"], small.t)
    with pytest.raises(InputError, match="not an empty folder"):
        small.save(out)
    empty = tmp_path / "empty"
    empty.mkdir()
    small.save(empty)  # an existing empty folder is fine


def test_colmap_registers_every_image(tmp_path):
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap not installed")
    scene = generate_scene3d(seed=0)
    images = scene.save(tmp_path / "images")
    names = [f"img{k + 1}.png" for k in range(len(scene))]
    db = tmp_path / "database.db"
    pycolmap.extract_features(db, images, image_names=names)
    pycolmap.match_exhaustive(db)
    (tmp_path / "sparse").mkdir()
    recs = pycolmap.incremental_mapping(db, images, tmp_path / "sparse")
    assert recs, "COLMAP built no reconstruction"
    best = max(recs.values(), key=lambda r: r.num_reg_images())
    assert best.num_reg_images() == len(scene)
    # the recovered camera centres match the truth up to a similarity transform
    by_name = {im.name: im.projection_center() for im in best.images.values()}
    est = np.array([by_name[n] for n in names])
    true = scene.centres
    a, b = est - est.mean(0), true - true.mean(0)
    U, S, Vt = np.linalg.svd(b.T @ a)
    D = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    rot = U @ D @ Vt
    scale = np.trace(np.diag(S) @ D) / (a * a).sum()
    resid = np.linalg.norm(scale * a @ rot.T - b, axis=1)
    assert resid.max() < 0.02 * np.linalg.norm(np.ptp(true, axis=0))
