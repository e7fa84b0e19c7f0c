"""Small versions of the fault soak and the message fuzzer (the full ones: scripts/soak_faults.py,
scripts/fuzz_messages.py)."""
import json
from pathlib import Path

import pytest
from script_modules import load_script

pytest.importorskip("zenoh")
ROOT = Path(__file__).resolve().parents[2]


def load(name):
    return load_script(name)


def test_soak_small(tmp_path):
    rc = load("soak_faults").main(["--runs", "1", "--images", "5", "--points", "300", "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "soak_faults.json").read_text())["rows"]
    assert len(rows) == 1
    assert all(r["outcome"] in ("completed identical", "clean failure") for r in rows), rows
    assert sum(r["left"] for r in rows) == 0 and not any(r["hang"] for r in rows)
    assert rc == 0
    assert "| runs | completed identical |" in (tmp_path / "soak_faults.md").read_text()


def test_fuzz_small(tmp_path):
    rc = load("fuzz_messages").main(["--messages", "400", "--out", str(tmp_path)])
    s = json.loads((tmp_path / "fuzz_messages.json").read_text())
    assert s["messages"] == 400 and s["labels_identical"] and s["crashes"] == 0
    assert s["refused_total"] == s["expected"]["refused"] > 0
    assert s["duplicates"] >= s["expected"]["duplicate"] > 0
    assert any("later epoch" in k for k in s["refused_by_reason"])
    assert any("another-job" in k for k in s["refused_by_reason"])
    assert rc == 0
