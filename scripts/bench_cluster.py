#!/usr/bin/env python
"""Benchmark the distributed runtime: M agent processes against the in-process
simulator and centralized QuickMatch, measured in the same run.

For each data set (generated SIFT-like sets of the given sizes; graf SIFT when
../shared is present) and each M: wall time of `dqm run`-style jobs (router +
M agents + coordinator processes, start-up included, and without start-up:
the coordinator's time from start to the last result), the simulator's wall
time, centralized QuickMatch (same finite kernel), bytes per feature, traffic
over raw descriptor bytes, per-phase times of the slowest agent, and whether
the runtime's clusters equal the simulator's. With --secure every job also runs under
mutual TLS and strict access control (`dqm run --secure`: one certificate per process, the
router enforcing the job's roster), right after the plain one, and the table gives the ratio.

    python scripts/bench_cluster.py [--sizes 25000,100000] [--agents 1,2,4,8] [--no-graf] [--mode balanced] [--secure]
"""
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import dqm  # noqa: E402
from dqm import synthetic  # noqa: E402
from dqm.distributed import DQMConfig, simulate  # noqa: E402
from dqm.runtime.launcher import run_job  # noqa: E402
from dqm.runtime.limits import RuntimeLimits  # noqa: E402


def datasets(sizes, graf):
    for n in sizes:
        ds = synthetic.sized(n)
        yield f"synthetic {len(ds)}", ds.descriptors, ds.image_ids
    if graf:
        from dqm.vision import datasets as D
        from dqm.vision import features

        p = ROOT.parent / "shared" / "data" / "oxford" / "graf"
        if p.exists():
            seq = D.load_homography_sequence(p)
            X, ids, _ = features.extract_many(seq.image_paths)
            yield f"graf {len(X)}", X, ids


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="25000,100000")
    ap.add_argument("--agents", default="1,2,4,8")
    ap.add_argument("--no-graf", action="store_true")
    ap.add_argument("--json", help="write raw numbers here")
    ap.add_argument("--mode", default="balanced", help="balanced, lean or paper")
    ap.add_argument("--secure", action="store_true",
                    help="also run every job under mutual TLS + access control and report the ratio")
    args = ap.parse_args(argv)
    rows = []
    for name, X, ids in datasets([int(s) for s in args.sizes.split(",") if s], not args.no_graf):
        t = time.perf_counter()
        dqm.quickmatch(X, ids, kernel="quadratic")  # centralized reference time
        t_central = time.perf_counter() - t
        raw = X.size * X.dtype.itemsize
        for m in [int(a) for a in args.agents.split(",")]:
            cfg = DQMConfig(agents=m, seed=1, mode=args.mode, job=f"bench{m}")
            t = time.perf_counter()
            sim = simulate(X, ids, cfg)
            t_sim = time.perf_counter() - t
            t = time.perf_counter()
            rep = run_job(X, ids, cfg, RuntimeLimits(job_timeout_s=3600))
            t_run = time.perf_counter() - t
            same = bool(np.array_equal(np.asarray(rep["labels"]), sim.labels))
            slowest = max(rep["per_agent"].values(), key=lambda s: s.get("cpu_s", 0))
            phases = {k[5:]: round(v, 2) for k, v in slowest.items() if k.startswith("time_")}
            phases["cpu"] = round(slowest.get("cpu_s", 0.0), 2)
            row = dict(data=name, n=len(X), m=m, central_s=t_central, simulator_s=t_sim, runtime_s=t_run,
                       runtime_job_s=rep["time_run_s"], runtime_startup_s=t_run - rep["time_run_s"],
                       ratio_vs_sim=t_run / t_sim, bytes=rep["total_bytes"],
                       bytes_per_feature=rep["total_bytes"] / len(X),
                       traffic_over_raw=rep["total_bytes"] / raw, wire=rep["wire_bytes_received_by_router"],
                       equal_to_simulator=same, phases_slowest_agent=phases)
            if args.secure:
                t = time.perf_counter()
                sec = run_job(X, ids, cfg, RuntimeLimits(job_timeout_s=3600), secure=True)
                row.update(secure_s=time.perf_counter() - t, secure_job_s=sec["time_run_s"],
                           secure_bytes=sec["total_bytes"], secure_wire=sec["wire_bytes_received_by_router"],
                           secure_equal=bool(np.array_equal(np.asarray(sec["labels"]), sim.labels)))
                row["secure_over_plain"] = row["secure_s"] / t_run
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    secure = ["secure s (job)", "secure / plain", "secure = simulator"] if args.secure else []
    head = ["data", "M", "centralized s", "simulator s", "runtime s (job / start-up)", "runtime / simulator",
            "bytes / feature", "traffic / raw", "= simulator"] + secure
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        extra = (f" {r['secure_s']:.1f} ({r['secure_job_s']:.1f}) | {r['secure_over_plain']:.2f} | "
                 f"{r['secure_equal']} |" if args.secure else "")
        print(f"| {r['data']} | {r['m']} | {r['central_s']:.1f} | {r['simulator_s']:.1f} | {r['runtime_s']:.1f} "
              f"({r['runtime_job_s']:.1f} / {r['runtime_startup_s']:.1f}) | {r['ratio_vs_sim']:.2f} | "
              f"{r['bytes_per_feature']:.0f} | {r['traffic_over_raw']:.2f} | {r['equal_to_simulator']} |" + extra)
    if args.secure:
        ratios = [r["secure_over_plain"] for r in rows]
        jobs = [r["secure_job_s"] / r["runtime_job_s"] for r in rows]
        print(f"\nmutual TLS + access control / plain TCP: whole run {min(ratios):.2f}-{max(ratios):.2f}x "
              f"(median {float(np.median(ratios)):.2f}), job without start-up {min(jobs):.2f}-{max(jobs):.2f}x "
              f"(median {float(np.median(jobs)):.2f})")
    print()
    for r in rows:
        print(f"- {r['data']}, M={r['m']}: slowest agent phases (s) {r['phases_slowest_agent']}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
