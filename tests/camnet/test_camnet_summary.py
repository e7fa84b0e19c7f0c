"""The camera-network report's one summary: camnet.json and camnet.md read the same numbers.

A tiny real run (3 cameras, 3 time steps, every method, the parameter sweep, a
second seed; false detections and localizations in it) goes through :func:`dqm.camnet.report.write_report`; the numbers
parsed back out of the markdown must equal the JSON's, and the summary's must
equal the experiment's own scoring functions.
"""
import dataclasses
import json
import math
import re

import numpy as np
import pytest

from dqm.camnet.experiment import detection_curve, localization_errors, operating_point, run_experiment
from dqm.camnet.pipeline import LABELS, METHODS, PAPER_RHO, PipelineConfig
from dqm.camnet.report import markdown, seed_row, write_report
from dqm.camnet.simulator import SimConfig
from dqm.camnet.summary import SeedRow, build_summary

TINY = dict(duration=9.0, rate=0.34, n_cameras=3)
NUM = r"(n/a|-?\d+(?:\.\d+)?)"


@pytest.fixture(scope="module")
def runs():
    pipe = PipelineConfig()
    main = run_experiment(SimConfig(seed=1, **TINY), pipe, METHODS, sweep=True, rhos=(0.75, PAPER_RHO),
                          ratios=(0.7, 0.75))
    other = run_experiment(SimConfig(seed=2, **TINY), pipe, METHODS, sweep=True, rhos=(0.75, PAPER_RHO),
                           ratios=(0.75,), snapshot_step=None)
    return main, [seed_row(main), seed_row(other)]


@pytest.fixture(scope="module")
def report(runs, tmp_path_factory):
    main, rows = runs
    out = tmp_path_factory.mktemp("camnet")
    written = write_report(main, out, command="test", seed_rows=rows)
    return json.loads(written["json"].read_text()), written["markdown"].read_text()


def _agrees(text: str, value: float, digits: int) -> bool:
    """The markdown's ``text`` is ``value`` written with ``digits`` decimals ("n/a": NaN)."""
    if text == "n/a":
        return value is None or math.isnan(value)
    return abs(float(text) - value) <= 0.5 * 10 ** -digits + 1e-9


def _table(md: str, heading_start: str):
    """The data rows (cells) of the first markdown table whose header line starts with ``heading_start``."""
    lines = md.splitlines()
    k = next(i for i, line in enumerate(lines) if line.startswith(heading_start))
    rows = []
    for line in lines[k + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")])
    return rows


def test_results_table_equals_json(report):
    data, md = report
    rows = _table(md, "| method | detection PR AUC |")
    by_label = {d["label"]: d for d in data["methods"].values()}
    assert [r[0] for r in rows] == [d["label"] for d in data["methods"].values()]
    for cells in rows:
        d = by_label[cells[0]]
        assert _agrees(cells[1].strip("*"), d["pr_auc"], 3)
        assert _agrees(cells[1].strip("*"), d["curve"]["auc"], 3)
        p, r, n_det, n_false = re.fullmatch(rf"{NUM} / {NUM} \((\d+) det\., (\d+) false\)", cells[3]).groups()
        op = d["at_rule"]
        assert _agrees(p, op["precision"], 2) and _agrees(r, op["recall"], 2)
        assert (int(n_det), int(n_false)) == (op["detections"], op["false_positives"])
        mean, std, n = re.fullmatch(rf"\*\*{NUM} \+- {NUM}\*\* \(n=(\d+)\)", cells[4]).groups()
        e = d["errors"]
        assert _agrees(mean, e["mean"], 2) and _agrees(std, e["std"], 2) and int(n) == e["n"]
        mean, std, n = re.fullmatch(rf"{NUM} \+- {NUM} \(n=(\d+)\)", cells[6]).groups()
        assert _agrees(mean, e["mean_tp"], 2) and _agrees(std, e["std_tp"], 2) and int(n) == e["n_tp"]
        assert _agrees(cells[7], e["median"], 2) and int(cells[8]) == e["n_without_estimate"]
        if d["paper"] is None:
            assert cells[2] == cells[5] == "-"
        else:
            assert _agrees(cells[2], d["paper"]["auc"], 2)


def test_sweep_tables_equal_json(report):
    data, md = report
    for m, d in data["methods"].items():
        if "sweep" not in d:
            continue
        sw = d["sweep"]
        rows = _table(md, f"| {LABELS[m]} {sw['parameter']} | PR AUC |")
        assert len(rows) == len(sw["table"]) > 0
        for cells, row in zip(rows, sw["table"]):
            assert float(cells[0].split(" ")[0]) == pytest.approx(row[sw["parameter"]])
            for text, key, nd in zip(cells[1:], ("auc", "precision", "recall", "mean_score_positive",
                                                 "mean_score_negative"), (3, 2, 2, 1, 1)):
                assert _agrees(text, row[key], nd), (m, key)


def test_online_section_equals_json(report):
    data, md = report
    vs = data["online"]["vs_batch_quadratic"]
    m = re.search(r"is the same in (\d+) of (\d+) frames \((\d+) of the (\d+) frames of the last camera.*?"
                  rf"online is higher in (\d+), lower in (\d+) \(mean \|difference\| {NUM}, at most (\d+)\); "
                  r"the detection at >= \d+ differs in (\d+) frames", md)
    got = m.groups()
    keys = ("same_score", "frames", "same_score_last_camera", "last_camera_frames", "online_higher", "online_lower")
    assert [int(g) for g in got[:6]] == [vs[k] for k in keys]
    assert _agrees(got[6], vs["mean_abs_score_difference"], 2)
    assert int(got[7]) == vs["max_abs_score_difference"] and int(got[8]) == vs["detection_differs"]
    on = data["online"]
    m = re.search(rf"takes {NUM} ms, {NUM} of a batch run .*? costs {NUM}x batch per step", md)
    assert _agrees(m.group(1), 1e3 * on["update_mean_s"], 1)
    assert _agrees(m.group(2), on["update_over_batch"], 2) and _agrees(m.group(3), on["online_over_batch"], 1)
    assert on["update_over_batch"] == pytest.approx(on["update_mean_s"] / on["batch_per_step_s"][
        "quickmatch-quadratic"])


def test_seeds_table_equals_json(report):
    data, md = report
    rows = _table(md, "| seed | frames (target visible) |")
    methods = list(data["methods"])
    assert len(rows) == len(data["seeds"]) + 1  # + the mean
    for cells, seed in zip(rows, data["seeds"]):
        assert int(cells[0]) == seed["seed"] and cells[1] == f"{seed['frames']} ({seed['positives']})"
        for k, m in enumerate(methods):
            assert _agrees(cells[2 + k], seed["auc"][m], 3)
        assert _agrees(cells[2 + len(methods)], seed["auc_quickmatch_paper_rho"], 3)
        assert _agrees(cells[3 + len(methods)], seed["auc_quickmatch_per_camera"], 3)
    mean = data["seeds_mean"]
    for k, m in enumerate(methods):
        assert _agrees(rows[-1][2 + k], mean["auc"][m], 3)
        assert mean["auc"][m] == pytest.approx(np.mean([s["auc"][m] for s in data["seeds"]]))


def test_comparison_equals_json(report):
    data, md = report
    c = data["comparison_with_paper"]
    for m, f in c["false_detections"].items():
        got = re.search(rf"{LABELS[m]} (\d+) \((\d+) with the decoy in view, (\d+) with less than \d+ px of the "
                        r"target in view, (\d+) on the scene's own texture\)", md).groups()
        assert [int(g) for g in got] == [f["total"], f["decoy"], f["partial"], f["scene"]]
        assert f["total"] == data["methods"][m]["at_rule"]["false_positives"]
        assert f["decoy"] + f["partial"] + f["scene"] == f["total"]
    for m, e in c["large_errors"].items():
        got = re.search(rf"{LABELS[m]} (\d+) \((\d+) of them false detections\)", md).groups()
        assert [int(g) for g in got] == [e["n"], e["n_false"]] and e["n"] <= data["methods"][m]["errors"]["n"]
    pct = re.search(rf"measured within {NUM}% of its ideal value", md).group(1)
    assert _agrees(pct, c["calibration_error_pct"], 1)
    rho = c["rho"]
    assert _agrees(re.search(rf"QuickMatch's AUC is {NUM}, ", md).group(1), rho["paper"]["auc"], 3)
    table = {r["rho"]: r for r in data["methods"]["quickmatch"]["sweep"]["table"]}
    assert rho["paper"]["auc"] == table[PAPER_RHO]["auc"]
    wins = re.search(r"QuickMatch has the highest AUC in (\d+)\.", md).group(1)
    assert int(wins) == c["seeds_quickmatch_highest"] == sum(
        all(s["auc"]["quickmatch"] >= s["auc"][m] for m in ("bf", "flann")) for s in data["seeds"])


def test_summary_equals_the_experiments_scores(runs):
    main, rows = runs
    s = build_summary(main, rows)
    assert s.method_names == main.methods
    for m, d in s.methods.items():
        assert d.pr_auc == detection_curve(main, m).auc()
        assert dataclasses.asdict(d.at_rule) == operating_point(main, m)
        e = localization_errors(main, m)
        assert d.errors.n == len(e.errors) and (d.errors.mean == e.mean or math.isnan(e.mean))
    assert [SeedRow.from_json(r) for r in rows] == list(s.seeds.rows)
    assert SeedRow.from_json(rows[0]) == SeedRow.of(main)
    json.dumps(s.as_json())  # plain data


def test_markdown_reads_only_the_summary(runs):
    """Change a number in the summary: the markdown shows the changed number, in every place it appears."""
    main, rows = runs
    s = build_summary(main, rows)
    bf = dataclasses.replace(s.methods["bf"], pr_auc=0.123456)
    changed = dataclasses.replace(s, methods={**s.methods, "bf": bf})
    md = markdown(changed, {}, "test")
    assert f"| {bf.label} | **0.123** |" in md
    assert "BF 0.123, FLANN" in md and "BF vs FLANN: 0.123 vs" in md
    assert f"| {bf.label} | **{s.methods['bf'].pr_auc:.3f}** |" in markdown(s, {}, "test")
