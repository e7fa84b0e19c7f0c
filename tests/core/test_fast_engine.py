"""The fast engine (inverted lists, issue 37): close to exact, deterministic, chosen by size."""
import subprocess
import sys

import numpy as np
import pytest
from conftest import assert_consistent

import dqm
from dqm import io as dqm_io
from dqm.core import inverted_lists
from dqm.core.clustering import FAST_FROM
from dqm.evaluation import comembership_scores
from dqm.synthetic import sift_like


@pytest.fixture(scope="module")
def scene():
    ds = sift_like(n_images=12, n_points=500, clutter_per_image=300, seed=7)
    return ds.descriptors, ds.image_ids, dqm.quickmatch(ds.descriptors, ds.image_ids)


def test_the_fast_engine_agrees_with_exact_and_loses_with_fewer_probes(scene):
    X, ids, exact = scene
    fast = dqm.quickmatch(X, ids, engine="fast")
    assert_consistent(fast.labels, ids)
    assert fast.stats["engine_fast"] == 1.0
    assert fast.stats["pairs_computed"] < 0.5 * len(X) ** 2  # it did not visit every pair
    assert comembership_scores(fast.labels, exact.labels).f1 >= 0.995
    np.testing.assert_array_equal(fast.sigma, exact.sigma)  # sigma is the exact engine's
    # each pair's terms are counted once however many tiles meet it: never more than the exact density
    assert (fast.density <= exact.density * (1 + 1e-6)).all()
    assert (fast.density < exact.density * (1 - 1e-9)).any()  # and some far terms are left out
    # a feature's own list only: far fewer pairs, and clusters whose members fall in other lists are lost
    poor = dqm.quickmatch(X, ids, engine="fast", n_probe=1)
    assert poor.stats["pairs_computed"] < fast.stats["pairs_computed"]
    assert comembership_scores(poor.labels, exact.labels).f1 < comembership_scores(fast.labels, exact.labels).f1
    # every list probed: every pair is met, so the densities and parents are the exact ones; and every two lists
    # are met whole, each pair of two lists once (the pairs within a list in both orders): n^2 / 2 and a little
    full = dqm.quickmatch(X, ids, engine="fast", n_probe=inverted_lists.n_lists(len(X)))
    assert len(X) ** 2 / 2 < full.stats["pairs_computed"] < 0.6 * len(X) ** 2
    np.testing.assert_allclose(full.density, exact.density, rtol=1e-6)
    assert comembership_scores(full.labels, exact.labels).f1 == 1.0


def test_the_fast_engine_is_deterministic_and_the_seed_is_its_own(scene):
    X, ids, _ = scene
    a = dqm.quickmatch(X, ids, engine="fast", n_threads=1)
    b = dqm.quickmatch(X, ids, engine="fast", n_threads=2)
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.density, b.density)  # sums in list order whatever the threads
    c = dqm.quickmatch(X, ids, engine="fast", seed=1)
    assert not np.array_equal(c.density, a.density)  # another sample, other lists


def test_the_integer_kernels_scan_gives_the_float_scans_result(scene):
    """On uint8 descriptors the scan takes its distances from the integer (VNNI) kernel where the CPU has it,
    else from a float32 GEMM: both exact integers, so the densities and clusters are the same bits."""
    from dqm.core import native

    if native.simd_level() < 3:
        pytest.skip("no AVX-512 VNNI on this CPU: the scan's integer path does not run here")
    X, ids, _ = scene
    vnni = dqm.quickmatch(X, ids, engine="fast")
    try:
        native.set_simd_level(2)
        gemm = dqm.quickmatch(X, ids, engine="fast")
    finally:
        native.set_simd_level(99)
    np.testing.assert_array_equal(vnni.labels, gemm.labels)
    np.testing.assert_array_equal(vnni.density, gemm.density)
    np.testing.assert_array_equal(vnni.parent, gemm.parent)


@pytest.mark.parametrize("setup_rows", [None, 7])
def test_scanned_lists_are_those_reached_before_the_quota(monkeypatch, setup_rows):
    """Each feature scans its other nearest lists while it has met fewer features than the quota (its own
    list's included): the definition by cumulative sums, on uneven lists; the same a few features at a time."""
    if setup_rows is not None:
        monkeypatch.setattr(inverted_lists, "SETUP_ROWS", setup_rows)
    rng = np.random.default_rng(3)
    k, t, n = 40, 9, 500
    counts = rng.integers(0, 60, k).astype(np.int32)
    near = np.stack([rng.permutation(k)[:t] for _ in range(n)]).astype(np.int32)
    for quota in (0.0, 30.0, 150.0, 1e9):
        sizes = counts[near[:, 1:]].astype(np.int64)
        before = np.cumsum(sizes, axis=1) - sizes + counts[near[:, 0]][:, None]
        expected = (before < quota).sum(axis=1)
        got = inverted_lists._scanned_lists(counts, near, quota)
        np.testing.assert_array_equal(got, expected)
        assert ((before < quota) == (np.arange(t - 1)[None, :] < got[:, None])).all()  # a prefix of the lists


def _random_scans(seed: int, k: int, t: int, n: int):
    """``n`` features' ``t`` nearest of ``k`` lists (distinct, in a random order) and which of the others each
    scans (half of them), with the generator for more."""
    rng = np.random.default_rng(seed)
    near = np.stack([rng.permutation(k)[:t] for _ in range(n)]).astype(np.int32)
    return near, rng.random((n, t - 1)) < 0.5, rng


@pytest.mark.parametrize("setup_rows", [None, 7])
def test_scan_bits_hold_each_features_scanned_lists(monkeypatch, setup_rows):
    """The bitset of a feature has bit l set exactly where it scans list l (its own, and its other nearest lists
    where ``scans`` says so), over more than one 64-bit word; the same a few features at a time."""
    if setup_rows is not None:
        monkeypatch.setattr(inverted_lists, "SETUP_ROWS", setup_rows)
    k, t, n = 150, 7, 60
    near, scans, _ = _random_scans(8, k, t, n)
    bits = inverted_lists._scan_bits(near, scans, k)
    assert bits.shape == (n, 3) and bits.dtype == np.uint64
    for i in range(n):
        scanned = {int(near[i, 0])} | {int(b) for b in near[i, 1:][scans[i]]}
        held = {w * 64 + b for w in range(3) for b in range(64) if (int(bits[i, w]) >> b) & 1}
        assert held == scanned, i


@pytest.mark.parametrize("entries", [None, 7])
def test_lists_met_whole_meet_every_pair_they_met_once_and_fewer_pairs(monkeypatch, entries):
    """Two lists whose members scan each other's so much that meeting them whole costs fewer pairs: every member
    of the lower list scans the higher and none of the higher's the lower. Every pair of features met before is
    met after, no pair of two lists is met from both sides, the bitsets say what is scanned, and the pairs computed
    fall; where no two lists qualify nothing changes. Also made a few scans at a time (``entries``: chunks of one
    feature, and of fewer list members than a list holds)."""
    if entries is not None:
        monkeypatch.setattr(inverted_lists, "ENTRIES", entries)
        monkeypatch.setattr(inverted_lists, "SETUP_ROWS", 9)  # the bitsets a few features at a time too
    rng = np.random.default_rng(5)
    k, t, n = 12, 6, 400
    own = rng.integers(0, k, n).astype(np.int32)
    own[:k] = np.arange(k)  # no list empty
    first = {3: [4], 4: [3]}  # lists 3 and 4 are each other's nearest: they qualify

    def nearest(o):
        ahead = first.get(int(o), [])
        return np.r_[o, ahead, rng.permutation(np.setdiff1d(np.arange(k), [o, *ahead]))[:t - 1 - len(ahead)]]

    near = np.stack([nearest(o) for o in own]).astype(np.int32)
    scans = rng.random((n, t - 1)) < 0.4
    scans[:, 0] = True
    scans[np.flatnonzero(own == 3)[::2], 0] = False  # half of list 3 scans list 4, all of list 4 scans list 3
    by_list = np.argsort(own, kind="stable")
    bounds = np.r_[0, np.cumsum(np.bincount(own, minlength=k))]
    counts = np.diff(bounds).astype(np.int32)

    def met(scans, extra_row, extra_list):
        """Every pair of features of two lists that is met (a set of frozensets), the pairs computed, and how
        often each is met."""
        rows = np.r_[np.repeat(np.arange(n), scans.sum(axis=1)), extra_row]
        lists = np.r_[near[:, 1:][scans], extra_list]
        seen, times = set(), {}
        for i, b in zip(rows.tolist(), lists.tolist()):
            for j in np.flatnonzero(own == b).tolist():
                key = frozenset((i, j))
                times[key] = times.get(key, 0) + 1
                seen.add(key)
        return seen, sum(times.values()), times

    kept, bits, extra_row, extra_list = inverted_lists._lists_met_whole(own, near, scans, counts, by_list, bounds, k)
    assert len(extra_row) and (kept != scans).any()
    before, computed_before, _ = met(scans, np.zeros(0, int), np.zeros(0, int))
    after, computed_after, times = met(kept, extra_row, extra_list)
    assert before <= after and computed_after < computed_before
    across = [v for key, v in times.items() if {int(own[i]) for i in key} == {3, 4}]
    assert len(across) == counts[3] * counts[4] and set(across) == {1}  # lists 3 and 4: every pair, each once
    added = set(extra_row[extra_list == 4].tolist())
    assert added == set(np.flatnonzero(own == 3)[::2].tolist())  # the half of list 3 that did not scan list 4
    assert not any((near[j, 1:][kept[j]] == 3).any() for j in np.flatnonzero(own == 4))
    expected = inverted_lists._scan_bits(near, kept, k)
    inverted_lists._set_bits(expected, extra_row, extra_list)
    np.testing.assert_array_equal(bits, expected)
    # far lists that scan each other little: nothing qualifies, nothing changes
    lone = np.zeros_like(scans)
    same = inverted_lists._lists_met_whole(own, near, lone, counts, by_list, bounds, k)
    assert (same[0] == lone).all() and not len(same[2])



@pytest.mark.parametrize("entries", [None, 5])
def test_each_lists_probers_are_a_stable_sort_of_the_scans_by_list(monkeypatch, entries):
    """The features that scan each list, as the scan's positions, list by list: the scans in feature order, then
    the added ones in their order, as a stable sort of all of them by list would give; the same made a few scans
    at a time (``entries``)."""
    if entries is not None:
        monkeypatch.setattr(inverted_lists, "ENTRIES", entries)
    k, t, n = 9, 5, 300
    near, scans, rng = _random_scans(11, k, t, n)
    extra_row = rng.integers(0, n, 40).astype(np.int32)
    extra_list = rng.integers(0, k, 40).astype(np.int32)
    where = rng.permutation(n).astype(np.int32)
    probers, pbounds = inverted_lists._probers(near, scans, extra_row, extra_list, k, where)
    lists = np.r_[near[:, 1:][scans], extra_list]
    rows = np.r_[np.repeat(np.arange(n), scans.sum(axis=1)), extra_row]
    order = np.argsort(lists, kind="stable")
    np.testing.assert_array_equal(probers, where[rows[order]])
    np.testing.assert_array_equal(pbounds, np.r_[0, np.cumsum(np.bincount(lists, minlength=k))])
    assert probers.dtype == np.int32


def test_auto_runs_exact_below_its_size_and_engines_are_checked(scene):
    X, ids, exact = scene
    assert len(X) < FAST_FROM
    auto = dqm.quickmatch(X, ids, engine="auto")
    assert "engine_fast" not in auto.stats
    np.testing.assert_array_equal(auto.labels, exact.labels)
    with pytest.raises(dqm.InputError, match="engine must be one of exact, fast, auto, got 'quick'"):
        dqm.quickmatch(X, ids, engine="quick")
    with pytest.raises(dqm.InputError, match="n_probe must be a positive integer"):
        dqm.quickmatch(X, ids, engine="fast", n_probe=0)
    from dqm.core import memory

    exact_need = memory.base_bytes(len(X), X.shape[1], 2, X.dtype.itemsize)
    with pytest.raises(memory.MemoryBudgetError, match="the fast engine with 32 probes needs about"):
        dqm.quickmatch(X, ids, engine="fast", max_memory=exact_need + (1 << 20), n_threads=2)


def test_lists_are_powers_of_two_near_the_root_and_a_sixteenth_is_probed():
    assert inverted_lists.n_lists(90_000) == 512
    assert inverted_lists.n_lists(668_000) == 1024
    assert inverted_lists.n_lists(2_000_000) == 2048
    assert inverted_lists.n_lists(10) == 1
    assert [inverted_lists.default_probes(k) for k in (8, 64, 512, 1024, 2048)] == [8, 32, 32, 64, 128]


def test_cli_match_engines(tmp_path, scene):
    X, ids, exact = scene
    src = tmp_path / "f.npz"
    dqm_io.save_features(src, dqm_io.FeatureSet(X, ids))
    runs = {}
    for name, flags in (("fast", ["--engine", "fast"]), ("exact", ["--exact"])):
        out = tmp_path / f"{name}.npz"
        p = subprocess.run([sys.executable, "-m", "dqm", "match", str(src), "--out", str(out), "--quiet"] + flags,
                           capture_output=True, text=True)
        assert p.returncode == 0, p.stderr
        runs[name] = (p.stdout, dqm_io.load_clusters(out))
    assert "fast engine" in runs["fast"][0] and runs["fast"][1]["params"]["engine"] == "fast"
    assert runs["exact"][1]["params"]["engine"] == "exact"
    np.testing.assert_array_equal(runs["exact"][1]["labels"], exact.labels)
    p = subprocess.run([sys.executable, "-m", "dqm", "match", str(src), "--out", str(tmp_path / "x.npz"),
                        "--engine", "fast", "--approximate"], capture_output=True, text=True)
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert "--approximate and --engine fast are two different engines" in p.stderr
    p = subprocess.run([sys.executable, "-m", "dqm", "match", "--help"], capture_output=True, text=True)
    assert f"exact below {FAST_FROM:,} features" in " ".join(p.stdout.split())


def test_benchmark_script_small_fast_run():
    """The small version of scripts/bench_quickmatch.py --fast (the full one: docs/quickmatch.md's sets)."""
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "scripts" / "bench_quickmatch.py"
    p = subprocess.run([sys.executable, str(script), "--fast", "6000", "--sizes", "", "--no-graf"],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    lines = p.stdout.splitlines()
    (header,) = [line for line in lines if line.startswith("| data |")]
    (row,) = [line for line in lines if line.startswith("| 6000 |")]
    cell = dict(zip([c.strip() for c in header.split("|")[1:-1]], [c.strip() for c in row.split("|")[1:-1]]))
    assert cell["images"] == "3"
    assert 0 < float(cell["pairs computed (of n^2)"]) < 1.0
    assert float(cell["F1"]) >= 0.99  # against exact
    assert 0 < float(cell["fast / exact"]) < 10


@pytest.mark.parametrize("use_native", [True, False])
@pytest.mark.parametrize("with_image", [False, True])
def test_candidate_keeper_holds_each_childs_nearest_whatever_the_order(use_native, with_image):
    """The keeper of the scan's candidates (native and numpy): each child's k nearest by (g, candidate), edges
    given as tiles write them (row or column the child), ties in g, parts in two orders, the same result; the
    limit it hands the scan is just above the k-th g."""
    from dqm.core import native

    if use_native and not native.native_available():
        pytest.skip("the native kernel is not built")
    n, k, m = 60, 3, 6000
    rng = np.random.default_rng(1)
    rows = rng.permutation(n).astype(np.int64)[:40]
    r = rng.integers(0, len(rows), m).astype(np.int32)
    c = rng.integers(0, n, m).astype(np.int32)
    rev = rng.random(m) < 0.5
    r[rev] = -1 - r[rev]
    g = rng.integers(0, 50, m).astype(np.float32)  # many ties
    image = rng.integers(0, 4, n).astype(np.int32) if with_image else None
    at = rows[np.where(rev, -1 - r.astype(np.int64), r)]
    child, cand = np.where(rev, c, at), np.where(rev, at, c)
    results = []
    for order in (np.arange(m), rng.permutation(m)):
        held = inverted_lists.NearestCandidates(n, k, image)
        for s in range(0, m, 700):
            part = order[s:s + 700]
            native.keep_nearest(r[part], c[part], g[part], rows, held.image, held.g, held.cand, held.count,
                                held.limit, use_native=use_native)
        results.append(held)
    for j in range(n):
        mine = np.flatnonzero((child == j) & ((image[child] != image[cand]) if with_image else True))
        best = mine[np.lexsort((cand[mine], g[mine]))[:k]]
        for held in results:
            assert held.count[j] == len(best)
            assert held.cand[j, :len(best)].tolist() == cand[best].tolist()
            assert held.limit[j] == (np.nextafter(g[best[-1]], np.float32(np.inf)) if len(best) == k else np.inf)
    cr, cc = results[0].nearest()
    assert np.array_equal(np.bincount(cr, minlength=n), results[0].count)


@pytest.mark.parametrize("use_native", [True, False])
def test_each_features_nearest_lists_by_distance_then_index(use_native):
    """The nearest lists of every feature (native and numpy): the t smallest of each row by (value, index),
    with ties, NaN as +inf, t = 1 and t = every column."""
    from dqm.core import native

    if use_native and not native.native_available():
        pytest.skip("the native kernel is not built")
    rng = np.random.default_rng(2)
    D = rng.integers(0, 40, (300, 97)).astype(np.float32)  # many ties
    D[5, 3] = D[7, :] = np.nan
    D[9, :] = np.inf
    ref = np.lexsort((np.broadcast_to(np.arange(97), D.shape), np.where(np.isnan(D), np.inf, D)), axis=1)
    for t in (1, 2, 32, 97):
        got = native.smallest(D, t, use_native=use_native)
        assert got.dtype == np.int32 and got.shape == (300, t)
        np.testing.assert_array_equal(got, ref[:, :t])
    with pytest.raises(ValueError, match="t = 0"):
        native.smallest(D, 0, use_native=use_native)
    # 512 columns: t chunks of a multiple of 8 columns, where the native pass bounds the t-th smallest with
    # vector minima (SIMD level >= 1) or scalar ones (level 0); rows of NaN, of +inf, one chunk all NaN
    W = rng.integers(0, 60, (200, 512)).astype(np.float32)
    W[3, :] = np.nan
    W[4, :] = np.inf
    W[6, 16:32] = np.nan
    W[8, ::3] = np.nan
    W[10] -= 30  # negative distances (float error of a GEMM) and -0 tied with +0: ordered as numbers, then index
    W[11, :40] = np.where(np.arange(40) % 2, np.float32(0.0), np.float32(-0.0))
    ref = np.lexsort((np.broadcast_to(np.arange(512), W.shape), np.where(np.isnan(W), np.inf, W)), axis=1)
    levels = [native.set_simd_level(99), 0] if use_native else [None]
    try:
        for level in levels:
            if level is not None:
                native.set_simd_level(level)
            for t in (8, 32, 64):
                np.testing.assert_array_equal(native.smallest(W, t, use_native=use_native), ref[:, :t])
    finally:
        if use_native:
            native.set_simd_level(99)


def test_same_image_pairs_do_not_take_a_childs_candidate_places(scene):
    """parent='other-image': pairs within one image are dropped before each child's nearest are kept, so a
    tight cap still holds the nearest candidate from another image."""
    from dqm.core import clustering, pairs

    X, ids, exact = scene
    _, img = np.unique(ids, return_inverse=True)
    aug = pairs.Augmented(X)
    w, active = clustering.kernel_weights(exact.sigma, "gaussian", 0.25)
    radius = 1.1 * exact.sigma  # wide: many children have candidates in their own image too
    _, cr, cc, *_ = inverted_lists.scan(aug, w, active, "gaussian", radius, max_candidates=1500)
    assert np.bincount(cr).max() < 1500  # no child capped: every candidate of the scan
    other = img[cr] != img[cc]
    assert (~other).any()  # same-image candidates exist and would compete for the places
    cr, cc = cr[other], cc[other]
    order = np.lexsort((cc, pairs.exact_distances(aug.exact, cr, cc), cr))  # each child's nearest first
    cr, cc = cr[order], cc[order]
    first = np.r_[True, cr[1:] != cr[:-1]]
    best = dict(zip(cr[first].tolist(), cc[first].tolist()))
    _, kr, kc, *_ = inverted_lists.scan(aug, w, active, "gaussian", radius, max_candidates=1, image_index=img)
    assert (img[kr] != img[kc]).all()
    assert dict(zip(kr.tolist(), kc.tolist())) == best


def test_the_lists_k_means_beside_sigma_gives_the_same_centroids_and_stops_when_left(scene):
    """The fast engine runs the lists' k-means on its own thread while sigma's pass runs: the centroids are
    kmeans()'s; a block left early (an error, Ctrl-C) stops it at its next iteration and raises the
    block's own error."""
    import threading

    from dqm.core import pairs

    X, _, _ = scene
    aug = pairs.Augmented(X)
    with inverted_lists.centroids_meanwhile(aug.left, 64, 3) as centroids:
        got = centroids()
    np.testing.assert_array_equal(got, inverted_lists.kmeans(aug.left, 64, 3))
    with pytest.raises(KeyError, match="the caller's"):
        with inverted_lists.centroids_meanwhile(aug.left, 64, 3):
            raise KeyError("the caller's")
    stop = threading.Event()
    stop.set()
    with pytest.raises(inverted_lists.Stopped):
        inverted_lists.kmeans(aug.left, 64, 3, stop=stop)
    with pytest.raises(ValueError, match="centroids for"):
        inverted_lists.scan(aug, np.ones(len(X)), np.ones(len(X)), "gaussian", np.ones(len(X)), lists=32,
                            centroids=got)


def test_the_fast_engine_makes_the_left_operand_a_block_at_a_time(scene):
    """On integer descriptors the k-means and the nearest lists take the float32 left operand's rows block by
    block (Augmented.left_rows: the same values as the whole operand's rows) and the scan on the integer kernel
    never makes the whole operand (n x (dim + 2) float32); the centroids and lists are those of the whole
    operand. Float descriptors keep their operand made up front."""
    from dqm.core import pairs

    X, ids, _ = scene
    aug = pairs.Augmented(X)
    assert aug.exact_d2 and aug._operands[0] is None  # integer rows: the operand is made on first use
    whole = pairs.Augmented(X).left
    rows = np.array([5, 0, len(X) - 1, 5])
    np.testing.assert_array_equal(aug.left_rows(rows), whole[rows])
    np.testing.assert_array_equal(aug.left_rows(slice(7, 4103)), whole[7:4103])
    centroids = inverted_lists.kmeans(aug, 64, 3)
    np.testing.assert_array_equal(centroids, inverted_lists.kmeans(whole, 64, 3))
    np.testing.assert_array_equal(inverted_lists._nearest_centroids(aug, centroids, 4, 2),
                                  inverted_lists._nearest_centroids(whole, centroids, 4, 2))
    assert aug._operands[0] is None
    exact = dqm.quickmatch(X, ids)
    w, active = dqm.core.clustering.kernel_weights(exact.sigma, "gaussian", 0.25)
    _, cr, cc, *_ = inverted_lists.scan(aug, w, active, "gaussian", 0.9 * exact.sigma, lists=64,
                                       centroids=centroids)
    assert len(cr) and (aug._operands[0] is None) == aug.integer_kernel  # the GEMM path takes whole rows
    Xf = X.astype(np.float32) / 7
    f = pairs.Augmented(Xf)
    assert f._operands[0] is not None
    np.testing.assert_array_equal(f.left_rows(rows), f.left[rows])


@pytest.mark.parametrize("parent", ["other-image", "any"])
def test_children_cut_at_the_candidate_cap_still_get_their_parent(scene, monkeypatch, parent):
    """The scan keeps each child's MAX_CANDIDATES nearest candidates before the densities exist. A child whose
    kept candidates all rank below it (the densest members of a point seen in many images) is searched again
    once the densities are known (inverted_lists.nearest_above): with every list probed, a cap of 2 gives the
    exact engine's parents and clusters; without that search, such children become roots and clusters split
    (1M generated features over 500 images: F1 0.916 against exact, issue 59)."""
    X, ids, _ = scene
    exact = dqm.quickmatch(X, ids, parent=parent)
    every = inverted_lists.n_lists(len(X))
    monkeypatch.setattr(inverted_lists, "MAX_CANDIDATES", 2)
    capped = dqm.quickmatch(X, ids, engine="fast", n_probe=every, parent=parent)
    assert capped.stats["n_parents_searched"] > 50
    np.testing.assert_array_equal(capped.parent, exact.parent)
    np.testing.assert_array_equal(capped.labels, exact.labels)
    monkeypatch.setattr(inverted_lists, "nearest_above", lambda aug, index, rows, *a, **k: (rows[:0], rows[:0]))
    unsearched = dqm.quickmatch(X, ids, engine="fast", n_probe=every, parent=parent)
    assert (unsearched.parent < 0).sum() > (exact.parent < 0).sum() + 50
    assert comembership_scores(unsearched.labels, exact.labels).recall < 0.99


@pytest.mark.parametrize("columns, simd", [(None, 99), (1, 99), (700, 99), (700, 2)])
def test_nearest_above_is_the_nearest_higher_ranked_member_of_the_scanned_lists(scene, monkeypatch, columns, simd):
    """nearest_above against brute force: for each row, among the members of the lists the scan's rule gives
    it, the features that rank above it, lie within its radius and (with image_index) come from another image;
    the nearest of them (exact distances on uint8: no ties within a bound). Whatever lists a task gathers (one
    each; several, with lists no row scans between them, whose members are gathered too and left out; the
    default), on the integer kernel where the CPU has it and on the float32 GEMM (SIMD level 2)."""
    from dqm.core import native, pairs

    if simd < 99 and native.simd_level() < 3:
        pytest.skip("no AVX-512 VNNI on this CPU: the float32 path is the default case here")
    if columns is not None:
        monkeypatch.setattr(inverted_lists, "NEAREST_ABOVE_COLUMNS", columns)
    X, ids, exact = scene
    _, img = np.unique(ids, return_inverse=True)
    native.set_simd_level(simd)
    try:
        aug = pairs.Augmented(X)
        assert aug.integer_kernel == (native.simd_level() == 3)
        _check_nearest_above(aug, img, exact)
    finally:
        native.set_simd_level(99)


def _check_nearest_above(aug, img, exact):
    from dqm.core import pairs, tree

    w, active = dqm.core.clustering.kernel_weights(exact.sigma, "gaussian", 0.25)
    radius = 0.9 * exact.sigma
    found = inverted_lists.scan(aug, w, active, "gaussian", radius, lists=64, n_probe=6, max_candidates=3)
    capped = np.flatnonzero(found.capped)
    assert len(capped) > 300
    # many rows (every list scanned), and four (lists between the scanned ones that none of them scans)
    for rows, image_index in ((capped[::3], None), (capped[::3], img), (capped[:4], img)):
        child, cand = inverted_lists.nearest_above(aug, found.index, rows, exact.density, radius, image_index, 2)
        got = dict(zip(child.tolist(), cand.tolist()))
        assert len(got) == len(child)  # exact distances: one nearest each
        near, count = found.index.scanned(aug.left_rows(rows))
        for i, r in enumerate(rows):
            lists = near[i, :1 + count[i]]
            members = np.concatenate([found.index.members[found.index.bounds[b]:found.index.bounds[b + 1]]
                                      for b in lists])
            d = pairs.exact_distances(aug.exact, np.full(len(members), r), members)
            ok = tree.ranks_above(exact.density, members, np.full(len(members), r)) & (d < radius[r])
            if image_index is not None:
                ok &= img[members] != img[r]
            if not ok.any():
                assert r not in got
                continue
            best = members[ok][np.argmin(d[ok])]
            assert got[r] == best
