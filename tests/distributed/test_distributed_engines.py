"""The fast engine in distributed jobs (``DQMConfig(engine="fast")``, ``--engine fast``): gather, lean and paper
cluster with dqm.quickmatch's fast engine; balanced sends copies only where a pair is likely
(dqm.distributed.ghosts.likely_copies). Clusters are measured against the exact engine's, bytes against the
exact mode's."""
import numpy as np
import pytest

import dqm
from dqm import InputError, evaluation
from dqm.distributed import DQMConfig, boundary, forest, ghosts, simulate
from dqm.distributed.config import config_args, params_hash
from dqm.synthetic import sized


@pytest.fixture(scope="module")
def generated():
    ds = sized(12_000, features_per_image=1_000, seed=3)
    return ds.descriptors, ds.image_ids


@pytest.fixture(scope="module")
def central(generated):
    """Centralized QuickMatch (exact engine, the balanced mode's kernel) on the generated set, computed once."""
    return dqm.quickmatch(*generated, kernel="quadratic")


def test_engine_is_a_shared_parameter_checked_once():
    cfg = DQMConfig(agents=3, engine="fast").validated(100)
    assert "engine='fast'" in cfg.params_text()
    assert params_hash(cfg.params_text()) != params_hash(cfg.but(engine="exact").params_text())
    assert "--engine=fast" in config_args(cfg)
    assert cfg.fast and not cfg.sketches and DQMConfig(agents=3).sketches
    with pytest.raises(InputError, match="engine must be one of 'exact', 'fast', 'auto'; got 'quick'"):
        DQMConfig(agents=3, engine="quick").validated(100)


@pytest.mark.parametrize("m", [4, 8])
def test_fast_balanced_keeps_the_exact_clusters_with_fewer_copies(generated, central, m):
    X, ids = generated
    exact = simulate(X, ids, DQMConfig(agents=m, seed=1))
    fast = simulate(X, ids, DQMConfig(agents=m, seed=1, engine="fast"))
    np.testing.assert_array_equal(exact.labels, central.labels)
    f1 = evaluation.comembership_scores(fast.labels, central.labels).f1
    assert f1 >= 0.99, f1
    # fewer copies and bytes than the exact mode, within the budget; no sketches travel
    assert fast.stats["ghosts_per_feature"] <= ghosts.copy_budget(m) + 1e-9
    assert fast.stats["ghosts_per_feature"] < 0.6 * exact.stats["ghosts_per_feature"]
    assert fast.stats["bytes_over_raw"] < 0.7 * exact.stats["bytes_over_raw"]
    assert fast.traffic.total("sketch") == 0 and fast.traffic.total("request") == 0
    assert fast.stats["arrival_check_failures"] == 0
    assert all(agent["pairs_computed"] == agent["pairs"] for agent in fast.per_agent)  # cells too small for lists
    # every copy lies within the likely share of the reach that matters (the receiver's check agrees: no
    # failures above); the bound's rule would have sent far more
    H = boundary.bisector_lower_bounds(X.astype(np.float64), fast.sites, fast.cells, fast.weights)
    R = ghosts.reach(central.sigma, fast.config.rho)
    f, b = fast.copies[:, 0], fast.copies[:, 1]
    a = fast.cells[f]
    their = np.full((m, m), -np.inf)  # their[b, a]: the most a feature of cell b reaches past the bisector with a
    for cb in range(m):
        for ca in range(m):
            inside = fast.cells == cb
            if ca != cb and inside.any():
                their[cb, ca] = (R[inside] - H[inside, ca]).max()
    reach = np.maximum(R[f], their[b, a])
    assert (H[f, b] < ghosts.LIKELY_SHARE * reach * (1 + 1e-6) + 1e-9).all()
    assert len(f) < 0.6 * len(exact.copies)
    # deterministic
    again = simulate(X, ids, DQMConfig(agents=m, seed=1, engine="fast"))
    np.testing.assert_array_equal(again.labels, fast.labels)


def test_likely_copies_keep_the_nearest_within_the_budget():
    H = np.array([[0.1, 0.0, 0.05], [0.2, 0.0, 0.9], [0.01, 0.0, 0.02], [0.0, 0.0, 0.0]])
    R = np.array([1.0, 1.0, 1.0, 0.0])  # the last: an exact duplicate (reach 0)
    none = np.full(3, -np.inf)  # no feature of the receivers reaches past the bisector
    got = ghosts.likely_copies(H, R, [0, 2], budget=10.0, their_reach=none)
    assert got[0].tolist() == [0, 1, 2] and got[2].tolist() == [0, 2]  # the duplicate reaches nothing
    # budget 1 copy per feature: 4 features, 4 copies, the smallest H / R first (0.01, 0.02, 0.05, 0.1)
    got = ghosts.likely_copies(H, R, [0, 2], budget=1.0, their_reach=none)
    assert got[0].tolist() == [0, 2] and got[2].tolist() == [0, 2]
    # a receiver whose features reach 4 past the bisector: x travels within 0.3 * 4 of it (the duplicate too)
    far = np.array([4.0, -np.inf, -np.inf])
    got = ghosts.likely_copies(H + np.array([[1.0, 0, 0]]), R, [0, 2], budget=10.0, their_reach=far)
    assert got[0].tolist() == [0, 2, 3]  # 1.1, 1.01, 1.0 < 1.2; not 1.2
    assert ghosts.likely_mask(H[:, 0] + 1.0, R, 4.0).tolist() == [True, False, True, True]
    assert ghosts.likely_mask(H[:, 0], R, -np.inf).tolist() == [True, True, True, False]
    assert ghosts.copy_budget(8) > ghosts.copy_budget(4)


@pytest.mark.parametrize("mode", ["lean", "paper"])
def test_lean_and_paper_cluster_cells_with_the_fast_engine(generated, central, mode, monkeypatch):
    X, ids = generated
    engines = []
    real = dqm.distributed.cascade.quickmatch

    def spy(*args, **kwargs):
        engines.append(kwargs.get("engine"))
        return real(*args, **kwargs)

    monkeypatch.setattr(dqm.distributed.cascade, "quickmatch", spy)
    r = simulate(X, ids, DQMConfig(agents=3, seed=1, mode=mode, engine="fast"))
    assert engines and set(engines) == {"fast"}
    assert evaluation.comembership_scores(r.labels, central.labels).f1 > 0.9


def test_components_equal_scipys_on_random_forests():
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(0)
    for k, e in [(1, 0), (5, 0), (50, 30), (400, 390), (2000, 500)]:
        u, v = rng.integers(0, k, e), rng.integers(0, k, e)
        got = forest.components(k, u, v)
        _, ref = connected_components(coo_matrix((np.ones(e), (u, v)), shape=(k, k)), directed=False)
        # the same partition, each labelled by its lowest node
        lowest = np.full(k, k)
        np.minimum.at(lowest, ref, np.arange(k))
        np.testing.assert_array_equal(got, lowest[ref])
    chain = np.arange(999)
    assert (forest.components(1000, chain[::-1], chain[::-1] + 1) == 0).all()  # a long path, any order


def test_engine_auto_follows_the_features_in_all_as_dqm_match(generated, central, monkeypatch):
    X, ids = generated
    assert DQMConfig(agents=2, engine="auto").engine_for(49_999) == "exact"
    assert DQMConfig(agents=2, engine="auto").engine_for(50_000) == "fast"
    assert DQMConfig(agents=2, engine="fast").engine_for(10) == "fast"
    # below the threshold: the exact clusters; the coordinator's go named the engine, every agent ran it
    small = simulate(X, ids, DQMConfig(agents=4, seed=1, engine="auto"))
    assert small.config.engine == "exact"
    np.testing.assert_array_equal(small.labels, central.labels)
    # from the threshold (lowered here): the fast job, copy for copy
    monkeypatch.setattr(dqm.distributed.config, "FAST_FROM", len(X))
    picked = simulate(X, ids, DQMConfig(agents=4, seed=1, engine="auto"))
    fast = simulate(X, ids, DQMConfig(agents=4, seed=1, engine="fast"))
    assert picked.config.engine == "fast"
    np.testing.assert_array_equal(picked.labels, fast.labels)
    np.testing.assert_array_equal(picked.copies, fast.copies)
    assert picked.traffic.total("ghost") == fast.traffic.total("ghost") < small.traffic.total("ghost")


def test_fast_copies_survive_lost_duplicated_and_late_messages(generated):
    from dqm.distributed.network import Delay, Drop, Duplicate, FaultPlan

    X, ids = generated
    cfg = DQMConfig(agents=3, seed=1, engine="fast")
    clean = simulate(X, ids, cfg)
    plan = FaultPlan([Drop("ghost", src=1, nth=1), Drop("ack", src=2, dst=0, nth=1), Duplicate("grant", nth=2),
                      Delay("offer", src=0, nth=1)])
    r = simulate(X, ids, cfg, faults=plan)
    assert len(plan.struck) == 4
    np.testing.assert_array_equal(r.labels, clean.labels)
    assert r.stats["arrival_check_failures"] == 0 and r.traffic.counters()[2] >= 2  # resends


@pytest.mark.parametrize("recovery", ["takeover", "restart"])
def test_engine_auto_survives_a_lost_process(generated, monkeypatch, recovery):
    from dqm.distributed.network import FaultPlan, LoseProcess

    X, ids = generated
    monkeypatch.setattr(dqm.distributed.config, "FAST_FROM", len(X))  # auto picks fast
    cfg = DQMConfig(agents=3, seed=1, engine="auto")
    clean = simulate(X, ids, cfg)
    lost = simulate(X, ids, cfg, faults=FaultPlan([LoseProcess(1, "wait_ghost")]), recovery=recovery)
    assert lost.lost and clean.config.engine == lost.config.engine == "fast"
    np.testing.assert_array_equal(lost.labels, clean.labels)


def test_the_copy_budget_trades_bytes_for_the_exact_clusters(generated, central):
    X, ids = generated
    runs = {b: simulate(X, ids, DQMConfig(agents=8, seed=1, engine="fast", copy_budget=b)) for b in (0.3, 3.0)}
    few, many = runs[0.3], runs[3.0]
    assert few.stats["ghosts_per_feature"] <= 0.3 + 1e-9 < many.stats["ghosts_per_feature"]
    assert few.stats["bytes_over_raw"] < many.stats["bytes_over_raw"]
    f1 = {b: evaluation.comembership_scores(r.labels, central.labels).f1 for b, r in runs.items()}
    assert f1[0.3] < f1[3.0]
    assert DQMConfig(agents=8).copies_per_feature == ghosts.copy_budget(8)
    for bad in (-1.0, float("inf"), "2", True):
        with pytest.raises(InputError, match="copy_budget must be a number >= 0"):
            DQMConfig(agents=8, copy_budget=bad).validated(100)


def _met_pairs_by_rule(lists, aug, rad2, first, copy_bits=None):
    """The pairs the cell lists must hand over, by their definition: within ``rad2`` of either end (float32
    distances as the pass computes them) and met, one of the two scanning the other's list."""
    from dqm.core import inverted_lists

    n = aug.n
    G = aug.left_rows(np.arange(n)) @ aug.right.T
    i, j = np.nonzero(np.triu((G <= rad2[:, None]) | (G <= rad2[None, :]), 1))
    if copy_bits is None:  # own features among themselves
        li, lj = lists.own_list[i], lists.own_list[j]
        met = (li == lj) | inverted_lists._has_bit(lists.bits, i, lj) | inverted_lists._has_bit(lists.bits, j, li)
    else:  # own rows i < first, copies j >= first
        keep = (i < first) & (j >= first)
        i, j = i[keep], j[keep]
        bits, mine = copy_bits
        met = inverted_lists._has_bit(bits, j - first, lists.own_list[i]) | \
            inverted_lists._has_bit(lists.bits, i, mine[j - first])
    return set(zip(i[met].tolist(), j[met].tolist())), len(i)


def test_cell_lists_hand_over_every_met_pair_within_reach_once(generated, central):
    """The fast balanced mode's lists over a cell's own features (dqm.core.inverted_lists.CellLists): among the
    own features and between them and copies, every pair within reach that either feature's scan meets is
    handed over, once, lower index first, and nothing else; the lists scan a share of the pairs, so most (not
    all) pairs within reach are met."""
    from dqm.core import inverted_lists, pairs

    X, _ = generated
    own, copies = X[:4000], X[4000:6000]
    reach = ghosts.reach(central.sigma[:6000], 0.9)
    aug = pairs.Augmented(own)
    rad2 = pairs.search_rad2(aug, reach[:4000])
    lists = inverted_lists.CellLists(aug, seed=1)
    assert lists.t < lists.k  # a share of the lists, not all of them
    got = [(int(a), int(b)) for i, j in lists.own_pairs(aug, rad2) for a, b in zip(i, j)]
    want, within = _met_pairs_by_rule(lists, aug, rad2, 4000)
    assert len(got) == len(set(got)) and all(a < b for a, b in got)
    assert set(got) == want and 0.9 * within < len(want) < within
    held = pairs.Augmented(np.concatenate([own, copies]))
    rad2 = pairs.search_rad2(held, reach)
    got = [(int(a), int(b)) for i, j in lists.copy_pairs(held, rad2, 4000) for a, b in zip(i, j)]
    # the copies' scans, by the rule the class documents: their nearest lists, by the own features' quota
    centroids = (lists.centroids - held.center).astype(np.float32)
    near = inverted_lists._nearest_centroids(held.left_rows(np.arange(4000, 6000)), centroids, lists.t)
    count = inverted_lists._scanned_lists(lists.counts, near, lists.quota)
    bits = inverted_lists._scan_bits(near, np.arange(lists.t - 1)[None, :] < count[:, None], lists.k)
    want, within = _met_pairs_by_rule(lists, held, rad2, 4000, (bits, near[:, 0].astype(np.int64)))
    assert len(got) == len(set(got)) and all(a < 4000 <= b for a, b in got)
    assert set(got) == want and 0.9 * within < len(want) < within


def test_fast_balanced_cells_scan_lists_where_they_pay(generated, central, monkeypatch):
    """Cells of enough features (dqm.core.inverted_lists.lists_pay: from about 10,000 own features) meet only
    the pairs their lists' scans meet, not every pair: here forced on small cells, the clusters stay the exact
    engine's nearly everywhere, deterministically, with fewer parent candidates than the exact cell pass."""
    from dqm.core import inverted_lists

    X, ids = generated
    assert not inverted_lists.lists_pay(7_000) and inverted_lists.lists_pay(12_500) and inverted_lists.lists_pay(25_000)
    monkeypatch.setattr(inverted_lists, "lists_pay", lambda n: True)
    lists = simulate(X, ids, DQMConfig(agents=2, seed=1, engine="fast"))
    assert evaluation.comembership_scores(lists.labels, central.labels).f1 >= 0.99
    for agent in lists.per_agent:  # a share of the cell's pairs (without lists: all of them, the test above)
        assert 0 < agent["pairs_computed"] < 0.8 * agent["pairs"]
    again = simulate(X, ids, DQMConfig(agents=2, seed=1, engine="fast"))
    np.testing.assert_array_equal(again.labels, lists.labels)


def test_cell_lists_benchmark_script_small(capsys):
    """scripts/bench_cell_lists.py (the fast balanced cells with and without lists, side by side) at its CI size."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "scripts" / "bench_cell_lists.py"
    spec = importlib.util.spec_from_file_location("bench_cell_lists", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    from dqm.core import inverted_lists

    real = inverted_lists.lists_pay
    assert script.main(["--n", "6000", "--agents", "2", "--force"]) == 0
    assert inverted_lists.lists_pay is real  # given back
    out = capsys.readouterr().out.splitlines()
    rows = [ln.split("|")[1:-1] for ln in out if ln.startswith("| ") and "---" not in ln]
    assert [r[0].strip() for r in rows[1:]] == ["lists (forced)", "exact cell pass"]
    for r in rows[1:]:
        assert float(r[-1]) >= 0.99 and float(r[-2]) > 0
