"""Recovery from a lost agent process: a takeover against a whole-job restart, in the same run.

`dqm run` (one process per agent on this host, balanced mode) on generated features: first a
fault-free run, whose agent 1 timeline (its seconds in each state) says which state agent 1 enters at
25%, 50% and 90% of the job. Then, for each of those moments, the job again with agent 1's process
SIGKILLed when it enters that state, once with the takeover (the default: process 2 runs agent 1
again, the others keep their work) and once with ``--recovery restart`` (every process starts the job
again at the next epoch). Each row: the job's time to result (from every process ready to the labels,
the report's ``time_run_s``; the processes' start-up is the same in every row and left out), the
metered bytes over the fault-free run's, and whether the labels are the fault-free run's.

    python scripts/bench_recovery.py                      # 100k features, M = 8 (the issue's setting)
    python scripts/bench_recovery.py --features 4000 --agents 3 --at 50 --out /tmp/rec

Writes recovery.json and recovery.md to --out (default: the current folder; existing files are kept
unless --force).
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
from dqm.distributed.driver import states_for
from dqm.runtime.launcher import JobFailure, run_job
from dqm.runtime.limits import RuntimeLimits

VICTIM = 1


def timeline(report: dict, agent: int, mode: str):
    """(state, seconds from the job's start when the agent entered it) from its per-state times."""
    st = report["per_agent"][str(agent)]
    t, out = 0.0, []
    for state in states_for(mode):
        out.append((state, t))
        t += float(st.get(f"time_{state}", 0.0))
    return out, t


def pick_states(report: dict, mode: str, fractions):
    """The state agent ``VICTIM`` enters closest to each fraction of its time in the job (never
    ``wait_start``, ``wait_finish``: before go and after its results nothing is redone)."""
    line, total = timeline(report, VICTIM, mode)
    line = [(s, t) for s, t in line if s not in ("wait_start", "wait_finish")]
    return {f: min(line, key=lambda st: abs(st[1] - f * total)) for f in fractions}, total


def run_once(X, ids, cfg, recovery=None, kill_state=None, timeout_s=900.0):
    """One job (killing agent VICTIM's process at ``kill_state``): (report or None, wall seconds, error)."""
    with tempfile.TemporaryDirectory(prefix="dqm-recovery-") as tmp:
        marker = Path(tmp) / "paused"
        env = dict(os.environ)
        if kill_state:
            env.update(DQM_FAULT_PAUSE=f"{VICTIM}:{kill_state}", DQM_FAULT_MARKER=str(marker))
        started = {}

        def killer():
            while not started.get("done"):
                if marker.exists() and "agents" in started:
                    os.kill(started["agents"][VICTIM].pid, signal.SIGKILL)
                    return
                time.sleep(0.01)

        th = threading.Thread(target=killer, daemon=True)
        if kill_state:
            th.start()
        t0 = time.monotonic()
        try:
            limits = RuntimeLimits(job_timeout_s=timeout_s, max_lost=1, recovery=recovery or "takeover")
            rep = run_job(X, ids, cfg, limits, env=env, on_started=started.update)
            err = None
        except JobFailure as exc:
            rep, err = None, str(exc)
        started["done"] = True
        return rep, time.monotonic() - t0, err


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--features", type=int, default=100_000)
    ap.add_argument("--agents", type=int, default=8)
    ap.add_argument("--mode", default="balanced", choices=("balanced", "lean"))
    ap.add_argument("--at", default="25,50,90", help="percentages of the job at which agent 1 is lost")
    ap.add_argument("--out", default=".")
    ap.add_argument("--force", action="store_true", help="overwrite existing recovery.json / recovery.md")
    args = ap.parse_args(argv)
    out = Path(args.out)
    targets = [out / "recovery.json", out / "recovery.md"]
    if not args.force and any(p.exists() for p in targets):
        print(f"error: {', '.join(str(p) for p in targets if p.exists())} exists (pass --force)", file=sys.stderr)
        return 2
    fractions = [int(x) / 100 for x in args.at.split(",")]
    ds = synthetic.sized(args.features)
    X, ids = ds.descriptors, ds.image_ids
    cfg = DQMConfig(agents=args.agents, seed=0, mode=args.mode, job="recovery")
    base, base_s, err = run_once(X, ids, cfg)
    if base is None:
        print(f"error: the fault-free run failed: {err}", file=sys.stderr)
        return 3
    labels = np.asarray(base["labels"])
    picks, agent_s = pick_states(base, args.mode, fractions)
    base_run = base["time_run_s"]
    print(f"fault-free: {base_run:.1f} s to result ({base_s:.1f} s with start-up), {base['total_bytes']} bytes; "
          f"agent {VICTIM} in the job {agent_s:.1f} s", flush=True)
    rows = [{"case": "fault-free", "at": None, "state": None, "recovery": None, "wall_s": base_s, "run_s": base_run,
             "bytes": base["total_bytes"], "time_ratio": 1.0, "bytes_ratio": 1.0, "identical": True, "epochs": 1}]
    for f in fractions:
        state, t_enter = picks[f]
        for recovery in ("takeover", "restart"):
            rep, wall, err = run_once(X, ids, cfg, recovery, state)
            row = {"case": f"lost at {round(f * 100)}%", "at": f, "state": state, "entered_s": t_enter,
                   "recovery": recovery, "wall_s": wall}
            if rep is None:
                row.update(error=err, identical=False)
            else:
                row.update(run_s=rep["time_run_s"], bytes=rep["total_bytes"], time_ratio=rep["time_run_s"] / base_run,
                           bytes_ratio=rep["total_bytes"] /
                           base["total_bytes"], identical=bool(np.array_equal(np.asarray(rep["labels"]), labels)),
                           epochs=rep["epochs"], lost=rep["lost"])
            rows.append(row)
            print(f"lost at {f:.0%} ({state}), {recovery}: {row.get('run_s', float('nan')):.1f} s = "
                  f"{row.get('time_ratio', float('nan')):.2f}x, "
                  f"bytes {row.get('bytes_ratio', float('nan')):.2f}x, labels identical: {row['identical']}",
                  flush=True)
    out.mkdir(parents=True, exist_ok=True)
    summary = {"features": args.features, "agents": args.agents, "mode": args.mode, "cpus": os.cpu_count(),
               "rows": rows}
    targets[0].write_text(json.dumps(summary, indent=1))
    lines = [f"`python scripts/bench_recovery.py --features {args.features} --agents {args.agents}` "
             f"({args.mode}, generated data, {os.cpu_count()} cores, one process per agent on this host; agent "
             f"{VICTIM}'s process SIGKILLed when it enters the state; times are to the result, bytes metered):", "",
             "| lost | state (entered at) | recovery | time to result | x fault-free | bytes x fault-free | "
             "labels = fault-free |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        at = "never" if r["at"] is None else f"{r['at']:.0%}"
        where = "" if r["state"] is None else f"{r['state']} ({r['entered_s']:.1f} s)"
        if "error" in r:
            lines.append(f"| {at} | {where} | {r['recovery']} | failed: {r['error'][:80]} | | | no |")
            continue
        lines.append(f"| {at} | {where} | {r['recovery'] or ''} | {r['run_s']:.1f} s | {r['time_ratio']:.2f} | "
                     f"{r['bytes_ratio']:.2f} | {'yes' if r['identical'] else '**no**'} |")
    targets[1].write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"wrote {targets[0]} and {targets[1]}")
    return 0 if all(r["identical"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
