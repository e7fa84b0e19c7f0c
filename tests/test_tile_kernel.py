"""The tile kernel's contracts (issue 23): every SIMD level computes what the numpy version
computes, the densities' error bounds hold against float64, integer descriptors give exact
float32 distances, and the pass can hand its edges to a consumer tile by tile."""
import numpy as np
import pytest

import dqm
from dqm.core import clustering, native, pairs
from dqm.synthetic import sift_like
from test_quickmatch_equivalence import clustered

needs_native = pytest.mark.skipif(not native.native_available(), reason="the native tile kernel is not built")


@pytest.fixture
def levels():
    """Every SIMD level this CPU runs (the kernel is reset to its best afterwards)."""
    top = native.set_simd_level(99)
    yield list(range(top, -1, -1))
    native.set_simd_level(99)


def sift_tile(seed=0, m=300, k=517):
    """A float32 tile of exact squared distances between uint8 SIFT-like rows, and kernel weights."""
    ds = sift_like(n_images=6, n_points=250, clutter_per_image=120, seed=seed)
    X, ids = ds.descriptors, ds.image_ids
    aug = pairs.Augmented(X)
    _, img = np.unique(ids, return_inverse=True)
    sig = pairs.nearest_same_image(aug, img.ravel(), int(img.max()) + 1)
    sig[~np.isfinite(sig)] = 0.0
    a, b = np.arange(m), np.arange(m, m + k)
    G = aug.left[a] @ aug.right[b].T
    return aug, sig, a, b, np.ascontiguousarray(G)


@needs_native
@pytest.mark.parametrize("kernel", ["gaussian", "quadratic"])
def test_every_simd_level_matches_numpy(levels, kernel):
    aug, sig, a, b, G = sift_tile()
    w, active = clustering.kernel_weights(sig, kernel, 0.25)
    w, s = w.astype(np.float32), active.astype(np.float32)
    rad2 = pairs.search_rad2(aug, 1.2 * sig)
    args = (G, w[b], s[b], w[a], s[a], kernel, rad2[a], rad2[b])
    ref = [np.zeros(len(a)), np.zeros(len(a)), np.zeros(len(b)), np.zeros(len(b))]
    rr, rc = native.tile_sym(*args, *ref, use_native=False)
    assert len(rr) > 0  # the radius finds pairs, so the candidate test is exercised
    for level in levels:
        assert native.set_simd_level(level) == level
        got = [np.zeros(len(a)), np.zeros(len(a)), np.zeros(len(b)), np.zeros(len(b))]
        r, c = native.tile_sym(*args, *got)
        assert sorted(zip(r.tolist(), c.tolist())) == sorted(zip(rr.tolist(), rc.tolist())), level
        for x, y in zip(got, ref):
            np.testing.assert_allclose(x, y, rtol=2e-6, atol=1e-30)
        # the diagonal-tile kernel (one direction, the self pair skipped)
        d_ref, e_ref = np.zeros(len(a)), np.zeros(len(a))
        sq = np.ascontiguousarray(G[:, :len(a)])
        cr = native.tile(sq, w[b[:len(a)]], s[b[:len(a)]], kernel, rad2[a], 3, d_ref, e_ref, use_native=False)
        d, e = np.zeros(len(a)), np.zeros(len(a))
        cn = native.tile(sq, w[b[:len(a)]], s[b[:len(a)]], kernel, rad2[a], 3, d, e)
        assert sorted(zip(*map(list, cn))) == sorted(zip(*map(list, cr)))
        np.testing.assert_allclose(d, d_ref, rtol=2e-6, atol=1e-30)


@needs_native
def test_labels_identical_at_every_simd_level(levels):
    ds = sift_like(n_images=5, n_points=300, clutter_per_image=150, seed=11)
    runs = []
    for level in levels:
        native.set_simd_level(level)
        runs.append(dqm.quickmatch(ds.descriptors, ds.image_ids, rho=1.1))
    for r in runs[1:]:
        np.testing.assert_array_equal(r.labels, runs[0].labels)
        np.testing.assert_array_equal(r.parent, runs[0].parent)


@needs_native
def test_rows_longer_than_the_bound_are_refused():
    G = np.zeros((2, native.MAX_ROW + 1), np.float32)
    w = np.ones(G.shape[1], np.float32)
    with pytest.raises(ValueError, match="at most"):
        native.tile(G, w, w, "gaussian", np.zeros(2, np.float32), 0, np.zeros(2), np.zeros(2))


def test_integer_descriptors_give_exact_float32_distances():
    ds = sift_like(n_images=4, n_points=200, clutter_per_image=50, seed=2)
    X = ds.descriptors
    assert X.dtype == np.uint8
    aug = pairs.Augmented(X)
    assert aug.exact_d2 and aug.gamma == 0.0 and aug.Xc is None
    G = aug.left[:300] @ aug.right[300:700].T
    exact = ((X[:300, None, :].astype(np.int64) - X[None, 300:700, :]) ** 2).sum(-1)
    np.testing.assert_array_equal(G.astype(np.int64), exact)
    # the same integers as floats, and a shifted copy: still exact
    assert pairs.Augmented(X.astype(np.float32) + 1000.0).exact_d2
    # non-integers, or integers whose GEMM sums leave float32's exact range, keep the error bound
    assert not pairs.Augmented(X + 0.5).exact_d2
    big = pairs.Augmented(X.astype(np.int32) * 64)
    assert not big.exact_d2 and big.gamma > 0


@pytest.mark.parametrize("kernel", ["gaussian", "quadratic"])
@pytest.mark.parametrize("integer", [True, False])
def test_density_error_bounds_hold_against_float64(kernel, integer):
    """The pass's densities lie within their bounds of the float64 values (the contract that
    decides which densities are refined)."""
    if integer:
        ds = sift_like(n_images=6, n_points=300, clutter_per_image=200, seed=4)
        X, ids = ds.descriptors, ds.image_ids
    else:
        X, ids = clustered(3, n_images=8, n_points=200, dim=32, clutter=80)
    aug = pairs.Augmented(X)
    assert aug.exact_d2 == integer
    _, img = np.unique(ids, return_inverse=True)
    sig = pairs.nearest_same_image(aug, img.ravel(), int(img.max()) + 1)
    w, active = clustering.kernel_weights(sig, kernel, 0.25 if kernel == "gaussian" else 1.0)
    dens, err, _, _ = pairs.kernel_pass(aug, w, active, kernel, 0.9 * sig)
    exact = pairs.exact_density_others(aug, np.arange(aug.n), w, active, kernel)
    assert (np.abs(dens - exact) <= err).all()
    if integer:  # exact distances: the bound is the kernel terms' own rounding, far below the float one
        float_err = err + (pairs.error_gamma(aug.dim) * (aug.norm2 + aug.max_norm2)
                           * (err / pairs.term_error_factor(aug)))
        assert np.median(err / float_err) < 0.5


def test_edges_handed_over_tile_by_tile_are_the_collected_ones(monkeypatch):
    monkeypatch.setattr(pairs, "BLOCK", 128)
    ds = sift_like(n_images=5, n_points=200, clutter_per_image=100, seed=8)
    aug = pairs.Augmented(ds.descriptors)
    _, img = np.unique(ds.image_ids, return_inverse=True)
    sig = pairs.nearest_same_image(aug, img.ravel(), int(img.max()) + 1)
    zero = np.zeros(aug.n)
    for limit in (None, 700):
        _, _, cr, cc = pairs.kernel_pass(aug, zero, zero, "quadratic", 1.3 * sig, rows_limit=limit)
        got = []
        _, _, r2, c2 = pairs.kernel_pass(aug, zero, zero, "quadratic", 1.3 * sig, rows_limit=limit,
                                         on_edges=lambda r, c: got.append((r, c)))
        assert len(r2) == 0 and len(got) > 1
        r = np.concatenate([g[0] for g in got])
        c = np.concatenate([g[1] for g in got])
        assert sorted(zip(r.tolist(), c.tolist())) == sorted(zip(cr.tolist(), cc.tolist()))
