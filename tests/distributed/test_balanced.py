"""The balanced mode: identical to centralized QuickMatch, and the pieces that make it so."""
import math

import numpy as np
import pytest
from conftest import assert_consistent

import dqm
from dqm import InputError
from dqm.core import density
from dqm.distributed import DQMConfig, boundary, forest, ghosts, messages, partition, protocol, simulate, sketch
from dqm.distributed.sources import image_owners
from dqm.synthetic import sift_like


def _same_as_central(r, central):
    np.testing.assert_array_equal(r.labels, central.labels)
    np.testing.assert_array_equal(r.parent, central.parent)
    np.testing.assert_array_equal(r.parent_distance, central.parent_distance)
    # densities: the centralized engine refines only those whose order is uncertain, the rest
    # carry its float32 bound; the agents' exact values must lie within it
    np.testing.assert_allclose(r.density, central.density, rtol=1e-3)
    assert r.stats["arrival_check_failures"] == 0


@pytest.fixture(scope="module")
def sift():
    ds = sift_like(n_images=7, n_points=160, clutter_per_image=70, noise=0.3, seed=11)
    return ds.descriptors, ds.image_ids


@pytest.fixture(scope="module")
def floats():
    rng = np.random.default_rng(3)
    centers = rng.normal(size=(60, 12)) * 4.0
    X = centers[rng.integers(0, 60, 700)] + rng.normal(size=(700, 12))
    return X.astype(np.float32), rng.integers(0, 9, 700)


@pytest.mark.parametrize("m", range(1, 9))
def test_identical_to_centralized_on_synthetic_sift(sift, m):
    X, ids = sift
    central = dqm.quickmatch(X, ids, kernel="quadratic")
    r = simulate(X, ids, DQMConfig(agents=m, seed=m))
    _same_as_central(r, central)
    assert_consistent(r.labels, ids)


@pytest.mark.parametrize("m", [1, 2, 3, 5, 8])
def test_identical_to_centralized_on_random_floats(floats, m):
    X, ids = floats
    central = dqm.quickmatch(X, ids, kernel="quadratic")  # float32 is what travels
    r = simulate(X, ids, DQMConfig(agents=m, seed=7, partition="seeded", seed_norm=20.0))
    _same_as_central(r, central)


@pytest.mark.parametrize("m", [2, 5, 8])
def test_identical_to_centralized_on_real_graf(graf_sift, m):
    X, ids = graf_sift
    keep = np.concatenate([np.flatnonzero(ids == k)[:700] for k in np.unique(ids)])
    X, ids = X[keep], ids[keep]
    central = dqm.quickmatch(X, ids, kernel="quadratic")
    r = simulate(X, ids, DQMConfig(agents=m, seed=1))
    _same_as_central(r, central)
    assert r.stats["ghosts_per_feature"] > 0


@pytest.mark.parametrize("variant", [{"ghost_rule": "two-way", "sketch_dims": 0}, {"sketch_dims": 0},
                                     {"sketch_dims": 6}, {"cell_weights": False}, {"rho": 1.4}])
def test_every_variant_is_exact(sift, variant):
    X, ids = sift
    rho = variant.get("rho", dqm.DEFAULT_RHO)
    central = dqm.quickmatch(X, ids, kernel="quadratic", rho=rho)
    _same_as_central(simulate(X, ids, DQMConfig(agents=4, seed=3, **variant)), central)


def test_ties_duplicates_and_single_feature_images():
    """Symmetric grids (exact density ties), duplicates within and across images, lonely images."""
    g = np.stack(np.meshgrid(np.arange(5.0), np.arange(5.0)), -1).reshape(-1, 2)
    X = np.vstack([g, g + 0.1, g + 0.2, g[:3], [[50.0, 50.0]], [[2.0, 2.05]]]).astype(np.float32)
    ids = np.concatenate([np.repeat([0, 1, 2], len(g)), [0, 1, 1], [7], [8]])
    central = dqm.quickmatch(X, ids, kernel="quadratic")
    assert (central.sigma == 0).any()  # the repeated grid points in one image
    for m in (2, 3, 4):
        r = simulate(X, ids, DQMConfig(agents=m, seed=m, samples_per_agent=8))
        np.testing.assert_array_equal(r.labels, central.labels)
        np.testing.assert_array_equal(r.parent, central.parent)
    assert r.traffic.messages("fill") == m - 1  # the median sigma of single-feature images was agreed


def test_work_is_spread_and_cells_balanced():
    ds = sift_like(n_images=12, n_points=700, clutter_per_image=250, noise=0.3, seed=2)
    m = 8
    r = simulate(ds.descriptors, ds.image_ids, DQMConfig(agents=m, seed=1))
    s = r.stats
    assert s["largest_cell_share"] <= 1.25
    assert s["max_pair_share"] <= 2.5 / m
    assert 0 < s["ghosts_per_feature"] < m - 1
    assert s["bytes_over_raw"] > 0 and s["arrival_check_failures"] == 0
    # flow control: every agent asks for its copies a window at a time (two out at most) and lets each go
    # once met, so the most features it holds at once (measured by its driver at every message) stays
    # near its cell plus two windows, while it meets several times that many copies
    source = np.bincount(image_owners(ds.image_ids, m), minlength=m)  # each agent's own images' features
    for a, p in enumerate(r.per_agent):
        own = p["features_owned"]
        window = max(256, math.ceil(own / 4))
        assert p["ghost_windows"] >= p["ghosts_held"] / window  # pulled in windows
        # the held features: the source's before routing, then the cell and at most two windows
        assert p["held_peak"] <= max(source[a] + own, own + 2 * window)
        assert p["ghosts_held"] > 2 * window  # more copies met than held at once
    assert s["max_features_share"] <= 2.0 / m
    # the lean cascade gathers the work at agent 0 on the same data
    lean = simulate(ds.descriptors, ds.image_ids, DQMConfig(agents=m, seed=1, mode="lean"))
    assert lean.stats["max_pair_share"] > 2 * s["max_pair_share"]


def test_sketches_travel_only_where_they_pay(graf_sift):
    """Generated SIFT-like data defeats 48 projected dimensions: after the pilot the senders ask
    for no more sketches, and the bytes stay within the pilot's cost of no sketch at all. On real
    SIFT the full sketches keep about half the copies home and save bytes."""
    ds = sift_like(n_images=12, n_points=700, clutter_per_image=250, noise=0.3, seed=2)
    on, off = (simulate(ds.descriptors, ds.image_ids, DQMConfig(agents=8, seed=1, sketch_dims=k)).stats
               for k in (48, 0))
    assert on["ghosts_per_feature"] == off["ghosts_per_feature"]
    assert on["sketches_per_feature"] < 0.15 * (8 - 1) / 2
    assert on["bytes_over_raw"] <= 1.06 * off["bytes_over_raw"]
    X, ids = graf_sift
    keep = np.concatenate([np.flatnonzero(ids == k)[:700] for k in np.unique(ids)])
    on, off = (simulate(X[keep], ids[keep], DQMConfig(agents=5, seed=1, sketch_dims=k)).stats for k in (48, 0))
    assert on["ghosts_per_feature"] < 0.7 * off["ghosts_per_feature"]
    assert on["bytes_over_raw"] < off["bytes_over_raw"]


def test_gaussian_kernel_is_refused_clearly(sift):
    X, ids = sift
    with pytest.raises(InputError, match="a balanced-mode distributed job needs the finite kernel"):
        simulate(X, ids, DQMConfig(agents=2, kernel="gaussian"))


@pytest.mark.parametrize("kwargs, pattern", [
    ({"ghost_rule": "sideways"}, "ghost_rule must be one of"), ({"sketch_dims": -1}, "sketch_dims"),
    ({"balance_rounds": 1.5}, "balance_rounds"), ({"cell_weights": "yes"}, "cell_weights"),
])
def test_bad_balanced_configuration(sift, kwargs, pattern):
    with pytest.raises(InputError, match=pattern):
        simulate(*sift, DQMConfig(agents=2, **kwargs))


# ----------------------------------------------------------------- exact sums


def test_exact_sums_are_correctly_rounded_and_partition_free():
    rng = np.random.default_rng(0)
    d2 = rng.uniform(0, 2, 5000)
    w = rng.uniform(0.5, 1.5, 5000)
    terms = density.quadratic_terms(d2, w)
    assert np.all(terms * 2.0 ** 53 == np.round(terms * 2.0 ** 53))  # on the 2^-53 grid
    target = rng.integers(0, 40, 5000)
    whole = density.ExactSums(40)
    whole.add_terms(target, terms)
    expect = np.array([math.fsum(terms[target == t]) for t in range(40)])
    np.testing.assert_array_equal(whole.values(), expect)
    # the same sums from three agents' partial sums, shipped in wire form, in another order
    parts = rng.integers(0, 3, 5000)
    total = density.ExactSums(40)
    for p in (2, 0, 1):
        part = density.ExactSums(40)
        sel = parts == p
        part.add_terms(target[sel], terms[sel])
        units, high = density.pack_parts(*part.parts(np.arange(40)))
        total.add_parts(np.arange(40), *density.unpack_parts(units, high))
    np.testing.assert_array_equal(total.values(), expect)


def test_large_partial_sums_travel_in_the_wide_form():
    s = density.ExactSums(2)
    s.add_terms(np.zeros(3000, np.int64), np.ones(3000))  # a partial density of 3000 > 1024
    units, high = density.pack_parts(*s.parts(np.arange(2)))
    assert len(high) == 2
    t = density.ExactSums(2)
    t.add_parts(np.arange(2), *density.unpack_parts(units, high))
    assert t.values()[0] == 3000.0 and t.values()[1] == 0.0


# ----------------------------------------------------------------- geometry, sketches, ghosts


def test_power_bisector_lower_bounds_are_additive():
    rng = np.random.default_rng(5)
    P = rng.normal(size=(6, 10)) * 3
    w = rng.normal(size=6) * 4
    X = rng.normal(size=(400, 10)) * 3
    cells = partition.route(X, P, w)
    H = boundary.bisector_lower_bounds(X, P, cells, w)
    D = np.sqrt(((X[:, None] - X[None]) ** 2).sum(-1))
    i, j = np.nonzero(cells[:, None] != cells[None, :])
    assert (D[i, j] >= H[i, cells[j]] + H[j, cells[i]]).all()


@pytest.mark.parametrize("their_reach", [True, False])
def test_sketch_prefilter_never_drops_a_pair(their_reach):
    """Brute force: every x with some y within the threshold is kept; some others are dropped."""
    ds = sift_like(n_images=6, n_points=300, clutter_per_image=100, noise=0.3, seed=9)
    X = ds.descriptors.astype(np.float64)
    rng = np.random.default_rng(1)
    sample = X[rng.choice(len(X), 200, replace=False)]
    center = sample.mean(0)
    space = sketch.SketchSpace(sketch.basis_from_sample(sample, center, 48), center)
    half = len(X) // 2
    xs, ys = X[:half], X[half:]
    Rx = rng.uniform(120, 260, len(xs))
    Ry = rng.uniform(120, 260, len(ys))
    sk = dict(sketch.encode(space, ys, Ry), pending=0)
    payload = protocol.merge_parts("sketch", [messages.decode(b) for b in
                                              protocol.data_messages("sketch", "j", 1, sk)])
    kept = sketch.plausible(space, xs, Rx, payload, use_their_reach=their_reach)
    D = np.sqrt(((xs[:, None] - ys[None]) ** 2).sum(-1))
    thr = np.maximum(Rx[:, None], Ry[None, :]) if their_reach else Rx[:, None]
    needed = (D < thr).any(axis=1)
    assert needed.any() and (~needed).any()
    assert kept[needed].all()
    assert (~kept).sum() >= 0.1 * (~needed).sum()  # and it filters


def test_one_way_ghost_rule_covers_every_interacting_pair():
    """For every cross-cell pair within either feature's reach, the sender of the pair's
    orientation ships its feature (bisector rule alone, from the exchanged summaries)."""
    rng = np.random.default_rng(4)
    X = (rng.normal(size=(40, 8)) * 6.0)[rng.integers(0, 40, 1500)] + rng.normal(size=(1500, 8))
    m = 5
    P = partition.kmeans_seeds(X[::7], m, 3)
    cells = partition.route(X, P)
    R = rng.uniform(0.5, 2.5, len(X))
    H = boundary.bisector_lower_bounds(X, P, cells)
    E = np.full((m, m), np.inf)
    S = np.full((m, m), np.inf)
    for c in range(m):
        sel = cells == c
        E[c], S[c] = ghosts.cell_summaries(H[sel], R[sel], c)
    ships = ghosts.orientation(m, "one-way")
    assert (ships | ships.T | np.eye(m, dtype=bool)).all() and not (ships & ships.T).any()
    shipped = np.zeros((len(X), m), bool)
    for a in range(m):
        sel = np.flatnonzero(cells == a)
        for b in range(m):
            if ships[a, b]:
                shipped[sel, b] = ghosts.ship_mask(H[sel, b], R[sel], E[b, a], S[b, a], "one-way")
    D = np.sqrt(((X[:, None] - X[None]) ** 2).sum(-1))
    i, j = np.nonzero((cells[:, None] != cells[None, :]) & (D < np.maximum(R[:, None], R[None, :])))
    a, b = cells[i], cells[j]
    sender_is_i = ships[a, b]
    assert len(i) and np.where(sender_is_i, shipped[i, b], shipped[j, a]).all()
    assert shipped.sum() < (len(X) * (m - 1)) / 2  # and the rule does not ship everything


def test_the_rest_of_a_sketch_is_asked_for_only_if_it_can_pay():
    assert sketch.worth_the_rest(n_unhit=100, n_rest=200, copy_bytes=168, sketch_bytes=53)
    assert not sketch.worth_the_rest(n_unhit=10, n_rest=800, copy_bytes=168, sketch_bytes=53)
    ids = np.arange(80_000)
    assert 0.11 < sketch.pilot_mask(ids).mean() < 0.14  # an eighth, deterministic
    np.testing.assert_array_equal(sketch.pilot_mask(ids), sketch.pilot_mask(ids.copy()))


def test_crossing_components_go_to_the_lowest_agent():
    # fragments 10 (agent 3) -> 20 (agent 1) -> 30 (agent 2); 40 (agent 2) -> 50 (agent 4)
    keys, agents, targets = forest.assign_components(
        np.array([10, 20, 40]), np.array([3, 1, 2]), np.array([20, 30, 50]), np.array([1, 2, 4]))
    got = dict(zip(keys.tolist(), zip(agents.tolist(), targets.tolist())))
    assert got == {10: (3, 1), 20: (1, 1), 30: (2, 1), 40: (2, 2), 50: (4, 2)}
    assert forest.fragment_roots(np.array([-1, 0, 1, -1, 3])).tolist() == [0, 0, 0, 3, 3]


def test_routing_of_a_row_does_not_depend_on_its_batch():
    """Points on (or within rounding of) a bisector go to the exact nearest seed, alone or in any batch:
    identical descriptors held by different sources must meet in one cell."""
    rng = np.random.default_rng(8)
    P = rng.normal(size=(6, 128)) * 100
    w = rng.normal(size=6)
    i, j = rng.integers(0, 6, 150), rng.integers(0, 6, 150)
    X = (P[i] + P[j]) / 2 + rng.choice([0.0, 1e-13, -1e-13], size=(150, 1)) * rng.normal(size=(150, 128))
    X = np.vstack([X, rng.normal(size=(100, 128)) * 100])
    for weights in (None, w):
        batch = partition.route(X, P, weights)
        alone = np.array([partition.route(X[k:k + 1], P, weights)[0] for k in range(len(X))])
        np.testing.assert_array_equal(batch, alone)
        np.testing.assert_array_equal(partition.route(X[::-1], P, weights)[::-1], batch)
        exact = [partition._exact_route(x, P, weights, np.arange(6)) for x in X[:40]]
        np.testing.assert_array_equal(batch[:40], exact)


def test_exact_routing_equals_rational_arithmetic():
    """The near-tie decision in scaled integers equals the least power in fractions, at any scale,
    with subnormal coordinates, exact ties (the lower index) and weights."""
    from fractions import Fraction

    def least_power(x, P, w):
        xs = [Fraction(v) for v in x.tolist()]
        powers = [sum(Fraction(c) * (Fraction(c) - 2 * v) for c, v in zip(P[a].tolist(), xs))
                  - (0 if w is None else Fraction(float(w[a]))) for a in range(len(P))]
        return min(range(len(P)), key=lambda a: (powers[a], a))

    rng = np.random.default_rng(3)
    for trial in range(120):
        m, dim = int(rng.integers(2, 7)), int(rng.integers(1, 40))
        scale = 10.0 ** int(rng.integers(-30, 30))
        P = rng.normal(size=(m, dim)) * scale
        if trial % 3 == 0:
            P[1] = P[0]
        w = None if trial % 2 else rng.normal(size=m) * scale ** 2 * rng.choice([0.0, 1e-3, 1.0])
        i, j = rng.integers(0, m, 2)
        x = (P[i] + P[j]) / 2 + rng.choice([0.0, 1e-13]) * rng.normal(size=dim) * scale
        if trial % 7 == 0:
            x[0] = 5e-324
        assert partition._exact_route(x, P, w, np.arange(m)) == least_power(x, P, w), trial


def test_many_agents_with_few_features_each_still_get_seeds():
    rng = np.random.default_rng(0)
    X = rng.integers(0, 50, (30, 8)).astype(np.uint8)
    ids = np.repeat([0, 1], 15)
    central = dqm.quickmatch(X, ids, kernel="quadratic")
    r = simulate(X, ids, DQMConfig(agents=20, seed=2, samples_per_agent=4))
    np.testing.assert_array_equal(r.labels, central.labels)


def test_a_sketch_of_the_wrong_width_is_counted_not_fatal():
    from dqm.distributed.balanced import BalancedCore

    center = np.zeros(16)
    space = sketch.SketchSpace(sketch.basis_from_sample(np.random.default_rng(0).normal(size=(40, 16)), center, 6),
                               center)
    core = BalancedCore(0, DQMConfig(agents=2).validated(), space)
    good = sketch.encode(space, np.ones((3, 16)), np.ones(3))
    bad = sketch.encode(sketch.SketchSpace(np.eye(16, dtype=np.int8)[:4], center), np.ones((3, 16)), np.ones(3))
    assert core._sketch_ok(good) and core.failures == 0
    assert not core._sketch_ok(bad) and core.failures == 1
    assert not core._sketch_ok(None) and core.failures == 1


def test_parts_that_do_not_fit_together_are_refused():
    a = messages.decode(messages.encode("notify", "j", 1, seq=0, part=0, parts=2, child=np.arange(2),
                                        parent=np.arange(2)))
    b = messages.decode(messages.encode("notify", "j", 1, seq=1, part=1, parts=3, child=np.arange(2),
                                        parent=np.arange(2)))
    with pytest.raises(messages.MessageError, match="parts"):
        protocol.merge_parts("notify", [a, b])
    c = messages.decode(messages.encode("ghost", "j", 1, seq=0, part=0, parts=2, offset=0, ids=np.arange(1),
                                        image_ids=np.zeros(1, np.int64), descriptors=np.zeros((1, 4), np.uint8),
                                        sigma=np.ones(1)))
    d = messages.decode(messages.encode("ghost", "j", 1, seq=1, part=1, parts=2, offset=0, ids=np.arange(1),
                                        image_ids=np.zeros(1, np.int64), descriptors=np.zeros((1, 5), np.uint8),
                                        sigma=np.ones(1)))
    with pytest.raises(messages.MessageError, match="disagree on descriptors"):
        protocol.merge_parts("ghost", [c, d])


# ----------------------------------------------------------------- messages


def test_round_messages_split_into_parts_and_merge_back():
    rng = np.random.default_rng(0)
    n = 300_000  # over PART_BYTES of rows
    payload = {"ids": np.arange(n), "image_ids": rng.integers(0, 5, n), "sigma": rng.random(n),
               "parent": rng.integers(-1, n, n), "distance": rng.random(n)}
    msgs = protocol.data_messages("component", "j", 2, payload, seq0=5)
    assert len(msgs) == protocol.part_count("component", payload) > 1
    decoded = [messages.decode(b, job="j", agents=3) for b in msgs]
    assert [d["seq"] for d in decoded] == list(range(5, 5 + len(msgs)))
    merged = protocol.merge_parts("component", decoded[::-1])
    for f, v in payload.items():
        np.testing.assert_array_equal(merged[f], v)


@pytest.mark.parametrize("kind, fields, pattern", [
    ("ghost", {"offset": 0, "ids": np.array([-1]), "image_ids": np.zeros(1, np.int64),
               "descriptors": np.zeros((1, 4), np.uint8), "sigma": np.ones(1)}, "negative feature id"),
    ("ghost", {"offset": 0, "ids": np.arange(2), "image_ids": np.zeros(1, np.int64),
               "descriptors": np.zeros((2, 4), np.uint8), "sigma": np.ones(2)}, "rows"),
    ("ghost", {"offset": -1, "ids": np.arange(1), "image_ids": np.zeros(1, np.int64),
               "descriptors": np.zeros((1, 4), np.uint8), "sigma": np.ones(1)}, "negative ghost.offset"),
    ("grant", {"offset": 0, "count": -2}, "negative grant.count"),
    ("density", {"density": np.array([np.nan])}, "non-finite density"),
    ("assign", {"key": np.arange(2), "target": np.array([0, 9])}, "outside"),
    ("bounds", {"minima": np.zeros(2), "slack": np.zeros(2)}, "for 3 agents"),
    ("sums", {"units": np.array([-5]), "high": np.zeros(0, np.int64)}, "negative sums.units"),
    ("proposal", {"index": np.zeros(1, np.int64), "parent": np.array([-1]), "distance": np.zeros(1)}, "parent below 0"),
    ("sketch", {"codes": np.zeros((1, 3), np.int8), "residual": np.zeros(1, np.uint8),
                "reach": np.ones(1, np.float32), "scale": np.ones(2), "bounds": np.zeros(4), "pending": 0}, "scales"),
])
def test_hostile_round_messages_are_refused(kind, fields, pattern):
    raw = messages.encode(kind, "j", 1, seq=0, part=0, parts=1, **fields)
    with pytest.raises(messages.MessageError, match=pattern):
        messages.decode(raw, job="j", agents=3)
    bad_part = messages.encode(kind, "j", 1, seq=0, part=3, parts=2, **fields)
    with pytest.raises(messages.MessageError):
        messages.decode(bad_part, job="j", agents=3)


def test_an_offer_larger_than_any_job_is_refused_not_allocated():
    """A sender's offer sizes the receiver's bookkeeping of the copies it will pull: an absurd count is a
    failure and nothing is pulled from that sender, instead of an allocation that exhausts the machine."""
    from dqm.distributed.balanced import MAX_OFFER, ROUNDS, BalancedCore
    from dqm.distributed.shard import Shard

    rng = np.random.default_rng(0)
    X = rng.integers(0, 255, (40, 8)).astype(np.uint8)
    core = BalancedCore(1, DQMConfig(agents=2, seed=1, sketch_dims=0))
    core.set_shard([Shard(np.arange(40), np.arange(40) % 4, X, np.ones(40), np.ones(40, np.int64))],
                   rng.normal(size=(2, 8)), None)
    core.round = ROUNDS.index("ghost")
    assert core.senders("offer") == [0]
    assert core.step({0: {"count": MAX_OFFER + 1}}) == {}
    assert core.failures == 1 and core.next_grant() is None and core.pulled()
    assert len(core.held_ids) == 40  # its own features only


def test_an_agent_over_its_memory_budget_refuses_in_one_line(sift, monkeypatch):
    """The agents' pass streams its edges tile by tile and keeps only parent candidates; when those
    would pass the budget, the agent says so instead of exhausting the machine."""
    from dqm.core import memory

    X, ids = sift
    monkeypatch.setattr(memory, "resolve_budget", lambda _: 1 << 20)  # below any agent's base arrays
    with pytest.raises(memory.MemoryBudgetError, match=r"agent \d+: the parent candidates .*\(rho 3\)"):
        simulate(X, ids, DQMConfig(agents=3, rho=3.0))
