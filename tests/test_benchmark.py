"""QuickMatch against pairwise BF / FLANN tracks on ground truth (dqm.benchmark).

The seed paper's claim, tested as stated: QuickMatch at its default rho has a
higher F1 than BF and FLANN union-find tracks, on the CMU hotel landmarks and on
generated scenes. It holds at dqm's default rho 0.9 (at the former default
0.75 it did not on two scenes and hotel: docs/evaluation-notes.md); the tests
after it pin down where QuickMatch's remaining errors come from.
"""
import dataclasses

import numpy as np
import pytest
from conftest import assert_consistent, require_data

import dqm
from dqm import benchmark as BM
from dqm.vision.baselines import MATCHERS, TRACK_POLICIES

TRACKS = [f"{m}-{p}" for m in MATCHERS for p in TRACK_POLICIES]
SCENES = ("scene:0", "scene:1", "scene:2")

_cache = {}


def bench(spec):
    if spec not in _cache:
        if spec == "hotel":
            require_data("cmu_hotel")
            _cache[spec] = BM.load_benchmark("hotel", require_data())
        else:
            _cache[spec] = BM.load_benchmark(spec)
    return _cache[spec]


def operating_points(spec, rho=dqm.DEFAULT_RHO):
    key = (spec, rho)
    if key not in _cache:
        rows = BM.evaluate(bench(spec), ["quickmatch"] + TRACKS, rho=rho, curves=False)
        _cache[key] = {r.method: r for r in rows}
    return _cache[key]


@pytest.mark.parametrize("spec", SCENES + ("hotel",))
def test_quickmatch_default_beats_bf_and_flann_tracks_in_f1(spec):
    res = operating_points(spec)
    qm = res["quickmatch"].scores.f1
    for m in TRACKS:
        assert qm > res[m].scores.f1, (spec, m, qm, res[m].scores.f1)


@pytest.mark.parametrize("spec", SCENES + ("hotel",))
def test_quickmatch_default_is_more_precise_than_theia_tracks(spec):
    """Tracks that keep conflicting components (drop only the later feature) buy recall with precision."""
    res = operating_points(spec)
    for m in ("bf-drop-later", "flann-drop-later"):
        assert res["quickmatch"].scores.precision >= res[m].scores.precision, (spec, m)


@pytest.mark.parametrize("spec", SCENES)
def test_quickmatch_default_beats_openmvg_tracks_on_scenes(spec):
    res = operating_points(spec)
    for m in ("bf-drop-track", "flann-drop-track"):
        assert res["quickmatch"].scores.f1 > res[m].scores.f1, (spec, m)


@pytest.mark.parametrize("spec", SCENES)
def test_quickmatch_at_rho_1_beats_every_track_variant_on_scenes(spec):
    qm = operating_points(spec, rho=1.0)["quickmatch"].scores.f1
    res = operating_points(spec)
    for m in TRACKS:
        assert qm > res[m].scores.f1, (spec, m)


def test_hotel_errors_are_split_landmarks_not_mixed_ones():
    b = bench("hotel")
    r = dqm.quickmatch(b.descriptors, b.image_ids)
    res = operating_points("hotel")
    assert res["quickmatch"].scores.precision == 1.0  # no cluster mixes two landmarks
    split = [L for L in range(30) if len(np.unique(r.labels[b.point_ids == L])) > 1]
    assert 0 < len(split) <= 10
    # each split landmark falls apart into earlier and later frames of the sequence
    for L in split:
        m = np.flatnonzero(b.point_ids == L)
        parts = [np.median(b.image_ids[m][r.labels[m] == k]) for k in np.unique(r.labels[m])]
        assert max(parts) - min(parts) > 20, (L, parts)
    # the tracks' advantage is recall, not precision
    assert res["quickmatch"].scores.recall < res["bf-drop-later"].scores.recall


def test_rho_path_equals_direct_runs():
    b = bench("scene:1")
    rhos = [0.4, 0.6, 0.75, 0.9, 1.1]
    big = dqm.quickmatch(b.descriptors, b.image_ids, rho=1.1)
    for rho, labels in zip(rhos, BM.quickmatch_rho_path(big, rhos)):
        np.testing.assert_array_equal(labels, dqm.quickmatch(b.descriptors, b.image_ids, rho=rho).labels)
    with pytest.raises(dqm.InputError, match="exceeds"):
        BM.quickmatch_rho_path(big, [1.5])


def test_full_evaluation_of_a_scene():
    b = bench("scene:1")
    rows = BM.evaluate(b, rhos=(0.5, 0.75, 1.0), ratios=(0.6, 0.75, 0.9))
    by = {r.method: r for r in rows}
    assert list(by) == list(BM.METHODS)
    for m, r in by.items():
        assert 0 < r.scores.precision <= 1 and 0 < r.scores.recall <= 1 and r.time_s >= 0
        expected = {"quickmatch": {0.5, 0.75, 1.0, dqm.DEFAULT_RHO},
                    "quickmatch-verify": {dqm.DEFAULT_RHO},
                    "quickmatch-guided": {dqm.DEFAULT_RHO}}.get(m, {0.6, 0.75, 0.9})
        assert set(np.round(r.curve.thresholds, 6)) == expected and 0 < r.curve.auc() <= 1, m
        if m in ("bf", "flann"):  # raw pairwise matches are not consistent
            assert r.violations.c1_features > 0 and r.violations.c2_tracks > 0
        else:  # clusters and tracks are partitions without two features of one image
            assert r.violations.c1_features == 0 and r.violations.c2_tracks == 0
    # recall grows along the sweeps of QuickMatch and raw pairs (more matches accepted); tracks
    # need not: at a loose ratio their components chain into conflicting giants that get dropped
    for r in rows:
        if r.method in ("quickmatch", "bf", "flann"):
            assert np.all(np.diff(r.curve.recall[np.argsort(r.curve.thresholds)]) >= 0), r.method
    assert by["bf-drop-track"].curve.recall[-1] < by["bf-drop-track"].curve.recall[1]
    table = BM.markdown_table({"scene": rows}, {"scene": b})
    assert table.count("\n") == 2 + len(rows) and "QuickMatch" in table


def test_tracks_from_evaluate_are_consistent():
    b = bench("scene:1")
    from dqm.vision import baselines

    cand = baselines.pairwise_candidates(b.descriptors, b.image_ids, "bf")
    for policy in TRACK_POLICIES:
        assert_consistent(baselines.build_tracks(*cand.select(0.75), b.image_ids, policy), b.image_ids)


def test_unknown_dataset_and_method():
    with pytest.raises(dqm.InputError, match="not found"):
        BM.load_benchmark("/nonexistent/folder")
    with pytest.raises(dqm.InputError, match="unknown method"):
        BM.evaluate(bench("scene:1"), ["quickmatch", "orb"])


def test_truth_chance_links_compares_growth_rules_under_true_and_shifted_geometry(tmp_path):
    """scripts/truth_chance.py --links (docs/match-defaults/growth-chance.md, issue 61): per link rule of guided
    growth, the links its planar pairs propose under their homographies and under the same shifted (chance
    alone), and the grown clusters' scores. On a generated scene the true geometry proposes far more links than
    a shifted one; the default rule's scores are `dqm evaluate`'s grown row; a looser rule proposes more."""
    from script_modules import load_script

    from dqm.vision import guided

    mod = load_script("truth_chance")
    out = tmp_path / "g.md"
    assert mod.main(["scene:0", "--links", "--out", str(out)]) == 0
    text = out.read_text()
    assert "`python scripts/truth_chance.py scene:0 --links --out" in text
    features = BM.load_benchmark("scene:0", preset="sfm")
    rows = mod.link_rows(features)
    rules = [(r["threshold"], r["max_sigma"]) for r in rows]
    n = len(mod.LINK_RULES)
    assert rules == list(mod.LINK_RULES) + [mod.LINK_RULES[0]] + list(mod.LINK_RULES)
    assert [r["kind"] for r in rows] == ["rectified"] * n + ["rectified, no ring"] + ["clustered"] * n
    rectified, no_ring, clustered = rows[:n], rows[n], rows[n + 1:]
    for kind in (rectified, clustered):
        default, *looser = kind
        assert (default["threshold"], default["max_sigma"]) == (guided.DEFAULT_LINK_THRESHOLD,
                                                                guided.DEFAULT_MAX_SIGMA)
        assert default["planar_pairs"] > 0 and default["links"] > 4 * max(default["chance"], 1)
        assert looser[-1]["links"] > default["links"]
    # rectified, the default rule proposes more links under the true geometry than the clustered descriptors;
    # its ring adds links under the true geometry and hardly any by chance
    assert no_ring["links"] > clustered[0]["links"]
    assert rectified[0]["links"] > no_ring["links"]
    assert rectified[0]["chance"] - no_ring["chance"] < 0.1 * (rectified[0]["links"] - no_ring["links"])
    assert no_ring["scores"] is None
    grown = BM.evaluate(features, ["quickmatch-guided"], curves=False)[0].scores
    assert rectified[0]["scores"].f1 == grown.f1  # dqm evaluate's grown row compares rectified, with the ring
    assert f"| scene:0 | rectified | 2, 1.5 | {rows[0]['planar_pairs']} | {rows[0]['links']:,} |" in text
    assert f"| scene:0 | rectified, no ring | 2, 1.5 | {no_ring['planar_pairs']} | {no_ring['links']:,} |" in text


def test_truth_chance_script_counts_the_truths_coincidences_beside_dqm_match(tmp_path, capsys):
    """scripts/truth_chance.py (docs/match-defaults/truth-chance.md, issue 61) on a generated scene: the truth's
    pairs, those chance alone gives (fewer), bounds on the real ones within the truth, and dqm match's
    clusters' scores, which are the grown row of `dqm evaluate` on the same features."""
    from script_modules import load_script

    mod = load_script("truth_chance")
    out = tmp_path / "t.md"
    assert mod.main(["scene:0", "--fit", "--out", str(out)]) == 0
    features = BM.load_benchmark("scene:0", preset="sfm")  # the script's default preset, dqm match's
    c = mod.chance_rows(features)
    assert 0 < c["chance"] < c["truth"] and c["chance"] > 0.02 * c["truth"]
    assert 0 <= c["real_lo"] <= c["real_hi"] <= c["truth"]
    grown = BM.evaluate(features, ["quickmatch-guided"], curves=False)[0].scores
    text = out.read_text()
    assert "`python scripts/truth_chance.py scene:0 --fit --out" in text
    row = next(line for line in text.splitlines() if line.startswith("| scene:0 |"))
    assert f"{c['truth']:,}" in row and f"{grown.precision:.3f} / {grown.f1:.3f}" in row
    # --fit: the generated scene's truth is exact, so no image pair is listed ...
    assert "| scene:0 | none of " in text
    labels = BM.grown_labels(features)
    exact = {r["pair"]: r for r in mod.fit_rows(features, labels)}
    assert len(exact) >= 3 and all(r["beyond"] < 0.2 and r["truth_median"] < 2 for r in exact.values())
    # ... and a truth whose last image is 8 px off lists every pair with that image, whose fitted homographies
    # still agree with their compositions through the other images
    last = features.n_images - 1
    shift = np.array([[1.0, 0, 8], [0, 1, 0], [0, 0, 1]])
    true_h = features.homography

    def off_by_8px(i, j):
        H = true_h(i, j)
        return shift @ H if j == last else H @ np.linalg.inv(shift) if i == last else H

    wrong = dataclasses.replace(features, homography=off_by_8px, _truth=None)
    listed = {r["pair"]: r for r in mod.fit_rows(wrong, labels) if r["beyond"] > 0.2}
    assert set(listed) == {pair for pair in exact if last in pair} != set()
    assert all(r["chain_median"] < 1 and r["truth_median"] > 5 for r in listed.values())
