"""Online QuickMatch's parts on their own: parameters, dtype, the stores, identity reconciliation."""
import numpy as np
import pytest

import dqm
from dqm.core import clustering, online_update
from dqm.core.events import replay
from dqm.core.online import OnlineQuickMatch
from dqm.core.online_identity import reconcile
from dqm.core.online_store import DuplicateGroups, FeatureStore, NeighbourStore
from dqm.core.params import FINITE_KERNEL, QuickMatchParams


def test_parameters_are_one_quickmatch_params():
    om = OnlineQuickMatch(rho=0.8, parent="other-image", n_threads=2)
    assert om.params == QuickMatchParams(rho=0.8, kernel=FINITE_KERNEL, parent="other-image")
    assert (om.rho, om.kernel, om.parent_mode) == (0.8, "quadratic", "other-image")
    assert om.get_params() == {**om.params.as_kwargs(), "n_threads": 2}
    assert OnlineQuickMatch().kernel == FINITE_KERNEL
    # the shared vocabulary: a params object's keyword arguments build the same engine
    again = OnlineQuickMatch(**om.params.as_kwargs())
    assert again.params == om.params
    with pytest.raises(dqm.InputError, match="online QuickMatch needs the finite kernel"):
        OnlineQuickMatch(**QuickMatchParams().as_kwargs())  # the batch default, Gaussian
    with pytest.raises(dqm.InputError, match="parent"):
        OnlineQuickMatch(parent="nearest")
    with pytest.raises(dqm.InputError, match="ratio_density"):
        OnlineQuickMatch(ratio_density=0)


def test_integer_descriptors_keep_their_dtype_and_match_batch():
    rng = np.random.default_rng(0)
    X = rng.integers(0, 40, size=(120, 16)).astype(np.uint8)
    ids = np.repeat(np.arange(12), 10)
    ids[:2] = [50, 51]  # single-feature images
    for dtype in (np.uint8, np.int16, np.float64):
        om = OnlineQuickMatch(rho=1.2)
        for img in np.unique(ids):
            om.add(X[ids == img].astype(dtype), ids[ids == img])
        assert om.descriptors.dtype == np.uint8  # every value an integer in 0..255: the compact copy
        ref = dqm.quickmatch(om.descriptors, om.image_ids, rho=1.2, kernel="quadratic")
        assert np.array_equal(om.labels, ref.labels)
    before = om.descriptors
    om.add(X[:3].astype(np.float64) + 0.5, np.full(3, 99))
    assert om.descriptors.dtype == np.float64  # a float arrived: widened, values kept
    assert np.array_equal(om.descriptors[:-3], before)
    assert np.array_equal(om.labels, dqm.quickmatch(om.descriptors, om.image_ids, rho=1.2, kernel="quadratic").labels)


def test_lonely_sigma_is_the_batch_rule():
    assert online_update.lonely_sigma is clustering.lonely_sigma
    rng = np.random.default_rng(1)
    X = rng.normal(size=(30, 8))
    ids = np.r_[np.repeat(np.arange(5), 5), np.arange(10, 15)]  # five single-feature images
    om = OnlineQuickMatch(rho=1.0)
    om.add(X, ids)
    sig = om.result().sigma
    assert np.all(sig[25:] == clustering.lonely_sigma(sig[:25]))


def test_neighbour_store_merges_runs_and_drops_dead_pairs():
    alive = np.ones(6, bool)
    st = NeighbourStore()
    st.add(np.array([0, 2]), np.array([1, 3]), np.array([1.0, 4.0]), alive)
    st.add(np.array([2, 4]), np.array([5, 0]), np.array([9.0, 16.0]), alive)
    assert len(st.runs) == 1 and len(st) == 4  # equal-size runs merge
    a, b, d = st.query(np.array([2]), alive)
    assert sorted(zip(a.tolist(), b.tolist(), d.tolist())) == [(2, 3, 4.0), (2, 5, 9.0)]
    alive[5] = False
    a, b, d = st.query(np.array([2]), alive)
    assert b.tolist() == [3]
    st.remap(np.array([0, 1, 2, -1, 3, -1]))
    assert sorted(zip(*[x.tolist() for x in st.query(np.arange(4), np.ones(4, bool))])) == [
        (0, 1, 1.0), (3, 0, 16.0)]


def test_duplicate_groups_flag_and_unflag():
    s = FeatureStore(2, np.float64)
    slots = s.grow(3)
    g = DuplicateGroups()
    g.add(s, slots, np.array([[0.0, 1.0], [-0.0, 1.0], [2.0, 2.0]]))  # -0.0 equals 0.0
    assert s.dup[:3].tolist() == [True, True, False]
    assert g.shared_key(0) is not None and g.shared_key(2) is None
    key = g.discard(s, 1)
    assert key is not None and g.members(key) == [0] and not s.dup[0]
    assert g.discard(s, 2) is None


def test_reconcile_keeps_the_largest_overlap_and_names_every_move():
    # before: cluster 5 = keys 0, 1, 2; cluster 7 = keys 3, 4; key 9 (cluster 7) is removed
    old = {0: 5, 1: 5, 2: 5, 3: 7, 4: 7, 9: 7}
    before = dict(old)
    keys = np.array([0, 1, 2, 3, 4, 10])
    # after: keys 0, 1 stay together; key 2 joins keys 3, 4; new key 10 alone
    local = np.array([0, 0, 1, 1, 1, 2])
    out = reconcile(keys, np.array([1, 2, 3, 1, 2, 4]), local, old, {9}, {9: 6}, {10}, next_cid=8)
    assert out.ids.tolist() == [5, 5, 7, 7, 7, 8] and out.next_cid == 9
    kinds = [(e.kind, e.cluster, e.source) for e in out.events]
    assert kinds == [("shrunk", 7, -1), ("split", 7, 5), ("created", 8, -1)]
    assert replay(before, out.events) == dict(zip(keys.tolist(), out.ids.tolist()))
    # a cluster nobody keeps merges into another
    out = reconcile(keys[:5], np.arange(5), np.zeros(5, np.int64), {0: 5, 1: 5, 2: 5, 3: 7, 4: 7}, set(), {},
                    set(), next_cid=8)
    assert out.ids.tolist() == [5] * 5 and [(e.kind, e.cluster, e.source) for e in out.events] == [
        ("merged", 5, 7)]
