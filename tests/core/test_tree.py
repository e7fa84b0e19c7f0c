"""The tree's nearest candidate per child against the definition: the first of each child in
(distance, candidate or tie key, position) order."""
import numpy as np
import pytest

from dqm.core import native, tree


def _by_lexsort(child, cand, dist, n, tie=None):
    parent, pdist, row = np.full(n, -1), np.full(n, np.inf), np.full(n, -1)
    order = np.lexsort((cand if tie is None else tie, dist, child))
    c = child[order]
    first = np.ones(len(c), dtype=bool)
    first[1:] = c[1:] != c[:-1]
    sel = order[first]
    parent[child[sel]], pdist[child[sel]], row[child[sel]] = cand[sel], dist[sel], sel
    return parent, pdist, row


@pytest.mark.parametrize("use_native", [True, False])
def test_nearest_candidates_is_the_first_in_distance_then_key_order(use_native):
    if use_native and not native.native_available():
        pytest.skip("the native kernel is not built")
    rng = np.random.default_rng(0)
    for trial in range(400):
        n, m = int(rng.integers(1, 60)), int(rng.integers(1, 300))
        child, cand = rng.integers(0, n, m), rng.integers(0, n, m)
        if trial % 4 == 1:  # sorted by child
            child = np.sort(child)
        elif trial % 4 == 2:  # child by child, children in any order (the fast engine's edges)
            child = rng.permutation(n)[np.sort(child)]
        dist = rng.integers(0, 4, m).astype(float)  # ties in distance, and repeated (child, cand) edges
        if trial % 3 == 0:
            dist[rng.random(m) < 0.2] = np.inf
        tie = rng.integers(0, 3, m) if trial % 2 else None
        if trial % 5 == 0:  # narrower index types than int64
            child, cand = child.astype(np.int32), cand.astype(np.int32)
            tie = None if tie is None else tie.astype(np.int32)
        got = tree.nearest_candidates(child, cand, dist, n, tie=tie, use_native=use_native)
        for a, b in zip(got, _by_lexsort(child, cand, dist, n, tie=tie)):
            np.testing.assert_array_equal(a, b)
        # parents: the nearest among the candidates that rank above the child (higher density, then lower index)
        density = rng.integers(0, 3, n).astype(float)
        above = (density[cand] > density[child]) | ((density[cand] == density[child]) & (cand < child))
        want = _by_lexsort(child[above], cand[above], dist[above], n)
        got = tree.select_parents(n, child, cand, dist, density, use_native=use_native)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
    assert tree.nearest_candidates(np.zeros(0, int), np.zeros(0, int), np.zeros(0), 3,
                                   use_native=use_native)[0].tolist() == [-1, -1, -1]


def test_member_pairs_are_every_two_members_of_every_cluster_in_order():
    """Clusters of many sizes (singletons, pairs, one large), labels in any order and of any sign: every two
    members once, i < j, cluster by cluster in label order and row order within one."""
    from dqm.core.tree import member_pairs

    rng = np.random.default_rng(5)
    labels = np.r_[rng.integers(-3, 40, 300), np.full(25, 99)][rng.permutation(325)]
    want = [(i, j) for lab in np.unique(labels) for i in np.flatnonzero(labels == lab)
            for j in np.flatnonzero(labels == lab) if i < j]
    a, b = member_pairs(labels)
    assert a.dtype == np.int64 and list(zip(a.tolist(), b.tolist())) == want
    for few in ([], [7], [1, 2, 3]):
        assert len(member_pairs(np.array(few, np.int64))[0]) == 0


def test_the_native_pass_refuses_indices_outside_its_arrays():
    """The C loop writes at each child's slot: an index outside them raises instead of writing elsewhere."""
    if not native.native_available():
        pytest.skip("the native kernel is not built")
    with pytest.raises(IndexError, match="child index"):
        tree.nearest_candidates(np.array([0, 3]), np.array([1, 1]), np.array([1.0, 2.0]), 3)
    with pytest.raises(IndexError, match="candidate index"):
        tree.select_parents(3, np.array([0, 1]), np.array([1, -1]), np.array([1.0, 2.0]), np.ones(3))
