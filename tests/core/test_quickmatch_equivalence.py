"""The fast engine against the dense reference (tests/dense_reference.py)."""
import numpy as np
import pytest
from conftest import assert_consistent
from dense_reference import dense_quickmatch, same_partition
from generators.points import clustered

import dqm
from dqm.core import native
from dqm.synthetic import sift_like

KERNELS = ["gaussian", "quadratic"]
PARENTS = ["any", "other-image"]


def check_against_reference(X, ids, rho, kernel, parent):
    r = dqm.quickmatch(X, ids, rho=rho, kernel=kernel, parent=parent)
    labels, sigma, density, par, pdist = dense_quickmatch(X, ids, rho, kernel=kernel, parent_mode=parent)
    assert_consistent(r.labels, ids)
    assert same_partition(r.labels, labels)
    np.testing.assert_allclose(r.sigma, sigma, rtol=1e-12, atol=0)
    np.testing.assert_allclose(r.density, density, rtol=1e-3)
    # parents agree wherever dqm reports one (within rho * sigma); beyond, none can merge
    has = r.parent >= 0
    np.testing.assert_array_equal(r.parent[has], par[has])
    np.testing.assert_allclose(r.parent_distance[has], pdist[has], rtol=1e-12)
    assert (pdist[~has] >= rho * sigma[~has] * (1 - 1e-12)).all()
    return r


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("parent", PARENTS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_clustered_data(seed, kernel, parent):
    X, ids = clustered(seed)
    r = check_against_reference(X, ids, rho=0.9, kernel=kernel, parent=parent)
    assert r.n_clusters < len(X) * 0.8  # the data really has matches


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("parent", PARENTS)
def test_synthetic_sift(kernel, parent):
    ds = sift_like(n_images=5, n_points=150, clutter_per_image=60, noise=0.3, seed=3)
    check_against_reference(ds.descriptors, ds.image_ids, rho=0.75, kernel=kernel, parent=parent)


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("parent", PARENTS)
def test_real_sift_graf(graf_sift, kernel, parent):
    X, ids = graf_sift
    rng = np.random.default_rng(0)
    sel = np.sort(rng.choice(len(X), 2500, replace=False))
    r = check_against_reference(X[sel], ids[sel], rho=1.0, kernel=kernel, parent=parent)
    assert r.n_clusters < len(sel)


def test_numpy_and_native_paths_agree(monkeypatch):
    if not native.native_available():
        pytest.skip("native tile kernel not built on this machine (numpy path only)")
    ds = sift_like(n_images=4, n_points=300, clutter_per_image=100, seed=5)
    fast = dqm.quickmatch(ds.descriptors, ds.image_ids)
    monkeypatch.setattr(native, "_LIB", None)
    slow = dqm.quickmatch(ds.descriptors, ds.image_ids)
    np.testing.assert_array_equal(fast.labels, slow.labels)
    np.testing.assert_array_equal(fast.parent, slow.parent)
    np.testing.assert_allclose(fast.density, slow.density, rtol=1e-5)


def test_many_blocks_match_reference(monkeypatch):
    """Block size shrunk so that diagonal, off-diagonal and ragged tiles all occur."""
    from dqm.core import pairs

    monkeypatch.setattr(pairs, "BLOCK", 64)
    X, ids = clustered(7, n_images=5, n_points=80)
    for kernel in KERNELS:
        check_against_reference(X, ids, rho=0.9, kernel=kernel, parent="any")
