"""Recovery from a lost agent process: a takeover against a whole-job restart, in the same run.

`dqm run` (one process per agent on this host, balanced mode) on generated features: first a
fault-free run, which says how long the processes take to start and the job to run. Then, for 25%,
50% and 90% of that run time, the job again with agent 1's process SIGKILLed at that moment after
the processes started, once with the takeover (the default: process 2 runs agent 1 again, the others
keep their work) and once with ``--recovery restart`` (every process starts the job again at the
next epoch); the report says the phase agent 1 was in. Each row: the job's time to result (from
every process ready to the labels, the report's ``time_run_s``; the processes' start-up is the same
in every row and left out), the metered bytes over the fault-free run's, and whether the labels are
the fault-free run's. ``--states`` kills agent 1's process when it enters the states named instead
(the agents' test hook: exact, for small jobs whose few seconds leave no room for timing).

    python scripts/bench_recovery.py --docs               # 100k features, M = 8 (the issue's setting)
    python scripts/bench_recovery.py --features 3000 --agents 3 --states wait_ghost --out /tmp/rec

Writes recovery.json and recovery.md to --out (default: the current folder; existing files are kept
unless --force); --docs also writes the table into its block of docs/runtime.md.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dqm import synthetic
from dqm.distributed import DQMConfig
from dqm.runtime.launcher import JobFailure, run_job
from dqm.runtime.limits import RuntimeLimits

VICTIM = 1


def run_once(X, ids, cfg, recovery=None, kill_after_s=None, kill_state=None, timeout_s=900.0):
    """One job, SIGKILLing agent VICTIM's process ``kill_after_s`` after the processes were started, or when its
    agent enters ``kill_state`` (the agents' test hook): (report or None, seconds from the processes' start to
    the report, error)."""
    started, done = {}, threading.Event()
    env = dict(os.environ)
    marker = Path(tempfile.mkdtemp(prefix="dqm-recovery-")) / "paused"
    if kill_state:
        env.update(DQM_FAULT_PAUSE=f"{VICTIM}:{kill_state}", DQM_FAULT_MARKER=str(marker))

    def killer():
        while "agents" not in started and not done.is_set():
            time.sleep(0.005)
        if kill_state:
            while not marker.exists():
                if done.wait(0.005):
                    return
        elif done.wait(max(0.0, kill_after_s - (time.monotonic() - started["t"]))):
            return
        os.kill(started["agents"][VICTIM].pid, signal.SIGKILL)

    def on_started(procs):
        started.update(procs, t=time.monotonic())

    if kill_after_s is not None or kill_state:
        threading.Thread(target=killer, daemon=True).start()
    try:
        limits = RuntimeLimits(job_timeout_s=timeout_s, max_lost=1, recovery=recovery or "takeover")
        rep, err = run_job(X, ids, cfg, limits, env=env, on_started=on_started), None
    except JobFailure as exc:
        rep, err = None, str(exc)
    done.set()
    marker.unlink(missing_ok=True)
    marker.parent.rmdir()
    return rep, time.monotonic() - started.get("t", time.monotonic()), err


def _row(rep, err, base, labels, **what) -> dict:
    row = dict(what)
    if rep is None:
        return {**row, "error": err, "identical": False}
    return {**row, "run_s": rep["time_run_s"], "bytes": rep["total_bytes"],
            "time_ratio": rep["time_run_s"] / base["time_run_s"],
            "bytes_ratio": rep["total_bytes"] / base["total_bytes"],
            "identical": bool(np.array_equal(np.asarray(rep["labels"]), labels)), "epochs": rep["epochs"],
            "lost": rep["lost"], "state": rep["lost"][0]["phase"] if rep["lost"] else "(nothing lost)"}


def render(summary: dict) -> str:
    """The markdown table of a run (what recovery.md and the block in docs/runtime.md hold)."""
    lines = [f"`{summary['command']}` ({summary['mode']}, {summary['features']} generated features, M = "
             f"{summary['agents']}, {summary['cpus']} cores, one process per agent on this host; agent {VICTIM}'s "
             "process SIGKILLed that far into the fault-free run's time, or when its agent enters the state; times "
             "are the job's run to the result, bytes metered):", "",
             "| lost at | agent 1's phase | recovery | time to result | x fault-free | bytes x fault-free | "
             "labels = fault-free |", "|---|---|---|---|---|---|---|"]
    for r in summary["rows"]:
        at, where = r["at"], r.get("state", "")
        if "error" in r:
            lines.append(f"| {at} | {where} | {r['recovery']} | failed: {r['error'][:80]} | | | no |")
            continue
        lines.append(f"| {at} | {where} | {r['recovery']} | {r['run_s']:.1f} s | {r['time_ratio']:.2f} | "
                     f"{r['bytes_ratio']:.2f} | {'yes' if r['identical'] else '**no**'} |")
    return "\n".join(lines) + "\n"


DOC = Path(__file__).resolve().parents[1] / "docs" / "runtime.md"
BLOCK = ("<!-- recovery: written by scripts/bench_recovery.py --docs -->", "<!-- /recovery -->")


def write_docs(text: str) -> None:
    """Put ``text`` between the markers of docs/runtime.md."""
    s = DOC.read_text()
    if BLOCK[0] not in s or BLOCK[1] not in s:
        raise SystemExit(f"error: {DOC} has no block {BLOCK[0]} ... {BLOCK[1]}")
    DOC.write_text(s[:s.index(BLOCK[0]) + len(BLOCK[0])] + "\n" + text + s[s.index(BLOCK[1]):])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--features", type=int, default=100_000)
    ap.add_argument("--agents", type=int, default=8)
    ap.add_argument("--mode", default="balanced", choices=("balanced", "lean"))
    ap.add_argument("--at", default="25,50,90", help="percentages of the job's run time at which agent 1 is lost")
    ap.add_argument("--states", default="", help="or: agent 1's states at which it is lost (comma-separated)")
    ap.add_argument("--out", default=".")
    ap.add_argument("--force", action="store_true", help="overwrite existing recovery.json / recovery.md")
    ap.add_argument("--docs", action="store_true", help="also write the table into docs/runtime.md")
    args = ap.parse_args(argv)
    out = Path(args.out)
    targets = [out / "recovery.json", out / "recovery.md"]
    if not args.force and any(p.exists() for p in targets):
        print(f"error: {', '.join(str(p) for p in targets if p.exists())} exists (pass --force)", file=sys.stderr)
        return 2
    ds = synthetic.sized(args.features)
    X, ids = ds.descriptors, ds.image_ids
    cfg = DQMConfig(agents=args.agents, seed=0, mode=args.mode, job="recovery")
    base, base_s, err = run_once(X, ids, cfg)
    if base is None:
        print(f"error: the fault-free run failed: {err}", file=sys.stderr)
        return 3
    labels = np.asarray(base["labels"])
    base_run = base["time_run_s"]
    print(f"fault-free: {base_run:.1f} s to result ({base_s:.1f} s with the processes' start), "
          f"{base['total_bytes']} bytes", flush=True)
    rows = [{**_row(base, None, base, labels, at="never", recovery="", wall_s=base_s), "state": ""}]
    # the job runs at the end of the processes' time: it starts about (their time - its run time) after them
    cases = ([(f"state {s}", None, s) for s in args.states.split(",") if s] if args.states else
             [(f"{int(p)}% ({int(p) / 100 * base_run:.1f} s)", (base_s - base_run) + int(p) / 100 * base_run, None)
              for p in args.at.split(",")])
    for at, kill_s, state in cases:
        for recovery in ("takeover", "restart"):
            rep, wall, err = run_once(X, ids, cfg, recovery, kill_s, state)
            row = _row(rep, err, base, labels, at=at, recovery=recovery, wall_s=wall)
            rows.append(row)
            print(f"lost at {at} ({row.get('state')}), {recovery}: {row.get('run_s', float('nan')):.1f} s = "
                  f"{row.get('time_ratio', float('nan')):.2f}x, bytes {row.get('bytes_ratio', float('nan')):.2f}x, "
                  f"labels identical: {row['identical']}", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    shown = (["--docs"] if args.docs else []) + [f"--features {args.features}", f"--agents {args.agents}"] + (
        [f"--mode {args.mode}"] if args.mode != "balanced" else []) + (
        [f"--states {args.states}"] if args.states else [f"--at {args.at}"] if args.at != "25,50,90" else [])
    summary = {"features": args.features, "agents": args.agents, "mode": args.mode, "cpus": os.cpu_count(),
               "command": " ".join(["python scripts/bench_recovery.py", *shown]), "rows": rows}
    targets[0].write_text(json.dumps(summary, indent=1))
    text = render(summary)
    targets[1].write_text(text)
    print(text, end="")
    print(f"wrote {targets[0]} and {targets[1]}")
    if args.docs:
        write_docs(text)
        print(f"and its block in {DOC}")
    return 0 if all(r["identical"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
