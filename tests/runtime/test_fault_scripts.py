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


def test_recovery_bench_small(tmp_path):
    """scripts/bench_recovery.py at a small size: a takeover and a restart after agent 1's process is
    killed in the ghost round, both with the fault-free labels, and the takeover sends fewer bytes."""
    rc = load("bench_recovery").main(["--features", "2000", "--agents", "2", "--states", "wait_ghost",
                                      "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "recovery.json").read_text())["rows"]
    assert rc == 0 and [r["recovery"] for r in rows] == ["", "takeover", "restart"]
    assert all(r["identical"] for r in rows)
    took, again = rows[1], rows[2]
    assert [x["recovery"] for x in took["lost"]] == ["takeover"] and took["epochs"] == 1
    assert [x["recovery"] for x in again["lost"]] == ["restart"] and again["epochs"] == 2
    assert took["bytes"] < again["bytes"]
    md = (tmp_path / "recovery.md").read_text()
    assert "| state wait_ghost |" in md and "| takeover |" in md and "| restart |" in md
    # it keeps what exists unless told
    assert load("bench_recovery").main(["--features", "2000", "--agents", "2", "--out", str(tmp_path)]) == 2
