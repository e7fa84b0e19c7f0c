"""The tile kernel's contracts (issue 23): every SIMD level computes what the numpy version
computes, the densities' error bounds hold against float64, integer descriptors give exact
float32 distances, and the pass can hand its edges to a consumer tile by tile."""
import numpy as np
import pytest
from generators.points import clustered

import dqm
from dqm.core import clustering, native, pairs
from dqm.synthetic import sift_like

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
                                         on_edges=lambda r, c, got=got: got.append((r, c)))
        assert len(r2) == 0 and len(got) > 1
        r = np.concatenate([g[0] for g in got])
        c = np.concatenate([g[1] for g in got])
        assert sorted(zip(r.tolist(), c.tolist())) == sorted(zip(cr.tolist(), cc.tolist()))
        # undirected: every pair of those edges once, lower index first, diagonal tiles (both directions) too
        once = []
        pairs.kernel_pass(aug, zero, zero, "quadratic", 1.3 * sig, rows_limit=limit, undirected=True,
                          on_edges=lambda r, c, got=once: got.append((r, c)))
        lo = np.concatenate([g[0] for g in once])
        hi = np.concatenate([g[1] for g in once])
        assert (lo < hi).all() and len(np.unique(lo * aug.n + hi)) == len(lo)
        np.testing.assert_array_equal(np.sort(lo * aug.n + hi),
                                      np.unique(np.minimum(cr, cc) * aug.n + np.maximum(cr, cc)))


needs_vnni = pytest.mark.skipif(native.simd_level() < 3, reason="the CPU has no AVX-512 VNNI (integer distance kernel)")


@pytest.mark.parametrize("fused", [False, pytest.param(True, marks=needs_vnni)])
def test_own_by_batch_pass_meets_exactly_the_cross_pairs(monkeypatch, fused):
    """A balanced agent meets one window of copies at a time (rows: its own features, columns: the
    window): the tiles cover the own-by-window rectangle only, at any boundary, and give exactly the cross
    edges, with the float GEMM and with the fused integer tiles (whose columns start at multiples of 32: a
    boundary inside a group of 32 puts a few own features among the columns; their pairs are filtered)."""
    monkeypatch.setattr(pairs, "BLOCK", 128)
    ds = sift_like(n_images=5, n_points=200, clutter_per_image=100, seed=8)
    aug = pairs.Augmented(ds.descriptors)
    if fused:
        assert aug.u8 is not None
    else:
        monkeypatch.setattr(aug, "integer_kernel", False)  # the float GEMM path (aug.u8 is then None)
    _, img = np.unique(ds.image_ids, return_inverse=True)
    sig = pairs.nearest_same_image(aug, img.ravel(), int(img.max()) + 1)
    n, zero, radius = aug.n, np.zeros(aug.n), 0.9 * sig
    X = aug.exact.astype(np.float64)
    n2 = (X * X).sum(1)
    d = np.sqrt(np.maximum(n2[:, None] + n2[None, :] - 2.0 * X @ X.T, 0.0))  # integers: exact in float64
    for cut in (700, 768, 1100):
        within = d < radius[:, None]  # child (row) -> candidate (column)
        within[:cut, :cut] = within[cut:, cut:] = False
        got = []
        pairs.kernel_pass(aug, zero, zero, "quadratic", radius, rows_limit=cut, cols_from=cut,
                          on_edges=lambda r, c, got=got: got.append((r, c)))
        r = np.concatenate([g[0] for g in got])
        c = np.concatenate([g[1] for g in got])
        assert ((r < cut) != (c < cut)).all(), cut  # own by batch only
        assert len(np.unique(r * n + c)) == len(r), cut  # every pair once
        kept = d[r, c] < radius[r]  # the pass's edges are a superset; the ones that matter are all there
        assert within.sum() > 0
        np.testing.assert_array_equal(np.sort(r[kept] * n + c[kept]), np.flatnonzero(within))
        # undirected (the balanced agents' call): each of those pairs once, lower index first
        once = []
        pairs.kernel_pass(aug, zero, zero, "quadratic", radius, rows_limit=cut, cols_from=cut, undirected=True,
                          on_edges=lambda r, c, got=once: got.append((r, c)))
        lo = np.concatenate([g[0] for g in once])
        hi = np.concatenate([g[1] for g in once])
        assert (lo < cut).all() and (hi >= cut).all(), cut
        np.testing.assert_array_equal(np.sort(lo * n + hi), np.unique(np.minimum(r, c) * n + np.maximum(r, c)))


@needs_vnni
def test_vnni_distances_are_exact_for_every_tile_shape():
    rng = np.random.default_rng(1)
    X = rng.integers(0, 256, size=(300, 130), dtype=np.uint8)  # any bytes, a dimension not a multiple of 4
    ops = native.U8Operands(X)
    exact = ((X[:, None, :].astype(np.int64) - X[None, :, :]) ** 2).sum(-1)
    for a, a1, b, b1 in [(0, 300, 0, 300), (5, 17, 32, 33), (288, 300, 256, 300), (0, 1, 64, 127)]:
        np.testing.assert_array_equal(ops.d2(a, a1, b, b1).astype(np.int64), exact[a:a1, b:b1])
    other = native.U8Operands(X[::7])  # rows packed apart, columns from the full set
    np.testing.assert_array_equal(other.d2(0, len(X[::7]), 0, 300, cols=ops).astype(np.int64), exact[::7])
    with pytest.raises(ValueError, match="multiples of 32"):
        ops.d2(0, 5, 16, 40)


def _packed_by_numpy(X):
    """Reference for U8Operands: its layout made with numpy (rows x - 128 as int8, columns in groups of 16
    features with 4 bytes of each a step, na = |x|^2, nb = |x|^2 - 256 sum(x), zero padding)."""
    n, dim = X.shape
    nq = -(-dim // 4)
    groups = -(-n // 32) * 2
    rows = np.zeros((n + 8, 4 * nq), np.int8)
    rows[:n, :dim] = (X ^ np.uint8(0x80)).view(np.int8)
    cols = np.zeros((groups * 16, 4 * nq), np.uint8)
    cols[:n, :dim] = X
    cols = cols.reshape(groups, 16, nq, 4).transpose(0, 2, 1, 3)
    norm = np.square(X, dtype=np.uint16).sum(axis=1, dtype=np.int32)
    na, nb = np.zeros(n + 8, np.int32), np.zeros(groups * 16, np.int32)
    na[:n], nb[:n] = norm, norm - 256 * X.sum(axis=1, dtype=np.int32)
    return {"rows": rows, "cols": cols, "na": na, "nb": nb}


@pytest.mark.skipif(native._LIB is None, reason="native kernel not built")
def test_native_packing_is_numpys_packing_of_the_gathered_rows():
    """U8Operands packs in C, gathering the rows it is given (no copy of them first): the same bytes and norms
    as numpy's packing of the gathered rows, for counts around the 16- and 32-feature groups, dimensions that
    are no multiple of 4, a row stride that is no row's size, and no rows at all."""
    rng = np.random.default_rng(3)
    for n, dim in [(0, 128), (1, 128), (15, 3), (16, 64), (31, 130), (33, 128), (200, 129)]:
        X = rng.integers(0, 256, size=(n + 9, dim + 2), dtype=np.uint8)[:, 1:dim + 1]  # strided rows
        rows = rng.permutation(n + 9)[:n]
        for got, want in ((native.U8Operands(X, rows), _packed_by_numpy(X[rows])),
                          (native.U8Operands(X), _packed_by_numpy(X))):
            for part in ("rows", "cols", "na", "nb"):
                np.testing.assert_array_equal(getattr(got, part), want[part], err_msg=f"{n} {dim} {part}")
    with pytest.raises(IndexError, match="outside"):
        native.U8Operands(X, np.array([0, n + 9]))


@needs_vnni
@pytest.mark.parametrize("kernel", ["gaussian", "quadratic"])
def test_fused_integer_pass_matches_the_float_pass(kernel, monkeypatch):
    monkeypatch.setattr(pairs, "BLOCK", 256)  # diagonal, off-diagonal and ragged tiles
    ds = sift_like(n_images=5, n_points=300, clutter_per_image=100, seed=6)
    aug = pairs.Augmented(ds.descriptors)
    assert aug.u8 is not None
    _, img = np.unique(ds.image_ids, return_inverse=True)
    sig = pairs.nearest_same_image(aug, img.ravel(), int(img.max()) + 1)
    w, active = clustering.kernel_weights(sig, kernel, 0.25)
    fused = pairs.kernel_pass(aug, w, active, kernel, 1.1 * sig)
    monkeypatch.setattr(aug, "integer_kernel", False)
    plain = pairs.kernel_pass(aug, w, active, kernel, 1.1 * sig)
    assert sorted(zip(fused[2].tolist(), fused[3].tolist())) == sorted(zip(plain[2].tolist(), plain[3].tolist()))
    np.testing.assert_allclose(fused[0], plain[0], rtol=1e-6, atol=1e-30)
    # the float64 densities from the integer distances equal those from the float32 GEMM's
    idx = np.arange(0, aug.n, 7)
    monkeypatch.undo()
    a = pairs.exact_density_others(aug, idx, w, active, kernel)
    monkeypatch.setattr(aug, "integer_kernel", False)
    b = pairs.exact_density_others(aug, idx, w, active, kernel)
    np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-300)


@pytest.mark.parametrize("as_float", [False, True])
@pytest.mark.parametrize("kernel", ["gaussian", "quadratic"])
def test_exact_densities_in_chunks_on_threads_are_the_same_bits(kernel, as_float):
    """The refinement's float64 densities come in chunks of targets, several threads at a time: every value is
    the same whatever the thread count, and each equals the sum over the active others computed directly."""
    ds = sift_like(n_images=5, n_points=300, clutter_per_image=100, seed=8)
    X = ds.descriptors.astype(np.float64) if as_float else ds.descriptors
    aug = pairs.Augmented(X)
    _, img = np.unique(ds.image_ids, return_inverse=True)
    sig = pairs.nearest_same_image(aug, img.ravel(), int(img.max()) + 1)
    w, active = clustering.kernel_weights(sig, kernel, 0.25)
    idx = np.arange(aug.n)[::-1].copy()  # more than one chunk, out of order
    one = pairs.exact_density_others(aug, idx, w, active, kernel, n_threads=1)
    three = pairs.exact_density_others(aug, idx, w, active, kernel, n_threads=3)
    np.testing.assert_array_equal(one, three)
    Xd = ds.descriptors.astype(np.float64)
    for i in idx[::97]:
        d2 = ((Xd - Xd[i]) ** 2).sum(axis=1)
        t = d2 * w
        terms = np.exp(-t) if kernel == "gaussian" else np.maximum(1.0 - t, 0.0)
        terms[i] = 0.0
        np.testing.assert_allclose(one[idx == i], (terms * (active > 0)).sum(), rtol=1e-12, atol=1e-300)


@pytest.mark.parametrize("kernel", ["gaussian", "quadratic"])
def test_uint8_and_the_same_values_as_floats_give_identical_results(kernel):
    """uint8 input stays uint8 (the integer kernel where the CPU has it); the same values as
    float64 take the float32 GEMM path: both exact, so every output agrees bit for bit."""
    from dqm import validation

    ds = sift_like(n_images=6, n_points=300, clutter_per_image=120, seed=9)
    X, ids = ds.descriptors, ds.image_ids
    kept = validation.check_descriptors(X, keep_integer=True)
    assert kept.dtype == np.uint8 and np.shares_memory(kept, X)
    a = dqm.quickmatch(X, ids, kernel=kernel, rho=1.0)
    b = dqm.quickmatch(X.astype(np.float64), ids, kernel=kernel, rho=1.0)
    for field in ("labels", "parent", "sigma", "parent_distance"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    np.testing.assert_allclose(a.density, b.density, rtol=1e-12)


@needs_native
def test_a_native_kernel_built_for_another_dqm_is_not_loaded(monkeypatch):
    """A kernel older than the Python beside it (a checkout updated without a new install: its entry points take
    other buffers) or of another version is never called: the numpy version runs, and one warning says to
    rebuild. The kernel built here is this dqm's."""
    import logging

    assert native._LIB.dqm_kernel_version() == native.KERNEL_VERSION

    class Call:
        restype = None

        def __call__(self):
            return native.KERNEL_VERSION + 1

    class Older:  # built before the check: no such symbol
        def __init__(self, path):
            pass

        def __getattr__(self, name):
            raise AttributeError(name)

    class Newer:
        def __init__(self, path):
            self.dqm_kernel_version = Call()

    records = []
    handler = logging.Handler()
    handler.emit = records.append
    log = logging.getLogger("dqm.core")
    log.addHandler(handler)
    level = log.level
    log.setLevel(logging.WARNING)
    try:
        for fake, says in [(Older, "version None"), (Newer, f"version {native.KERNEL_VERSION + 1}")]:
            monkeypatch.setattr(native.ctypes, "CDLL", fake)
            records.clear()
            assert native._load() is None
            assert records and all(says in r.getMessage() and "pip install -e ." in r.getMessage() for r in records)
    finally:
        log.removeHandler(handler)
        log.setLevel(level)


@needs_native
@pytest.mark.parametrize("kernel", ["gaussian", "quadratic"])
def test_the_fast_engines_scan_tile_matches_numpy_at_every_simd_level(levels, kernel):
    """The scan tile (dqm/core/inverted_lists.py): own rows one way without their self pair, other rows both
    ways except the pairs the other list's tile keeps, and edges in both directions."""
    aug, sig, a, b, G = sift_tile(seed=3, m=300, k=517)
    G = np.ascontiguousarray(G[:, :203])  # columns not a multiple of 8: the scalar tail runs too
    b = b[:203]
    w, active = clustering.kernel_weights(sig, kernel, 0.25)
    w, s = w.astype(np.float32), active.astype(np.float32)
    rad2 = pairs.search_rad2(aug, 1.2 * sig)
    rng = np.random.default_rng(0)
    row_list = rng.integers(0, 130, len(a)).astype(np.int32)
    row_list[:40] = 64  # the tile's own list: 40 own rows, the self pair at column r + 5
    bits = rng.integers(0, 2 ** 62, (len(b), 3)).astype(np.uint64)  # 130 lists: 3 words per column
    args = (G, w[b], s[b], w[a], s[a], kernel, rad2[a], rad2[b], 40, 5, row_list, bits, 64)
    d_ref, c_ref = np.zeros(len(a)), np.zeros(len(b))
    rr, rc, rg = native.scan_tile(*args, d_ref, c_ref, use_native=False)
    assert (rr < 0).any() and (rr >= 0).any()  # edges in both directions are exercised
    np.testing.assert_array_equal(rg, G[np.where(rr < 0, -1 - rr, rr), rc])  # each edge's squared distance
    wide = np.zeros((len(a), 32 + G.shape[1]), np.float32)
    wide[:, 32 - 7:-7] = G
    strided = wide[:, 32 - 7:-7]  # a view with a longer row stride, as the integer kernel's scan passes
    for level in levels:
        assert native.set_simd_level(level) == level
        d, c = np.zeros(len(a)), np.zeros(len(b))
        r, cc, g = native.scan_tile(*args, d, c)
        assert sorted(zip(r.tolist(), cc.tolist(), g.tolist())) == sorted(zip(rr.tolist(), rc.tolist(), rg.tolist()))
        np.testing.assert_allclose(d, d_ref, rtol=2e-5, atol=1e-12)
        np.testing.assert_allclose(c, c_ref, rtol=2e-5, atol=1e-12)
        d2, c2 = np.zeros(len(a)), np.zeros(len(b))
        out = native.scan_tile(strided, *args[1:], d2, c2)
        for x, y in zip(out + (d2, c2), (r, cc, g, d, c)):
            np.testing.assert_array_equal(x, y)


@needs_native
@pytest.mark.parametrize("kernel", ["gaussian", "quadratic"])
def test_a_scan_task_in_one_native_call_gives_the_block_by_block_results(kernel):
    """U8Scan.run (gather, integer distances and scan tile in one call) against the loop it replaced: rows
    gathered, U8Operands.d2 from the multiple of 32 below each block of at most MAX_ROW columns, scan_tile
    per block (the task makes its distances in strips of 64 rows). A list of 1,100 columns from an unaligned
    start (two blocks), own rows, a tightened limit on
    some features, and an edge buffer far too small (retries): the same sums to the bit, the same edges."""
    if native.simd_level() < 3:
        pytest.skip("no AVX-512 VNNI on this CPU: the integer scan does not run here")
    ds = sift_like(n_images=8, n_points=300, clutter_per_image=100, seed=5)
    X = ds.descriptors
    n = len(X)
    rng = np.random.default_rng(1)
    ops = native.U8Operands(X)
    w = rng.uniform(1e-5, 1e-4, n).astype(np.float32)
    s = (rng.random(n) < 0.9).astype(np.float32)
    rad2 = np.full(n, 60000.0, np.float32)
    limit = np.full(n, np.inf, np.float32)
    limit[rng.random(n) < 0.3] = 30000.0
    lists = rng.integers(0, 10, n).astype(np.int32)
    bits = rng.integers(0, 2 ** 10, (n, 1)).astype(np.uint64)
    lo, hi, r0, n_own, list_index = 37, 37 + 1100, 0, 100, 4  # own rows in two of the task's strips of 64 rows
    idx = np.concatenate([np.arange(lo, lo + n_own), rng.choice(np.arange(hi, n), 250, replace=False)])
    lists[lo:hi] = list_index
    rows = native.U8Operands(X[idx])
    d_ref, c_ref, edges = np.zeros(len(idx)), np.zeros(hi - lo), []
    for c0 in range(lo, hi, native.MAX_ROW):
        c1 = min(hi, c0 + native.MAX_ROW)
        b = c0 - c0 % 32
        G = rows.d2(0, len(idx), b, c1, cols=ops)[:, c0 - b:]
        r, c, g = native.scan_tile(np.ascontiguousarray(G), w[c0:c1], s[c0:c1], w[idx], s[idx], kernel,
                                   np.minimum(rad2[idx], limit[idx]), np.minimum(rad2[c0:c1], limit[c0:c1]),
                                   n_own, lo + r0 - c0, lists[idx], bits[c0:c1], list_index, d_ref,
                                   c_ref[c0 - lo:c1 - lo])
        edges.append((r, c + c0, g))
    ref = [np.concatenate(e) for e in zip(*edges)]
    assert len(edges) == 2 and (ref[0] < 0).any() and (ref[0] >= 0).any()
    scan = native.U8Scan(ops, w, s, kernel, rad2, limit, lists, bits)
    ws = scan.buffers(400)
    ws["edges"] = native._edge_buffers(16)  # far too small: the task runs again with more room
    d, c, got = scan.run(idx, lo, hi, n_own, r0, list_index, ws)
    assert len(ws["edges"][0]) > 16
    np.testing.assert_array_equal(d, d_ref)
    np.testing.assert_array_equal(c, c_ref)
    for x, y in zip(got, ref):
        np.testing.assert_array_equal(x, y)
    with pytest.raises(ValueError):
        scan.run(np.arange(401), lo, hi, n_own, r0, list_index, ws)  # more rows than the workspace holds
    for bad_rows, bad_hi in (([0, n], hi), ([-1], hi), ([0], n + 1)):  # refused before the C loop reads
        with pytest.raises(IndexError):
            scan.run(np.array(bad_rows), lo, bad_hi, 0, r0, list_index, ws)


def test_native_break_merge_gives_the_python_loops_labels():
    """dqm_merge_clusters against tree.merge_clusters' Python loop: ties in distance, NaN scales (Python's
    min() keeps the first NaN, the C code follows it), images seen many times, one-feature inputs."""
    from dqm.core import tree

    if not native.native_available():
        pytest.skip("the native kernel is not built")
    rng = np.random.default_rng(0)
    merged = 0
    for trial in range(150):
        n = int(rng.integers(1, 300))
        parent = np.where(rng.random(n) < 0.8, rng.integers(0, n, n), -1)
        parent[parent == np.arange(n)] = -1
        pdist = rng.integers(0, 20, n) / 10.0
        sigma = rng.integers(1, 10, n) / 5.0
        if trial % 5 == 0:
            sigma[rng.random(n) < 0.2] = np.nan
        image = rng.integers(0, max(1, n // int(rng.integers(1, 20))), n)
        fast = tree.merge_clusters(parent, pdist, sigma, image, 1.3)
        slow = tree.merge_clusters(parent, pdist, sigma, image, 1.3, use_native=False)
        np.testing.assert_array_equal(fast, slow)
        merged += n - len(np.unique(fast))
    assert merged > 1000  # the cases do merge, and refuse merges (image clashes, scales)


def test_native_uint8_distances_are_the_exact_integers():
    if not native.native_available():
        pytest.skip("the native kernel is not built")
    rng = np.random.default_rng(3)
    X = rng.integers(0, 256, (500, 130)).astype(np.uint8)
    X[7] = 255
    X[8] = 0  # the largest difference in every dimension
    a = np.r_[7, rng.integers(0, 500, 5000)]
    b = np.r_[8, rng.integers(0, 500, 5000)]
    want = ((X[a].astype(np.int64) - X[b]) ** 2).sum(axis=1).astype(np.float64)
    np.testing.assert_array_equal(native.sq_distances_u8(X, a, b), want)
    np.testing.assert_array_equal(pairs.exact_sq_distances(X, a, b), want)
    assert native.sq_distances_u8(X.astype(np.int16), a, b) is None  # other dtypes: the numpy loop


@pytest.mark.parametrize("use_native", [True, False])
def test_sigma_of_integer_descriptors_from_tile_minima_matches_brute_force(levels, use_native):
    """On integer descriptors the per-image pass takes sigma from the tiles' exact float32 minima alone: against
    a brute-force oracle on small uint8 sets with duplicates within and across images, one-feature images
    (nan) and images that get no feature, at every SIMD level and in numpy."""
    if use_native and not native.native_available():
        pytest.skip("the native kernel is not built")
    rng = np.random.default_rng(11)
    for _ in range(40):
        n, dim, n_img = int(rng.integers(1, 90)), int(rng.integers(1, 20)), int(rng.integers(1, 8))
        X = rng.integers(0, int(rng.choice([2, 4, 256])), (n, dim)).astype(np.uint8)
        img = rng.integers(0, n_img, n)
        D = np.sqrt(((X[:, None, :].astype(np.int64) - X[None, :, :]) ** 2).sum(-1))
        D[(img[:, None] != img[None, :]) | np.eye(n, dtype=bool)] = np.inf
        ref = D.min(axis=1)
        ref[np.isinf(ref)] = np.nan
        for level in (levels if use_native else [None]):
            if level is not None:
                native.set_simd_level(level)
            got = pairs.nearest_same_image(pairs.Augmented(X), img, n_img, use_native=use_native)
            np.testing.assert_array_equal(got, ref)


@needs_vnni
def test_vnni_minima_are_the_minima_of_the_tile_without_making_it(monkeypatch):
    """U8Operands.minima (sigma's tiles on the integer kernel: strips of 64 rows reduced at once) gives the row
    and column minima of d2's tile, the self pairs left out on a diagonal tile (FLT_MAX where nothing is left);
    and sigma over images of several blocks (off-diagonal and ragged tiles) is the brute-force nearest other
    feature of the same image."""
    rng = np.random.default_rng(4)
    X = rng.integers(0, 256, size=(300, 130), dtype=np.uint8)
    X[7] = X[150]  # a duplicate: a zero distance off the diagonal
    ops = native.U8Operands(X)
    big = np.finfo(np.float32).max
    for a, a1, b, b1, diag in [(0, 300, 0, 300, True), (0, 300, 0, 300, False), (64, 130, 64, 130, True),
                               (5, 17, 32, 33, False), (288, 300, 256, 300, False), (0, 1, 0, 1, True)]:
        G = ops.d2(a, a1, b, b1)
        if diag:
            np.fill_diagonal(G, big)
        rmin, cmin = ops.minima(a, a1, b, b1, diag)
        np.testing.assert_array_equal(rmin, G.min(axis=1), err_msg=str((a, a1, b, b1)))
        np.testing.assert_array_equal(cmin, G.min(axis=0), err_msg=str((a, a1, b, b1)))
    monkeypatch.setattr(pairs, "BLOCK", 64)
    img = rng.integers(0, 3, len(X))
    D = np.sqrt(((X[:, None, :].astype(np.int64) - X[None, :, :]) ** 2).sum(-1))
    D[(img[:, None] != img[None, :]) | np.eye(len(X), dtype=bool)] = np.inf
    np.testing.assert_array_equal(pairs.nearest_same_image(pairs.Augmented(X), img, 3), D.min(axis=1))


@needs_native
def test_distinctiveness_tile_matches_numpy_with_slack_and_minima_only(levels):
    """nearest_sym natively at every SIMD level against its numpy twin: the minima, and with a slack every entry
    within it of its row's or column's minimum (a huge diagonal never reported); without one the minima only."""
    rng = np.random.default_rng(4)
    G = rng.uniform(10.0, 50.0, (300, 217)).astype(np.float32)
    G[np.arange(200), np.arange(5, 205)] = np.finfo(np.float32).max  # the self pairs of a diagonal tile
    sr, sc = rng.uniform(0.0, 3.0, 300).astype(np.float32), rng.uniform(0.0, 3.0, 217).astype(np.float32)
    ref = native.nearest_sym(G, sr, sc, use_native=False)
    assert len(ref[2]) > 300  # entries beside the minima are reported
    for level in levels:
        native.set_simd_level(level)
        got = native.nearest_sym(G, sr, sc)
        np.testing.assert_array_equal(got[0], ref[0])
        np.testing.assert_array_equal(got[1], ref[1])
        assert sorted(zip(got[2].tolist(), got[3].tolist(), got[4].tolist())) == \
            sorted(zip(ref[2].tolist(), ref[3].tolist(), ref[4].tolist()))
        only = native.nearest_sym(G, None, None)
        np.testing.assert_array_equal(only[0], ref[0])
        np.testing.assert_array_equal(only[1], ref[1])
        assert all(len(x) == 0 for x in only[2:])
    numpy_only = native.nearest_sym(G, None, None, use_native=False)
    np.testing.assert_array_equal(numpy_only[0], ref[0])
    assert all(len(x) == 0 for x in numpy_only[2:])


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_the_pair_rate_probe_measures_the_pass_it_names(levels, dtype):
    """pair_cpu_s_here (what --mode auto scales its cost model by): kernel_pass on one thread over other
    rows of the same shape takes about that much per pair-dimension, at the best SIMD level and in portable
    C (loose bounds: a timing on a shared machine, wall time against the probe's CPU time)."""
    import time

    X = np.random.default_rng(1).integers(0, 256, size=(3072, 128), dtype=np.uint8)
    X = X if dtype == np.uint8 else (X / np.float32(256)).astype(np.float32)
    n = len(X)
    args = (np.full(n, 1e-6, np.float32), np.ones(n, np.float32), "quadratic", np.zeros(n))
    for level in levels[:1] + levels[-1:]:
        native.set_simd_level(level)
        rate = pairs.pair_cpu_s_here(128, dtype)
        assert np.isfinite(rate) and rate > 0
        aug = pairs.Augmented(X)
        spent = []
        for _ in range(3):  # the first warms up
            t = time.perf_counter()
            pairs.kernel_pass(aug, *args, n_threads=1)
            spent.append(time.perf_counter() - t)
        per_pair_dim = min(spent[1:]) / (n * (n - 1) / 2 * 128)
        assert 0.33 < per_pair_dim / rate < 3.0, (level, per_pair_dim, rate)
    with pytest.raises(ValueError, match="uint8 or float32"):
        pairs.pair_cpu_s_here(128, np.int16)


def test_the_pair_rate_probe_says_what_failed_in_its_thread(monkeypatch):
    def broken(*args, **kwargs):
        raise MemoryError("no room for a tile")

    monkeypatch.setattr(pairs, "pass_tile", broken)
    with pytest.raises(MemoryError, match="no room for a tile"):
        pairs.pair_cpu_s_here(128, np.uint8)
