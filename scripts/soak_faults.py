#!/usr/bin/env python
"""Soak test of the runtime's fault handling: kill agent processes at random moments.

Each run starts a job with ``dqm.runtime.launcher.run_job`` on generated SIFT-like
data (3 or 4 agents, the balanced mode), and SIGKILLs one agent process at a random
moment of the job (sometimes two, at two moments). Every run must either complete
with labels identical to the in-process simulator, or -- when more processes were
lost than the job may lose (``--max-lost``, default half of them) -- fail cleanly:
a paragraph naming what failed, within 10 s of the kill that broke the limit. It
reports: runs, completed identical, clean failures, hangs (must be 0) and processes
left behind (must be 0).

    python scripts/soak_faults.py                       # 50 runs -> ./dqm-out/soak_faults/
    python scripts/soak_faults.py --runs 5 --budget 120 # the small version CI runs
    python scripts/soak_faults.py --out docs            # also the summary block in docs/runtime.md
"""
import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dqm.distributed import DQMConfig, simulate  # noqa: E402
from dqm.runtime.coordinator import default_max_lost  # noqa: E402
from dqm.runtime.launcher import JobFailure, run_job  # noqa: E402
from dqm.runtime.lifeline import launched_by  # noqa: E402
from dqm.runtime.limits import RuntimeLimits  # noqa: E402
from dqm.synthetic import sift_like  # noqa: E402

BLOCK = ("<!-- soak: written by scripts/soak_faults.py --out docs -->", "<!-- /soak -->")
CLEAN_FAILURE_S = 10.0


def watch_ready(port: int, job: str, m: int, ready: threading.Event, deadline_s: float = 60.0) -> None:
    """Set ``ready`` once every agent process has sent the coordinator its ``ready`` (the job has started)."""
    from dqm.distributed import keys, messages
    from dqm.runtime.bus import open_client

    session = open_client(f"tcp/127.0.0.1:{port}")
    seen = set()

    def on_sample(sample):
        try:
            msg = messages.decode(bytes(sample.payload.to_bytes()), job=job)
        except messages.MessageError:
            return
        if msg["kind"] == "ready":
            seen.add(msg["src"])
            if len(seen) == m:
                ready.set()

    sub = session.declare_subscriber(keys.process_inbox(job, -1), on_sample)
    try:
        ready.wait(deadline_s)
    finally:
        sub.undeclare()
        session.close()


def one_run(k: int, rng: np.random.Generator, X, ids, sims, job_s: dict, timeout_s: float) -> dict:
    m = int(rng.choice([3, 4]))
    cfg = DQMConfig(agents=m, seed=int(rng.integers(1, 1000)), job=f"soak-{os.getpid()}-{k}")
    kills = 2 if rng.random() < 0.3 else 1
    victims = [int(v) for v in rng.choice(m, size=kills, replace=False)]
    # a moment inside the job: from the moment every agent process reported ready to the end of an
    # undisturbed job's run
    moments = sorted(float(rng.uniform(0.0, job_s[m])) for _ in victims)
    started, outcome = {}, {}
    ready = threading.Event()

    def on_started(info):
        started.update(info)
        threading.Thread(target=watch_ready, args=(info["port"], cfg.job, m, ready), daemon=True).start()

    def go():
        try:
            outcome["report"] = run_job(X, ids, cfg, RuntimeLimits(job_timeout_s=timeout_s, ready_timeout_s=15),
                                        on_started=on_started)
        except JobFailure as exc:
            outcome["failure"] = exc
        except Exception as exc:  # noqa: BLE001 - a crash of the launcher is a finding, not a soak crash
            outcome["crash"] = f"{type(exc).__name__}: {exc}"
        outcome["t_end"] = time.monotonic()

    th = threading.Thread(target=go, daemon=True)
    th.start()
    if not ready.wait(60):
        raise RuntimeError("the job never started")
    t0 = time.monotonic()
    killed = []
    for v, at in zip(victims, moments):
        time.sleep(max(0.0, t0 + at - time.monotonic()))
        p = started["agents"][v]
        if p.poll() is None:
            p.kill()
            killed.append((v, time.monotonic()))
    th.join(timeout_s + 60)
    hang = th.is_alive()
    time.sleep(0.5)
    left = launched_by(os.getpid())
    row = {"run": k, "agents": m, "victims": victims, "moments_s": [round(x, 2) for x in moments],
           "killed": [v for v, _ in killed], "hang": hang, "left": len(left)}
    limit = default_max_lost(m)
    if hang:
        row["outcome"] = "hang"
    elif "report" in outcome:
        rep = outcome["report"]
        same = np.array_equal(np.asarray(rep["labels"]), sims[(m, cfg.seed)])
        row.update(outcome="completed identical" if same else "completed DIFFERENT", epochs=rep["epochs"],
                   lost=[x["process"] for x in rep["lost"]], recovery=[x.get("recovery") for x in rep["lost"]],
                   wall_s=round(outcome["t_end"] - t0, 2))
    elif "failure" in outcome:
        exc = outcome["failure"]
        # the kill that broke the limit is the (limit+1)-th one
        broke = killed[limit][1] if len(killed) > limit else None
        took = outcome["t_end"] - broke if broke is not None else None
        clean = (broke is not None and took <= CLEAN_FAILURE_S and str(exc).startswith("The distributed job failed")
                 and "Traceback" not in str(exc))
        row.update(outcome="clean failure" if clean else "unclean failure", seconds_to_fail=round(took, 2)
                   if took is not None else None, paragraph=str(exc)[:300])
    else:
        row.update(outcome="crash", error=outcome.get("crash"))
    for p in left:  # never leave anything behind, even when the soak finds a fault
        try:
            os.kill(p, 9)
        except ProcessLookupError:
            pass
    return row


def summary_table(rows, args, took) -> str:
    count = lambda name: sum(r["outcome"] == name for r in rows)  # noqa: E731
    fails = [r["seconds_to_fail"] for r in rows if r["outcome"] == "clean failure"]
    two = [r for r in rows if len(r["killed"]) == 2]
    lines = [
        f"`python scripts/soak_faults.py --runs {args.runs}` ({len(rows)} runs in {took:.0f} s; generated data, "
        f"{args.images} images x {args.points} points, 3 or 4 agents, balanced mode, one SIGKILL per run at a random "
        f"moment, two in {len(two)} runs):",
        "",
        "| runs | completed identical | clean failures | completed different | unclean failures | hangs | "
        "processes left behind |",
        "|---|---|---|---|---|---|---|",
        f"| {len(rows)} | {count('completed identical')} | {count('clean failure')} | {count('completed DIFFERENT')} | "
        f"{count('unclean failure') + count('crash')} | {count('hang')} | {sum(r['left'] for r in rows)} |",
    ]
    restarted = [r for r in rows if r.get("epochs", 1) > 1]
    taken = [r for r in rows if "takeover" in r.get("recovery", [])]
    lines.append("")
    lines.append(f"Runs recovered by a takeover (the lost agents run again at a survivor, the others keep their work): "
                 f"{len(taken)}; runs that restarted at a new epoch (a loss before the job ran): {len(restarted)} (the "
                 "others were killed after delivering their results, or after the job ended). "
                 + (f"Clean failures failed {min(fails):.1f}-{max(fails):.1f} s after the kill that broke the "
                    "limit." if fails else ""))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--budget", type=float, default=1800.0, help="stop starting runs after this many seconds")
    ap.add_argument("--images", type=int, default=8)
    ap.add_argument("--points", type=int, default=700)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="dqm-out/soak_faults", help="output folder ('docs': also docs/runtime.md)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ds = sift_like(n_images=args.images, n_points=args.points, clutter_per_image=60, noise=0.3, seed=args.seed)
    X, ids = ds.descriptors, ds.image_ids
    t_all = time.monotonic()
    # how long an undisturbed job takes, per agent count (kill moments are drawn inside it)
    job_s = {}
    for m in (3, 4):
        rep = run_job(X, ids, DQMConfig(agents=m, seed=1, job=f"soak-{os.getpid()}-base{m}"),
                      RuntimeLimits(job_timeout_s=120))
        job_s[m] = rep["time_run_s"]
    print(f"undisturbed job, from start to results: {job_s[3]:.1f} s (3 agents), {job_s[4]:.1f} s (4 agents)",
          flush=True)
    sims = {}
    rows = []
    for k in range(args.runs):
        if time.monotonic() - t_all > args.budget:
            print(f"time budget of {args.budget:.0f} s spent after {k} runs", flush=True)
            break
        draws = np.random.default_rng([args.seed, k])  # a run's draws do not depend on earlier runs
        row = one_run(k, draws, X, ids, _Sims(sims, X, ids), job_s, timeout_s=90)
        rows.append(row)
        print(f"run {k:3d}: {row['agents']} agents, killed {row['killed']} at {row['moments_s']} s -> "
              f"{row['outcome']}" + (f" (epochs {row.get('epochs')})" if "epochs" in row else "")
              + (f" ({row.get('seconds_to_fail')} s)" if "seconds_to_fail" in row else "")
              + (f", {row['left']} processes left" if row["left"] else ""), flush=True)
    took = time.monotonic() - t_all
    text = summary_table(rows, args, took)
    print("\n" + text)
    (out / "soak_faults.json").write_text(json.dumps({"rows": rows, "job_s": job_s, "seconds": took}, indent=1))
    (out / "soak_faults.md").write_text("# Fault soak\n\n" + text + "\n")
    if out.resolve() == (ROOT / "docs").resolve():
        doc = ROOT / "docs" / "runtime.md"
        s = doc.read_text()
        if BLOCK[0] in s and BLOCK[1] in s:
            doc.write_text(s[:s.index(BLOCK[0]) + len(BLOCK[0])] + "\n" + text + "\n" + s[s.index(BLOCK[1]):])
    bad = sum(r["outcome"] not in ("completed identical", "clean failure") for r in rows) + sum(r["left"] for r in rows)
    return 1 if bad else 0


class _Sims(dict):
    """Simulator labels per (agents, seed), computed on first use."""

    def __init__(self, cache, X, ids):
        super().__init__()
        self.cache, self.X, self.ids = cache, X, ids

    def __getitem__(self, key):
        if key not in self.cache:
            m, seed = key
            self.cache[key] = simulate(self.X, self.ids, DQMConfig(agents=m, seed=seed)).labels
        return self.cache[key]


if __name__ == "__main__":
    sys.exit(main())
