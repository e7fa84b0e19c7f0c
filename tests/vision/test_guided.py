"""Geometry-guided cluster growth (dqm.vision.guided) and the colmap SIFT preset."""
import numpy as np
import pytest
from conftest import assert_consistent

import dqm
from dqm import InputError
from dqm.cli import main
from dqm.vision import features
from dqm.vision.guided import consistent_pairs, grow_clusters, guided_labels
from dqm.vision.scenes import generate_scene
from dqm.vision.verify import PairModel, fit_pairs, verify_clusters


@pytest.fixture(scope="module")
def planar():
    """A generated planar scene (known homographies) with RootSIFT, QuickMatch and the guided labels."""
    sc = generate_scene(n_images=4, size=(300, 400), seed=3)
    D, ids, kp = features.extract_many(sc.images)
    r = dqm.quickmatch(D, ids)
    labels, stats = guided_labels(r, kp, D)
    return sc, D, ids, kp, r, labels, stats


def _co_members(labels, ids):
    """Every pair (u, v), u < v, of members of one cluster."""
    order = np.argsort(labels, kind="stable")
    out = set()
    for lab in np.unique(labels):
        m = order[labels[order] == lab]
        out |= {(int(a), int(b)) for k, a in enumerate(m) for b in m[k + 1:]}
    return out


def test_guided_growth_keeps_c1_c2_and_adds_only_links_the_geometry_supports(planar):
    sc, D, ids, kp, r, labels, stats = planar
    assert labels.shape == r.labels.shape
    assert_consistent(labels, ids)  # C1 (a partition) and C2 (one feature per image per cluster)
    assert stats.n_merged > 0 and stats.verify.n_verified == 6
    # every member pair of an image pair with a verified model fits it within the 4 px
    models, _, _ = fit_pairs(*verify_inputs(labels, ids, kp))
    verified_before, _ = verify_clusters(r.labels, ids, kp)
    added = _co_members(labels, ids) - _co_members(verified_before, ids)
    assert len(added) > 20
    models0, _, _ = fit_pairs(*verify_inputs(r.labels, ids, kp))
    worst = 0.0
    for u, v in added:
        a, b = (u, v) if ids[u] < ids[v] else (v, u)
        m = models0.get((int(ids[a]), int(ids[b])))
        if m is not None:
            worst = max(worst, float(m.sq_residuals(kp[[a], :2], kp[[b], :2])[0]))
    assert worst <= 16.0 + 1e-6
    # against the scene's true homographies: the added co-memberships are right (within 5 px)
    right = 0
    for u, v in added:
        H = sc.homography(int(ids[u]), int(ids[v]))
        p = H @ np.r_[kp[u, :2], 1.0]
        right += np.hypot(*(p[:2] / p[2] - kp[v, :2])) <= 5.0
    assert right / len(added) >= 0.9, (right, len(added))


def verify_inputs(labels, ids, kp):
    return np.asarray(labels, np.int64), np.asarray(ids, np.int64), np.asarray(kp, np.float64)


def test_guided_growth_raises_recall_against_the_truth(planar):
    from dqm import evaluation

    sc, D, ids, kp, r, labels, _ = planar
    truth = evaluation.HomographyTruth(kp[:, :2], ids, sc.homography, 5.0)
    plain = truth.score(*evaluation.cluster_pairs(r.labels, ids))
    grown = truth.score(*evaluation.cluster_pairs(labels, ids))
    assert grown.recall > plain.recall and grown.precision >= 0.9 and grown.f1 > plain.f1


def test_guided_growth_is_deterministic_whatever_the_threads(planar):
    _, D, ids, kp, r, labels, stats = planar
    again, s2 = grow_clusters(r.labels, ids, kp, D, r.sigma, n_threads=1)
    assert np.array_equal(again, labels) and s2.n_merged == stats.n_merged
    # sigma computed when not given: QuickMatch's own
    third, _ = grow_clusters(r.labels, ids, kp, D)
    assert np.array_equal(third, labels)
    # progress: image pairs verified, then image pairs linked, each stage counted up to its total
    calls = []
    fourth, _ = grow_clusters(r.labels, ids, kp, D, r.sigma, progress=lambda d, t: calls.append((d, t)))
    assert np.array_equal(fourth, labels)
    restart = next(k for k in range(1, len(calls)) if calls[k][0] < calls[k - 1][0])
    verify, link = calls[:restart], calls[restart:]
    assert verify[-1] == (stats.verify.n_pairs,) * 2 and link[-1] == (stats.verify.n_verified,) * 2
    assert all(b[0] >= a[0] for stage in (verify, link) for a, b in zip(stage, stage[1:]))


def test_guided_growth_on_random_inputs_keeps_c1_c2():
    rng = np.random.default_rng(7)
    n_img, per = 5, 60
    ids = np.repeat(np.arange(n_img), per)
    kp = rng.uniform(0, 200, (len(ids), 2))
    D = rng.integers(0, 40, (len(ids), 16)).astype(np.uint8)
    r = dqm.quickmatch(D, ids, rho=1.5)
    labels, _ = grow_clusters(r.labels, ids, kp, D, r.sigma, min_inliers=8)
    assert_consistent(labels, ids)


def test_candidates_equal_the_brute_force_test():
    """The k-d tree / epipolar-ring search finds exactly the pairs within the threshold (H and F,
    epipoles inside, outside and at infinity)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    K = np.array([[500, 0, 400], [0, 500, 400], [0, 0, 1.0]])
    Ki = np.linalg.inv(K)
    for trial in range(12):
        xa, xb = rng.uniform(0, 800, (400, 2)), rng.uniform(0, 800, (350, 2))
        if trial % 3 == 0:
            M, kind = np.eye(3) + rng.normal(0, 0.05, (3, 3)) * [[1, 1, 0], [1, 1, 0], [0.001, 0.001, 0]], "H"
            M[:2, 2] = rng.normal(0, 50, 2)
        else:
            R = Rotation.from_rotvec(rng.normal(0, 0.2, 3)).as_matrix()
            t = rng.normal(0, 1, 3) if trial % 3 == 1 else np.array([1.0, 0.0, 0.0])  # last: epipole at infinity
            if trial % 3 == 2:
                R = np.eye(3)
            tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
            M, kind = Ki.T @ tx @ R @ Ki, "F"
        model = PairModel(0, 1, kind, M, np.zeros((0, 2), int), np.zeros((0, 2), int))
        r, c = consistent_pairs(model, xa, xb, 4.0)
        rr, cc = np.meshgrid(np.arange(len(xa)), np.arange(len(xb)), indexing="ij")
        res = model.sq_residuals(xa[rr.ravel()], xb[cc.ravel()]).reshape(len(xa), len(xb))
        assert set(zip(r.tolist(), c.tolist())) == set(zip(*map(np.ndarray.tolist, np.nonzero(res <= 16.0)))), trial
        assert len(r) == len(set(zip(r.tolist(), c.tolist())))  # no pair twice


def _random_f(rng, case):
    """A fundamental matrix of two 800 x 800 px views: epipoles inside (0), outside (1), at infinity (2)."""
    from scipy.spatial.transform import Rotation

    K = np.array([[500, 0, 400], [0, 500, 400], [0, 0, 1.0]])
    Ki = np.linalg.inv(K)
    R = np.eye(3) if case == 2 else Rotation.from_rotvec(rng.normal(0, 0.2, 3)).as_matrix()
    t = {0: np.array([0.05, -0.03, 1.0]), 1: rng.normal(0, 1, 3), 2: np.array([1.0, 0.0, 0.0])}[case]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return PairModel(0, 1, "F", Ki.T @ tx @ R @ Ki, np.zeros((0, 2), int), np.zeros((0, 2), int))


@pytest.mark.parametrize("case", [0, 1, 2])
def test_native_epipolar_scan_equals_numpy_at_every_simd_level(case):
    """The native kernel's fused pass (candidates, exact distances, each side's two nearest) gives the numpy
    path's numbers (consistent_pairs, exact_sq_distances, _best_two) at every SIMD level, ties included."""
    from dqm.core import native
    from dqm.vision import guided

    if not native._HAS_EPIPOLAR:
        pytest.skip("the native kernel is not built")
    rng = np.random.default_rng(case)
    model = _random_f(rng, case)
    n_a, n_b = 900, 800
    kp = np.r_[rng.uniform(0, 800, (n_a, 2)), rng.uniform(0, 800, (n_b, 2))]
    X = rng.integers(0, 4, (n_a + n_b, 130)).astype(np.uint8)  # few values: equal distances are common
    X[n_a:n_a + 300] = X[:300]  # and zero distances
    rows, cols = np.arange(n_a), np.arange(n_a, n_a + n_b)
    xa, xb = kp[rows], kp[cols]
    r, c = consistent_pairs(model, xa, xb, 30.0)
    assert len(r) > 5 * (n_a + n_b)  # many candidates per feature, so the ranking is tested
    d = np.sqrt(guided.exact_sq_distances(X, rows[r], cols[c]))
    want = guided._best_two(r, c, d, n_a) + guided._best_two(c, r, d, n_b)
    assert (want[1][want[0] >= 0] == want[2][want[0] >= 0]).any()  # ties between the best two exist
    top = native.set_simd_level(99)
    try:
        for level in range(top, -1, -1):
            assert native.set_simd_level(level) == level
            got = guided._nearest_two(model, rows, cols, X, kp, 30.0)
            for g, w, name in zip(got, want, ("best c", "d", "second", "best r", "d", "second")):
                assert np.array_equal(g, w), (level, name)
    finally:
        native.set_simd_level(99)


def test_best_two_breaks_ties_by_the_lower_index_whatever_the_order():
    from dqm.vision.guided import _best_two

    key, other, d = np.array([0, 0, 0, 1]), np.array([5, 2, 9, 3]), np.array([1.0, 1.0, 0.5, 2.0])
    for perm in ([0, 1, 2, 3], [3, 2, 1, 0], [1, 3, 0, 2]):
        best, bd, second = _best_two(key[perm], other[perm], d[perm], 3)
        assert best.tolist() == [9, 3, -1] and bd.tolist() == [0.5, 2.0, np.inf]
        assert second.tolist() == [1.0, np.inf, np.inf]
    best, _, second = _best_two(np.array([0, 0]), np.array([7, 4]), np.array([1.0, 1.0]), 1)
    assert best.tolist() == [4] and second.tolist() == [1.0]


def test_guided_growth_refuses_bad_inputs(planar):
    _, D, ids, kp, r, _, _ = planar
    with pytest.raises(InputError, match="descriptors"):
        grow_clusters(r.labels, ids, kp, D[:-1])
    with pytest.raises(InputError, match="keypoints"):
        grow_clusters(r.labels, ids, kp[:-1], D)
    with pytest.raises(InputError, match="ratio"):
        grow_clusters(r.labels, ids, kp, D, ratio=1.5)


def test_images_match_guided_export_colmap_reconstruct_every_image(tmp_path, capsys):
    """images -> dqm match --guided -> dqm export colmap -> pycolmap mapper (guided growth is opt-in since it
    cost SfM cameras in scripts/bench_sfm.py; the chain must still reconstruct every image)."""
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is not installed (pip install 'dqm[colmap]')")
    from generators.scenes3d import generate_scene3d

    from dqm import io

    sc = generate_scene3d(seed=0, n_images=6)
    sc.save(tmp_path / "img")
    assert main(["match", str(tmp_path / "img"), "--out", str(tmp_path / "c.npz"), "--guided", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "guided growth:" in out
    assert io.load_clusters(tmp_path / "c.npz")["params"]["guided"] is True
    assert main(["export", "colmap", str(tmp_path / "c.npz"), "--database", str(tmp_path / "db.db")]) == 0
    (tmp_path / "sparse").mkdir()
    recs = pycolmap.incremental_mapping(str(tmp_path / "db.db"), str(tmp_path / "img"), str(tmp_path / "sparse"))
    assert recs, "no reconstruction"
    best = max(recs.values(), key=lambda rec: rec.num_reg_images())
    assert best.num_reg_images() == 6
    assert best.compute_mean_reprojection_error() < 1.0


def test_match_guided_needs_keypoints_and_no_guided_gives_quickmatch(tmp_path, capsys):
    from dqm import io

    rng = np.random.default_rng(1)
    D = rng.integers(0, 50, (60, 8)).astype(np.uint8)
    ids = np.repeat(np.arange(3), 20)
    io.save_features(tmp_path / "f.npz", io.FeatureSet(descriptors=D, image_ids=ids))
    assert main(["match", str(tmp_path / "f.npz"), "--out", str(tmp_path / "c.npz"), "--guided", "--quiet"]) == 2
    assert "--guided needs keypoints" in capsys.readouterr().err
    # FEATURES files keep plain QuickMatch unless --guided is given
    assert main(["match", str(tmp_path / "f.npz"), "--out", str(tmp_path / "c.npz"), "--quiet"]) == 0
    assert np.array_equal(io.load_clusters(tmp_path / "c.npz")["labels"], dqm.quickmatch(D, ids).labels)


def test_colmap_preset_is_pycolmaps_sift(tmp_path):
    pytest.importorskip("pycolmap", reason="pycolmap is not installed (pip install 'dqm[colmap]')")
    sc = generate_scene(n_images=2, size=(240, 320), seed=1)
    D, ids, kp = features.extract_many(sc.images, preset="colmap", max_features=300)
    assert D.dtype == np.uint8 and D.shape[1] == 128 and kp.shape == (len(D), 4)
    assert set(np.unique(ids)) == {0, 1} and np.bincount(ids).max() <= 2 * 300  # 300 points, 2 orientations at most
    # RootSIFT-like: COLMAP stores L1-root normalised descriptors x 512; unit L2 norm within rounding
    norms = np.linalg.norm(D.astype(float), axis=1) / 512
    assert np.all(np.abs(norms - 1) < 0.05)
    again, _, kp2 = features.extract_many(sc.images, preset="colmap", max_features=300)
    assert np.array_equal(again, D) and np.array_equal(kp2, kp)
    with pytest.raises(InputError, match="not OpenCV"):
        features.create_sift("colmap")


def test_a_link_is_refused_when_another_member_pair_contradicts_a_verified_model():
    """Clusters {f0 (image 0), f1 (image 1)} and {f2 (image 2)}, linked by (f1, f2). Image pair
    (1, 2) has no model; pair (0, 2) is verified with the identity homography, and f0, f2 lie
    40 px apart: the union is refused. Without that model the same link joins them."""
    from dqm.vision.guided import _merge

    labels = np.array([0, 0, 2])
    ids = np.array([0, 1, 2])
    kp = np.array([[10.0, 10.0], [10.0, 10.0], [50.0, 30.0]])
    eye = PairModel(0, 2, "H", np.eye(3), np.zeros((0, 2), int), np.zeros((0, 2), int))
    link = (np.array([1]), np.array([2]), np.array([1.0]))
    out, merged, c2, geo = _merge(labels, ids, kp, {(0, 2): eye}, *link, 16.0)
    assert merged == 0 and geo == 1 and len(np.unique(out)) == 2
    out, merged, c2, geo = _merge(labels, ids, kp, {}, *link, 16.0)
    assert merged == 1 and geo == 0 and len(np.unique(out)) == 1
    # a link whose union would hold two features of one image is refused (C2)
    out, merged, c2, geo = _merge(np.array([0, 1, 1]), np.array([0, 0, 1]), kp, {}, np.array([0]), np.array([2]),
                                  np.array([1.0]), 16.0)
    assert merged == 0 and c2 == 1


def test_the_merge_residual_test_agrees_with_the_models_residuals():
    """_merge checks member pairs one at a time with scalar code; it must accept exactly the pairs
    that PairModel.sq_residuals (the vectorised residuals) puts within the threshold."""
    from dqm.vision.guided import _residual_ok

    rng = np.random.default_rng(2)
    K = np.array([[500, 0, 300], [0, 500, 200], [0, 0, 1.0]])
    tx = np.array([[0, -0.1, 0.2], [0.1, 0, -1.0], [-0.2, 1.0, 0]])
    F = np.linalg.inv(K).T @ tx @ np.linalg.inv(K)
    H = np.array([[1.02, 0.01, 5.0], [-0.02, 0.98, -3.0], [1e-5, -2e-5, 1.0]])
    xa = rng.uniform(0, 600, (2000, 2))
    for kind, M in (("F", F), ("H", H)):
        model = PairModel(0, 1, kind, M, np.zeros((0, 2), int), np.zeros((0, 2), int))
        near = xa @ M[:2, :2].T + M[:2, 2] if kind == "H" else None
        xb = (near if near is not None else xa) + rng.normal(0, 3, xa.shape)
        res = model.sq_residuals(xa, xb)
        scalar = np.array([_residual_ok(kind, tuple(M.ravel()), tuple(p), tuple(q), 16.0) for p, q in zip(xa, xb)])
        assert 0 < scalar.sum() < len(xa), kind  # both sides of the threshold are exercised
        assert np.array_equal(scalar, res <= 16.0), kind
