"""Defined behaviour, determinism and bad input of dqm.quickmatch."""
import warnings

import numpy as np
import pytest
from conftest import assert_consistent

import dqm
from dqm import InputError, QuickMatch
from dqm.synthetic import sift_like


@pytest.fixture(scope="module")
def scene():
    return sift_like(n_images=6, n_points=200, clutter_per_image=80, seed=11)


def pairwise_pr(labels, truth):
    """Pairwise precision/recall of clusters against ground-truth point ids (-1: none)."""
    same_pred = labels[:, None] == labels[None, :]
    same_true = (truth[:, None] == truth[None, :]) & (truth[:, None] >= 0)
    iu = np.triu_indices(len(labels), 1)
    p, t = same_pred[iu], same_true[iu]
    return (p & t).sum() / max(1, p.sum()), (p & t).sum() / max(1, t.sum())


def test_synthetic_scene_is_matched_well(scene):
    r = dqm.quickmatch(scene.descriptors, scene.image_ids)
    assert_consistent(r.labels, scene.image_ids)
    precision, recall = pairwise_pr(r.labels, scene.point_ids)
    assert precision > 0.95 and recall > 0.8, (precision, recall)


def test_deterministic(scene):
    a = dqm.quickmatch(scene.descriptors, scene.image_ids)
    b = dqm.quickmatch(scene.descriptors, scene.image_ids, n_threads=1)
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.parent, b.parent)
    np.testing.assert_array_equal(a.density, b.density)


def test_labels_follow_a_permutation_of_the_input(scene):
    rng = np.random.default_rng(0)
    perm = rng.permutation(len(scene))
    a = dqm.quickmatch(scene.descriptors, scene.image_ids)
    b = dqm.quickmatch(scene.descriptors[perm], scene.image_ids[perm])
    # same partition (ties by index may differ only on exactly equal densities, absent here)
    pairs = set(zip(a.labels[perm].tolist(), b.labels.tolist()))
    assert len(pairs) == a.n_clusters == b.n_clusters


def test_descriptor_scale_does_not_matter(scene):
    a = dqm.quickmatch(scene.descriptors, scene.image_ids)
    b = dqm.quickmatch(scene.descriptors.astype(np.float64) / 512.0, scene.image_ids)
    np.testing.assert_array_equal(a.labels, b.labels)


def test_rho_monotone(scene):
    counts = [dqm.quickmatch(scene.descriptors, scene.image_ids, rho=r).n_clusters for r in (0.3, 0.6, 0.9, 1.2)]
    assert counts == sorted(counts, reverse=True) and counts[0] > counts[-1]


def test_estimator_api(scene):
    qm = QuickMatch(rho=0.8).fit(scene.descriptors, scene.image_ids)
    ref = dqm.quickmatch(scene.descriptors, scene.image_ids, rho=0.8)
    np.testing.assert_array_equal(qm.labels_, ref.labels)
    assert qm.n_clusters_ == ref.n_clusters
    assert qm.get_params()["rho"] == 0.8
    with pytest.raises(InputError, match="unknown parameter"):
        qm.set_params(bogus=1)


def test_result_helpers(scene):
    r = dqm.quickmatch(scene.descriptors, scene.image_ids)
    sizes = r.cluster_sizes()
    assert sizes.sum() == len(scene) and len(sizes) == r.n_clusters
    clusters = r.clusters(min_size=2)
    assert all(len(c) >= 2 for c in clusters)
    assert sum(len(c) for c in r.clusters()) == len(scene)
    text = r.summary()
    assert f"{len(scene)} features" in text and f"{r.n_clusters} clusters" in text


# ----------------------------------------------------------------- edge cases

def test_empty_input():
    r = dqm.quickmatch(np.zeros((0, 128), np.uint8), np.zeros(0, int))
    assert r.n_features == 0 and r.n_clusters == 0 and r.labels.shape == (0,)


def test_single_image_gives_singletons():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(50, 8))
    with pytest.warns(UserWarning, match="one image"):
        r = dqm.quickmatch(X, np.zeros(50, int))
    assert r.n_clusters == 50
    assert np.isfinite(r.sigma).all()


def test_image_with_single_feature_uses_median_sigma():
    rng = np.random.default_rng(1)
    X = rng.normal(size=(21, 8))
    ids = np.array([0] * 10 + [1] * 10 + [2])
    r = dqm.quickmatch(X, ids)
    assert r.sigma[20] == pytest.approx(np.median(r.sigma[:20]))
    assert_consistent(r.labels, ids)


def test_single_feature_can_match():
    """A lone feature of its image still joins the cluster of its twin elsewhere."""
    rng = np.random.default_rng(2)
    X = rng.normal(size=(20, 8))
    lone = X[3] + 1e-3
    r = dqm.quickmatch(np.vstack([X, lone]), np.array([0] * 10 + [1] * 10 + [2]))
    assert r.labels[20] == r.labels[3]


def test_all_images_single_feature_nothing_merges():
    X = np.array([[0.0, 0.0], [0.0, 0.001], [5.0, 5.0]])
    r = dqm.quickmatch(X, [0, 1, 2])
    assert (r.sigma == 0).all() and r.n_clusters == 3


def test_duplicates_within_an_image_never_merge():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(10, 8))
    B = A + 1e-3 * rng.normal(size=A.shape)
    X = np.vstack([A, A[:1], B])  # feature 10 duplicates feature 0 in image 0
    ids = np.array([0] * 11 + [1] * 10)
    r = dqm.quickmatch(X, ids)
    assert r.sigma[0] == 0 and r.sigma[10] == 0
    assert (r.labels == r.labels[0]).sum() == 1 and (r.labels == r.labels[10]).sum() == 1
    assert_consistent(r.labels, ids)
    others = np.arange(1, 10)
    assert (r.labels[others] == r.labels[11 + others]).all()  # the rest still match


def test_duplicates_across_images_match_with_equal_density():
    rng = np.random.default_rng(4)
    A = rng.normal(size=(10, 8))
    X = np.vstack([A, A, A])
    ids = np.repeat([0, 1, 2], 10)
    r = dqm.quickmatch(X, ids)
    assert r.n_clusters == 10
    for k in range(10):
        assert r.labels[k] == r.labels[10 + k] == r.labels[20 + k]
        assert r.density[k] == r.density[10 + k] == r.density[20 + k]
    # equal density: the lower index ranks higher, so it is the parent
    assert r.parent[10] == 0 and r.parent[20] == 0


def test_uint8_and_float_inputs_agree(scene):
    a = dqm.quickmatch(scene.descriptors, scene.image_ids)
    b = dqm.quickmatch(scene.descriptors.astype(np.float32), scene.image_ids)
    np.testing.assert_array_equal(a.labels, b.labels)


def test_arbitrary_image_ids(scene):
    a = dqm.quickmatch(scene.descriptors, scene.image_ids)
    b = dqm.quickmatch(scene.descriptors, scene.image_ids * 7 + 1000)
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(b.image_ids, scene.image_ids * 7 + 1000)


# ----------------------------------------------------------------- bad input

X4 = np.arange(16, dtype=float).reshape(4, 4)
IDS4 = np.array([0, 0, 1, 1])


@pytest.mark.parametrize(
    "descriptors, ids, pattern",
    [
        (X4[0], IDS4, "must be 2-D"),
        (X4[None], IDS4, "must be 2-D"),
        (np.zeros((4, 0)), IDS4, "zero dimensions"),
        (X4.astype(complex), IDS4, "float or integer"),
        (X4.astype(bool), IDS4, "float or integer"),
        (np.array([["a"] * 4] * 4), IDS4, "float or integer"),
        (np.where(X4 == 5, np.nan, X4), IDS4, "NaN.*row 1"),
        (np.where(X4 == 9, np.inf, X4), IDS4, "inf"),
        (X4, IDS4[:3], "3 entries but there are 4 descriptors"),
        (X4, IDS4[:, None], "must be 1-D"),
        (X4, np.array([0, 0.5, 1, 1]), "must be integers"),
        (X4, np.array(["a", "a", "b", "b"]), "must be integers"),
    ],
)
def test_bad_input_is_named(descriptors, ids, pattern):
    with pytest.raises(InputError, match=pattern):
        dqm.quickmatch(descriptors, ids)


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        ({"rho": 0}, "rho must be a positive"),
        ({"rho": -1}, "rho must be a positive"),
        ({"rho": float("nan")}, "rho must be a positive"),
        ({"rho": "big"}, "rho must be a positive"),
        ({"ratio_density": 0}, "ratio_density"),
        ({"kernel": "epanechnikov"}, "kernel must be one of"),
        ({"parent": "nearest"}, "parent must be one of"),
        ({"sigma": np.ones(3)}, "sigma must be 4"),
        ({"sigma": -np.ones(4)}, "sigma must be 4"),
    ],
)
def test_bad_parameters_are_named(kwargs, pattern):
    with pytest.raises(InputError, match=pattern):
        dqm.quickmatch(X4, IDS4, **kwargs)


def test_input_error_is_a_value_error():
    assert issubclass(InputError, ValueError)


def test_no_warning_for_normal_input(scene):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dqm.quickmatch(scene.descriptors, scene.image_ids)
