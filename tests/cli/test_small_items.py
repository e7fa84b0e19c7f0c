"""Issue 21's small items: a change set prints short, doctor checks the colmap extra, data-set
names become safe file names, bench_online --quick gives no verdict on the full-size target, and
dqm evaluate's findings compare QuickMatch with the baselines (never with itself) under a header
whose command line regenerates the run exactly.
"""
import json
import shlex
import sys
from pathlib import Path

import numpy as np
import pytest
from script_modules import load_script

import dqm
from dqm import benchmark, synthetic
from dqm.cli import build_parser, main
from dqm.core.events import ClusterEvent
from dqm.vision import scenes

ROOT = Path(__file__).resolve().parents[2]


# 1. ChangeSet / ClusterEvent print short --------------------------------------------------------

def test_a_large_change_set_prints_a_bounded_summary():
    ds = synthetic.sift_like(n_images=6, n_points=400, clutter_per_image=100, seed=1)
    om = dqm.OnlineQuickMatch(rho=dqm.DEFAULT_RHO)
    for img in range(5):
        m = ds.image_ids == img
        om.add(ds.descriptors[m], ds.image_ids[m])
    m = ds.image_ids == 5
    cs = om.add(ds.descriptors[m], ds.image_ids[m])
    full = json.dumps(cs.to_dict())
    assert len(cs.events) > 100 and len(full) > 20_000  # a real, large add
    for text in (str(cs), repr(cs)):
        assert len(text) < 1000, len(text)
        assert cs.summary() in text and f"{len(cs.events) - 3} more event(s)" in text
        assert str(cs.events[0]) in text
    assert repr(cs).startswith("ChangeSet(") and "\n" not in repr(cs)
    assert str(cs).count("\n") == 4  # summary, three events, "... more"
    counts = cs.counts()
    assert all(f"{v} {k}" in str(cs) for k, v in counts.items() if v)
    # one event over many features stays short too, and names how many there are
    keys = np.arange(50_000)
    e = ClusterEvent("created", 7, keys, keys % 40, new=True)
    assert len(repr(e)) < 250 and "(50000 in all)" in repr(e) and "kind='created'" in repr(e)
    assert len(str(e)) < 250


# 2. doctor: pycolmap and h5py ---------------------------------------------------------------------

def test_doctor_reports_the_colmap_extra_with_versions_and_does_not_require_it(monkeypatch, capsys):
    pycolmap = pytest.importorskip("pycolmap")
    h5py = pytest.importorskip("h5py")
    assert main(["doctor"]) == 0
    lines = capsys.readouterr().out.splitlines()
    line = next(x for x in lines if "pycolmap" in x)
    assert line.startswith("ok") and pycolmap.__version__ in line and "dqm[colmap]" in line
    line = next(x for x in lines if "h5py" in x)
    assert line.startswith("ok") and h5py.__version__ in line
    monkeypatch.setitem(sys.modules, "h5py", None)  # as if not installed
    monkeypatch.setitem(sys.modules, "pycolmap", None)
    assert main(["doctor"]) == 0  # optional: reported, not required
    out = capsys.readouterr().out
    for name in ("pycolmap", "h5py"):
        line = next(x for x in out.splitlines() if name in x)
        assert line.startswith("--") and "not importable" in line
    assert "everything required works" in out


# 3. data-set names as file names ------------------------------------------------------------------

def test_file_stem_is_safe_portable_and_unique():
    assert benchmark.file_stem("scene:3") == "scene-3"
    assert benchmark.file_stem("graf") == "graf"
    assert benchmark.file_stem("my data/set: 2?") == "my-data-set-2"
    assert benchmark.file_stem("..") == "data" and benchmark.file_stem("") == "data"
    assert benchmark.file_stem(".hidden") == "hidden"
    assert benchmark.file_stem("scene:3", taken=["Scene-3"]) == "scene-3-2"
    assert benchmark.file_stem("scene:3", taken=["scene-3", "scene-3-2"]) == "scene-3-3"
    for name in ("a:b", "x/y\\z", "t\tab", "é"):
        stem = benchmark.file_stem(name)
        assert stem and all(c.isascii() and (c.isalnum() or c in "._-") for c in stem), stem


# 4. bench_online --quick ---------------------------------------------------------------------------

def _bench_online():
    return load_script("bench_online")


def test_bench_online_quick_says_the_target_is_for_the_full_size_only(capsys):
    mod = _bench_online()
    ds = synthetic.sift_like(n_images=4, n_points=40, seed=0)
    rows, stored = mod.run("generated", ds.descriptors, ds.image_ids, 1)
    capsys.readouterr()
    quick = mod.summarize("generated", rows, stored, quick=True)
    out = capsys.readouterr().out
    assert "target <= 10% (full size only; --quick is too small to judge)" in out
    assert "MISSED" not in out and ": met" not in out and quick["target"] == mod.QUICK_VERDICT
    full = mod.summarize("generated", rows, stored, quick=False)  # the full run's verdict is unchanged
    out = capsys.readouterr().out
    verdict = "met" if full["mean_add_over_final_batch"] <= 0.10 else "MISSED"
    assert full["target"] == verdict and f"target <= 10%: {verdict}" in out and "full size only" not in out


# 5. evaluation.md: findings and header --------------------------------------------------------------

@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    root = tmp_path_factory.mktemp("findings")
    scenes.generate_scene(3, (240, 320), seed=5).write(root / "my scene")
    argv = ["evaluate", str(root / "my scene"), "--out-dir", str(root / "out"), "--quiet",
            "--methods", "quickmatch,quickmatch-verify,bf,bf-drop-later", "--rhos", "0.5,1",
            "--ratios", "0.6,0.9", "--max-features", "300", "--preset", "opencv"]
    assert main(argv) == 0
    return root, argv


def test_findings_compare_quickmatch_with_the_baselines_and_verification_separately(evaluated):
    root, _ = evaluated
    md = (root / "out" / "evaluation.md").read_text()
    data = json.loads((root / "out" / "evaluation.json").read_text())
    rows = {r["method"]: r for r in data["datasets"]["my scene"]["methods"]}
    findings = md.split("## Where QuickMatch wins and loses")[1].split("## Data")[0]
    bullets = [x for x in findings.splitlines() if x.strip().startswith("- ")]
    assert len(bullets) == 3  # QuickMatch vs baselines, verified vs baselines, what verification changes
    verified = benchmark.METHODS["quickmatch-verify"]
    for line in bullets[:2]:
        # a comparison names a baseline, never a QuickMatch variant, as the other side
        for part in line.split(" vs ")[1:]:
            assert not part.split(")")[0].split(", ", 1)[-1].startswith("QuickMatch"), line
    assert f"loses to {verified}" not in findings and f", {verified})" not in findings
    assert bullets[1].strip().startswith(f"- {verified} ")
    p, v = rows["quickmatch"]["scores"], rows["quickmatch-verify"]["scores"]
    assert (f"precision {p['precision']:.3f} -> {v['precision']:.3f}, recall {p['recall']:.3f} -> "
            f"{v['recall']:.3f}, F1 {p['f1']:.3f} -> {v['f1']:.3f}") in bullets[2]
    base_f1 = max(rows[m]["scores"]["f1"] for m in ("bf", "bf-drop-later"))
    word = ("ties" if round(p["f1"], 3) == round(base_f1, 3) else "**wins**" if p["f1"] > base_f1 else "**loses**")
    assert f"QuickMatch {word} in F1 at the defaults ({p['f1']:.3f} vs {base_f1:.3f}" in bullets[0]
    # the verified row has one operating point: no best-threshold F1, no PR AUC in the table
    vrow = next(x for x in md.splitlines() if x.startswith("|  | " + verified))
    assert vrow.split(" | ")[6:8] == ["-", "-"]


def test_equal_shown_values_are_a_tie_not_a_win():
    assert benchmark._word(0.9694, 0.9690) == "ties"  # hotel's old "win" within 0.001
    assert benchmark._word(0.2803, 0.2801) == "ties"
    assert benchmark._word(0.612, 0.597) == "**wins**" and benchmark._word(0.486, 0.499) == "**loses**"


def test_header_states_the_settings_and_the_command_that_regenerates_it(evaluated):
    root, argv = evaluated
    md = (root / "out" / "evaluation.md").read_text()
    cmd = md.split("Generated by `", 1)[1].split("`", 1)[0]
    words = shlex.split(cmd)
    assert words[:2] == ["dqm", "evaluate"]
    parser = build_parser()
    again, original = vars(parser.parse_args(words[1:])), vars(parser.parse_args(argv))
    again.pop("_run"), original.pop("_run")
    assert again == original  # every non-default option, nothing else
    assert "--rho " not in cmd and "--tol" not in cmd  # defaults are not spelled out
    settings = md.split("## Settings")[1].split("## Results")[0]
    assert ("Methods (rows, in this order): QuickMatch; QuickMatch, geometrically verified; BF pairs; "
            "BF tracks, drop later (Theia).") in settings
    assert "preset `opencv` (OpenCV's default detector parameters, plain SIFT descriptors)" in settings
    assert "max features per image: 300" in settings and "rho 0.9 (the default)" in settings
    assert f"{benchmark.METHODS['quickmatch-verify']}: the QuickMatch clusters at rho 0.9" in settings
    assert "FLANN kd-trees" in settings  # BF / FLANN settings shown: baselines ran
    # file names from the data-set name: one rule (a space in the folder name)
    assert (root / "out" / "pr_my-scene.png").exists() and "(pr_my-scene.png)" in md
    assert main(["plot", "pr", str(root / "out" / "evaluation.json"), "--out-dir", str(root / "again")]) == 0
    assert [f.name for f in (root / "again").iterdir()] == ["pr_my-scene.png"]
