"""scripts/dqm_frontier.py at a small size: the table, the figure and the docs block it writes."""
import json
from pathlib import Path

from script_modules import load_script

ROOT = Path(__file__).resolve().parents[1]


def _script():
    return load_script("dqm_frontier")


def test_frontier_script_small(tmp_path, capsys):
    frontier = _script()
    marker_doc = tmp_path / "distributed.md"
    marker_doc.write_text("intro\n<!-- frontier: written by scripts/dqm_frontier.py -->\nold\n"
                          "<!-- /frontier -->\nend\n")
    frontier.main(["--data", "2500", "--agents", "2,4", "--modes", "balanced,two-way,lean,fast", "--out",
                   str(tmp_path)])
    rows = json.loads((tmp_path / "dqm_frontier.json").read_text())
    (key,) = rows
    got = {(r["mode"], r["m"]): r for r in rows[key]["rows"]}
    assert set(got) == {(mode, m) for mode in ("balanced", "two-way", "lean", "fast") for m in (2, 4)}
    for m in (2, 4):
        b = got[("balanced", m)]
        assert b["identical"] and b["f1"] == 1.0 and b["arrival_check_failures"] == 0
        assert b["max_pair_share"] < got[("lean", m)]["max_pair_share"]
        assert got[("two-way", m)]["bytes_over_raw"] > got[("balanced", m)]["bytes_over_raw"]
        assert got[("fast", m)]["bytes_over_raw"] < got[("balanced", m)]["bytes_over_raw"]
        assert got[("fast", m)]["f1"] > 0.98
    assert (tmp_path / "img" / "dqm_frontier.png").stat().st_size > 10_000
    text = (tmp_path / "dqm_frontier.md").read_text()
    assert "| generated" in text and "balanced labels identical at every m: yes" in text
    assert "fast balanced m=2: F1" in text
    doc = marker_doc.read_text()
    assert doc.startswith("intro\n") and doc.endswith("<!-- /frontier -->\nend\n") and "old" not in doc
    assert "| generated" in doc
    # a second run with one mode keeps the other rows
    frontier.main(["--data", "2500", "--agents", "2", "--modes", "lean", "--fresh", "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "dqm_frontier.json").read_text())[key]["rows"]
    assert len(rows) == 8
    capsys.readouterr()
