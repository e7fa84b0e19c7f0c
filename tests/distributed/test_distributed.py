"""Distributed QuickMatch: partition, boundary distances, contested test, simulator."""
import numpy as np
import pytest
from conftest import assert_consistent

import dqm
from dqm import InputError
from dqm.distributed import DQMConfig, boundary, contested, partition, simulate
from dqm.evaluation import comembership_scores
from dqm.synthetic import sift_like


@pytest.fixture(scope="module")
def scene():
    return sift_like(n_images=6, n_points=150, clutter_per_image=60, noise=0.3, seed=21)


# ----------------------------------------------------------------- boundary


def random_seeds(m, dim, seed):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(m, dim)) * 3.0


@pytest.mark.parametrize("m,dim", [(3, 2), (5, 4), (8, 16)])
def test_qp_distance_at_least_bisector_and_equal_when_foot_inside(m, dim):
    P = random_seeds(m, dim, m * dim)
    rng = np.random.default_rng(0)
    X = rng.normal(size=(60, dim)) * 3.0
    cells = partition.route(X, P)
    H = boundary.hyperplane_distances(X, P, cells)
    E = boundary.cell_distances(X, P, cells)
    assert (E >= H - 1e-9).all()
    assert (H[np.arange(len(X)), cells] == 0).all() and (E[np.arange(len(X)), cells] == 0).all()
    for k in range(len(X)):
        for a in range(m):
            if a == cells[k]:
                continue
            i = cells[k]
            normal = (P[a] - P[i]) / np.linalg.norm(P[a] - P[i])
            foot = X[k] + H[k, a] * normal
            foot_in_a = partition.route(foot[None], P)[0] == a or np.isclose(
                np.linalg.norm(foot - P[a]), np.min(np.linalg.norm(P - foot, axis=1)))
            if foot_in_a:
                assert E[k, a] == pytest.approx(H[k, a], rel=1e-6, abs=1e-9)


def test_qp_distance_is_the_true_distance_to_the_cell():
    """Dense sampling of the cell never finds a point closer than the QP distance, and finds one close to it."""
    P = random_seeds(4, 2, 7)
    rng = np.random.default_rng(1)
    X = rng.normal(size=(20, 2)) * 3.0
    cells = partition.route(X, P)
    E = boundary.cell_distances(X, P, cells)
    grid = np.stack(np.meshgrid(np.linspace(-15, 15, 601), np.linspace(-15, 15, 601)), -1).reshape(-1, 2)
    gcell = partition.route(grid, P)
    for a in range(4):
        pts = grid[gcell == a]
        d = np.sqrt(((X[:, None, :] - pts[None]) ** 2).sum(-1)).min(1)
        other = cells != a
        assert (d[other] >= E[other, a] - 1e-9).all()
        assert np.allclose(d[other], E[other, a], atol=0.1)


def test_bisector_bound_is_additive():
    P = random_seeds(5, 8, 3)
    rng = np.random.default_rng(2)
    X = rng.normal(size=(300, 8)) * 3.0
    cells = partition.route(X, P)
    H = boundary.hyperplane_distances(X, P, cells)
    D = np.sqrt(((X[:, None] - X[None]) ** 2).sum(-1))
    i, j = np.nonzero(cells[:, None] != cells[None, :])
    assert (D[i, j] >= H[i, cells[j]] + H[j, cells[i]] - 1e-9).all()


# ----------------------------------------------------------------- partition


def test_route_ties_go_to_the_lower_index():
    P = np.array([[0.0, 0.0], [2.0, 0.0]])
    assert partition.route(np.array([[1.0, 5.0]]), P)[0] == 0


def test_seeds_are_deterministic_and_depend_on_the_integer(scene):
    a = partition.seeded_seeds(5, 4, 128)
    assert np.array_equal(a, partition.seeded_seeds(5, 4, 128))
    assert not np.array_equal(a, partition.seeded_seeds(6, 4, 128))
    X = scene.descriptors.astype(float)
    k1 = partition.kmeans_seeds(X[:200], 4, 9)
    assert np.array_equal(k1, partition.kmeans_seeds(X[:200], 4, 9))


@pytest.mark.parametrize("bad", [-1, 2 ** 63, 1.5, "7", None, True])
def test_bad_partition_seed(bad):
    with pytest.raises(InputError, match="partition seed"):
        partition.check_seed(bad)


# ----------------------------------------------------------------- contested


def test_contested_test_never_misses_a_cross_cell_merge(scene):
    """Rigour of the default test: every merged centralized edge that crosses cells has a contested child."""
    X = scene.descriptors
    r = simulate(X, scene.image_ids, DQMConfig(agents=5, seed=2, mode="lean"))
    central = dqm.quickmatch(X, scene.image_ids, kernel="quadratic")
    child = np.flatnonzero(central.parent >= 0)
    par = central.parent[child]
    merged = central.labels[child] == central.labels[par]
    crossing = merged & (r.cells[child] != r.cells[par])
    assert crossing.any()
    assert r.contested[child[crossing]].all()


def test_unit_targets_pick_the_lowest_contested_agent():
    units = np.array([0, 0, 1, 2])
    C = np.zeros((4, 5), bool)
    C[0, 3] = True
    C[1, 1] = True
    C[2, 4] = True
    t = contested.unit_targets(units, C, me=4, below=4)
    assert t.tolist() == [1, 4, 4]  # unit 0 -> 1, unit 1 contested only upward (4 = me), unit 2 none


def test_tree_units_join_clusters_linked_by_any_edge():
    labels = np.array([0, 0, 1, 2])
    parent = np.array([-1, 0, 1, -1])  # 2's parent is 1 although they did not merge
    u = contested.units_from_tree(labels, parent)
    assert u[0] == u[1] == u[2] != u[3]


# ----------------------------------------------------------------- simulator


@pytest.mark.parametrize("mode", ["balanced", "lean", "paper"])
@pytest.mark.parametrize("m", [2, 3, 6])
def test_result_is_a_partition_with_c1_c2(scene, mode, m):
    r = simulate(scene.descriptors, scene.image_ids, DQMConfig(agents=m, mode=mode, seed=4))
    n = len(scene)
    assert r.labels.shape == (n,) and (r.holder >= 0).all() and (r.holder < m).all()
    assert_consistent(r.labels, scene.image_ids)
    # every cluster lives in exactly one agent
    for lab in np.unique(r.labels):
        assert len(np.unique(r.holder[r.labels == lab])) == 1
    assert r.stats["arrival_check_failures"] == 0
    # every message the runtime would send was counted; routing moved features
    assert r.traffic.total("features") > 0
    if mode == "balanced":
        assert r.traffic.messages("bounds") == m * (m - 1) and r.traffic.messages("ghost") > 0
    else:
        assert r.traffic.messages("minima") == m * (m - 1)


@pytest.mark.parametrize("mode", ["balanced", "lean", "paper"])
def test_one_agent_equals_centralized(scene, mode):
    r = simulate(scene.descriptors, scene.image_ids, DQMConfig(agents=1, mode=mode))
    central = dqm.quickmatch(scene.descriptors, scene.image_ids, kernel="quadratic")
    np.testing.assert_array_equal(r.labels, central.labels)
    assert r.traffic.total("features") == 0


def test_lean_mode_is_faithful(scene):
    central = dqm.quickmatch(scene.descriptors, scene.image_ids, kernel="quadratic")
    for m in (2, 4, 8):
        r = simulate(scene.descriptors, scene.image_ids, DQMConfig(agents=m, seed=1, mode="lean"))
        assert comembership_scores(r.labels, central.labels).f1 >= 0.99


def test_deterministic(scene):
    cfg = DQMConfig(agents=4, seed=8, partition="seeded")
    a = simulate(scene.descriptors, scene.image_ids, cfg)
    b = simulate(scene.descriptors, scene.image_ids, cfg)
    np.testing.assert_array_equal(a.labels, b.labels)
    assert a.traffic.as_json() == b.traffic.as_json()


def test_empty_cells_still_work(scene):
    """Seeded seeds far from the data leave agents without features; they still take part."""
    cfg = DQMConfig(agents=6, seed=0, partition="seeded")
    r = simulate(scene.descriptors, scene.image_ids, cfg)
    routed = np.bincount(r.cells, minlength=6)
    assert_consistent(r.labels, scene.image_ids)
    assert (routed == 0).any() or routed.min() < len(scene) / 6  # imbalance of the seeded mode
    empty = dqm.quickmatch(scene.descriptors[:0], scene.image_ids[:0])
    assert empty.n_clusters == 0


def test_force_empty_agent():
    X = np.array([[0.0, 0.0], [0.1, 0.0], [10.0, 0.0], [10.1, 0.0]])
    ids = np.array([0, 1, 0, 1])
    r = simulate(X, ids, DQMConfig(agents=3, seed=0))
    assert_consistent(r.labels, ids)
    assert r.labels[0] == r.labels[1] and r.labels[2] == r.labels[3] and r.labels[0] != r.labels[2]


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        ({"agents": 0}, "agents must be >= 1"),
        ({"agents": -2}, "agents must be >= 1"),
        ({"agents": 2.5}, "integer"),
        ({"agents": 10 ** 6}, "more agents"),
        ({"agents": 2, "seed": -3}, "partition seed"),
        ({"agents": 2, "partition": "random"}, "partition must be one of"),
        ({"agents": 2, "mode": "fast"}, "mode must be one of"),
        ({"agents": 2, "halo": 0}, "halo"),
    ],
)
def test_bad_configuration(scene, kwargs, pattern):
    with pytest.raises(InputError, match=pattern):
        simulate(scene.descriptors, scene.image_ids, DQMConfig(**kwargs))
