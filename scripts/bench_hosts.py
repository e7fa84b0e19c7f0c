#!/usr/bin/env python3
"""Time to result on emulated hosts and links: is running dqm across M machines faster than copying
every feature to one machine and matching there?

Each of M hosts is a network namespace in a cgroup-v1 CPU quota (2 cores / M each, so that the M
hosts share this machine's two cores as M small machines would), joined to a router namespace by a
veth capped with `tc tbf` at each link rate (`dqm.runtime.multihost.EmulatedHosts`). Source a's
features (whole images, image k -> source k mod M) start on host a. Modes, run one after the other
on the same hosts (`dqm.runtime.multihost.run_on_hosts`; with `--repeats N`, N rounds of them in turn, each
row the run of median time):

* gather: every source sends its features to host 0 (zenoh, through the router), which runs
  centralized QuickMatch (quadratic kernel, the same clusters as balanced) in the same CPU quota
  as one agent host;
* gather-approx: the same with approximate QuickMatch (faiss);
* lean, balanced: `dqm agent` on every host, the coordinator on host 0;
* auto: the same processes with `--mode auto`: the coordinator picks gather (every other agent's features to
  agent 0, which matches them with its own), lean or balanced with dqm.distributed.costmodel at this
  machine's measured pair rate, timing its link to every host only where the links can change the
  answer, and runs it. Its rows say what it picked and its time over the best
  of gather, lean and balanced in the same run ("auto / best").

Time to result: from starting the processes (Python start-up in the quota included, for every
mode) to the exit of the process that writes the labels (dqm run's coordinator, the gathering host's
process; the other processes' exits after it are not waited for, in any mode). Reported with the
bytes moved and the speed-up over gather at each rate; every row's labels are compared with gather's
(identical, or co-membership F1 for lean and approx).

    sudo .venv/bin/python scripts/bench_hosts.py --data graf --agents 2,4,8 --rates 1000,100,10
    sudo .venv/bin/python scripts/bench_hosts.py --data 100000 --agents 8 --json docs/bench_hosts.json

Needs root (network namespaces, cgroups, tc). Exit code 0: done; 2: cannot run here.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dqm import InputError, evaluation, outputs, synthetic  # noqa: E402
from dqm.core import inverted_lists  # noqa: E402
from dqm.core.pairs import pair_cpu_s_here  # noqa: E402
from dqm.distributed import DQMConfig  # noqa: E402
from dqm.distributed.config import DISTRIBUTED_ENGINES  # noqa: E402
from dqm.runtime.launcher import Processes, work_folder, write_agent_files  # noqa: E402
from dqm.runtime.multihost import (  # noqa: E402
    HOST_MODES,
    ROUTER_PORT,
    EmulatedHosts,
    NamespacesUnavailable,
    _wait_ready_file,
    netns_unavailable_reason,
    run_on_hosts,
    start_router,
)


def load(name: str):
    if name in ("graf", "wall", "boat", "bikes"):
        from dqm.vision import datasets, features

        path = ROOT.parent / "shared" / "data" / "oxford" / name
        if not path.exists():
            print(f"skipping {name}: {path} is absent", file=sys.stderr)
            return None
        seq = datasets.load_homography_sequence(path)
        X, ids, _ = features.extract_many(seq.image_paths)
        return f"{name} ({len(X)})", X, ids
    ds = synthetic.sized(int(name))
    return f"generated {len(ds)}", ds.descriptors, ds.image_ids


def agreement(run, ref) -> dict:
    assert np.array_equal(run.ids, ref.ids), "the runs cover different features"
    same = bool(np.array_equal(_canonical(run.labels), _canonical(ref.labels)))
    f1 = 1.0 if same else evaluation.comembership_scores(run.labels, ref.labels).f1
    return {"identical": same, "f1": f1}


def _canonical(labels: np.ndarray) -> np.ndarray:
    _, first, inv = np.unique(labels, return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))
    return order[inv]


def bench(name, X, ids, m: int, rates, modes, workdir: Path, timeout_s: float, log, rows: list, save,
          repeats: int = 1, engine: str = "exact") -> list:
    """Run every mode at every rate on M emulated hosts, ``repeats`` times in turn (the first round in the
    order given, gather first; each later round starts one mode further on, so that no mode always runs
    first or after the same one). Each mode's row is its run of median time so far (of an even count, the
    lower of the two middle ones), with every run's time in ``runs_s``. Keeps ``rows`` up to date and calls
    ``save()`` after each run (a long benchmark keeps what it measured). A mode whose run fails is a row
    with its ``error`` (and is not run again at that rate)."""
    workdir.mkdir(parents=True, exist_ok=True)
    files = write_agent_files(X, ids, m, workdir)
    raw = X.size * X.dtype.itemsize
    cpu = 2.0 / m
    cfg = DQMConfig(agents=m, seed=1, job=f"hosts{m}", engine=engine).validated(len(X))
    # this machine's all-pairs kernel: scripts/fit_costmodel.py scales each row's pair work by it
    kernel = pair_cpu_s_here(X.shape[1], X.dtype)

    def rate_rows(rate, runs: dict, failed: dict) -> list:
        """The rows of one rate from the runs so far: one per mode that ran or failed, in ``modes``' order."""
        median = {mode: sorted(rs, key=lambda r: r.seconds)[(len(rs) - 1) // 2] for mode, rs in runs.items() if rs}
        ref = median.get("gather")
        out = []
        for mode in [mode for mode in modes if mode in failed or mode in median]:
            # cell_share: the share of a cell's pairs fast balanced computes here (its lists where they pay),
            # which scripts/fit_costmodel.py reads
            row = {"data": name, "n": int(len(X)), "m": m, "rate_mbit": rate, "cpu_per_host": cpu,
                   "mode": mode, "engine": engine, "kernel_cpu_s": kernel,
                   "cell_share": inverted_lists.cell_pairs_share(len(X) // m)}
            if mode in failed:
                row.update(error=failed[mode][0], seconds=failed[mode][1])
            else:
                r = median[mode]
                row.update(seconds=r.seconds, bytes=r.bytes, bytes_over_raw=r.bytes / raw, **r.detail)
                if repeats > 1:
                    row["runs_s"] = [x.seconds for x in runs[mode]]
                if ref is not None:
                    row.update(agreement(r, ref), speedup_over_gather=ref.seconds / r.seconds)
            out.append(row)
        return out

    for rate in rates:
        base = len(rows)
        with EmulatedHosts(hosts=m, rate_mbit=rate, cpu_cores=cpu) as nss:
            procs = Processes()
            runs: dict = {mode: [] for mode in modes}
            failed: dict = {}
            try:
                endpoints = [f"tcp/{nss.router_addr(h)}:{ROUTER_PORT}" for h in range(m)]
                start_router(procs, endpoints, workdir, _wait_ready_file, prefix=nss.prefix(nss.router_ns))
                for k in range(repeats):
                    for mode in modes[k % len(modes):] + modes[:k % len(modes)]:
                        if mode in failed:
                            continue
                        t = time.perf_counter()
                        try:
                            r = run_on_hosts(nss, mode, cfg, files, workdir, timeout_s=timeout_s)
                        except RuntimeError as exc:  # JobFailure included: the row says why
                            failed[mode] = (str(exc).split("\n")[0], time.perf_counter() - t)
                            log(f"{name} M={m} {rate:g} Mbit/s {mode}: FAILED after {failed[mode][1]:.1f} s: "
                                f"{failed[mode][0]}")
                        else:
                            runs[mode].append(r)
                            picked = f" (picked {r.detail['picked']})" if "picked" in r.detail else ""
                            log(f"{name} M={m} {rate:g} Mbit/s {mode}{picked}: {r.seconds:.1f} s, "
                                f"{r.bytes / raw:.2f}x raw ({time.perf_counter() - t:.1f} s)")
                        rows[base:] = rate_rows(rate, runs, failed)
                        save()
            finally:
                procs.stop_all()
    return rows


def after_start_up(r: dict) -> float:
    """Seconds without the processes' start-up: the coordinator's start-to-last-result (lean, balanced),
    the gathering host's time from its own start-up to its labels (gather)."""
    return r["job_s"] if "job_s" in r else r["gather_s"] + r["match_s"]


#: the modes auto picks from: "auto / best" is auto's time over the best of these in the same run
AUTO_PICKS = ("gather", "lean", "balanced")


def auto_over_best(r: dict, rows) -> str:
    """An auto row's time over the best time of gather, lean and balanced at the same data, M and rate
    ("" for other rows, or when none of them ran)."""
    if r["mode"] != "auto" or "error" in r:
        return ""
    same = [o["seconds"] for o in rows if o["mode"] in AUTO_PICKS and "error" not in o
            and (o["data"], o["m"], o["rate_mbit"]) == (r["data"], r["m"], r["rate_mbit"])]
    return f"{r['seconds'] / min(same):.2f}" if same else ""


def table(rows) -> str:
    out = ["| data | M | link Mbit/s | mode | time to result s | speed-up over gather | after start-up s | "
           "speed-up over gather | bytes / raw | labels vs gather | auto picked | auto / best |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    def key(r: dict) -> tuple:
        return r["data"], r["m"], r["rate_mbit"], r.get("engine", "exact")

    def shown(r: dict) -> str:  # the mode, and the engine where it is not the exact one (gather-approx: faiss)
        fast = r.get("engine", "exact") != "exact" and r["mode"] != "gather-approx"
        return r["mode"] + (f" ({r['engine']})" if fast else "")

    ref = {key(r): r for r in rows if r["mode"] == "gather"}
    for r in rows:
        if "error" in r:
            out.append(f"| {r['data']} | {r['m']} | {r['rate_mbit']:g} | {shown(r)} | failed after "
                       f"{r['seconds']:.0f} s: {r['error']} | | | | | | | |")
            continue
        agree = "" if "identical" not in r else ("identical" if r["identical"] else f"F1 {r['f1']:.4f}")
        speed = f"{r['speedup_over_gather']:.2f}" if "speedup_over_gather" in r else ""
        g = ref.get(key(r))
        g = g if g is not None and "error" not in g else None
        warm = f"{after_start_up(g) / after_start_up(r):.2f}" if g else ""
        out.append(f"| {r['data']} | {r['m']} | {r['rate_mbit']:g} | {shown(r)} | {r['seconds']:.1f} | {speed} | "
                   f"{after_start_up(r):.1f} | {warm} | {r['bytes_over_raw']:.2f} | {agree} | {r.get('picked', '')} | "
                   f"{auto_over_best(r, rows)} |")
    return "\n".join(out)


def figure(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if "error" not in r]
    groups = sorted({(r["data"], r["m"]) for r in rows})
    fig, axes = plt.subplots(2, len(groups), figsize=(4.2 * len(groups), 6.6), squeeze=False)
    for col, (data, m) in enumerate(groups):
        for row, (what, get) in enumerate((("time to result (s)", lambda r: r["seconds"]),
                                           ("after start-up (s)", after_start_up))):
            ax = axes[row][col]
            for mode in HOST_MODES:
                pts = sorted((r["rate_mbit"], get(r)) for r in rows
                             if (r["data"], r["m"], r["mode"]) == (data, m, mode))
                if pts:
                    ax.plot(*zip(*pts), marker="o", label=mode)
            ax.set_xscale("log")
            ax.set_xlabel("link rate (Mbit/s)")
            ax.set_ylabel(what)
            ax.set_ylim(bottom=0)
            ax.set_title(f"{data}, M = {m}")
            ax.grid(alpha=0.3)
    axes[0][0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="graf", help="comma-separated: graf, wall, boat, bikes and/or generated sizes")
    ap.add_argument("--agents", default="2,4,8", help="host counts M")
    ap.add_argument("--rates", default="1000,100,10", help="link rates in Mbit/s")
    ap.add_argument("--modes", default=",".join(HOST_MODES), help=f"of {', '.join(HOST_MODES)}; gather first")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds one mode may take")
    ap.add_argument("--repeats", type=int, default=1,
                    help="runs of every mode at every rate, in turn; each row is the run of median time")
    ap.add_argument("--engine", default="exact", choices=DISTRIBUTED_ENGINES,
                    help="every mode's engine (gather's dqm.quickmatch included): rows compare like with like")
    ap.add_argument("--json", help="write the rows here (after every run; an existing file is refused unless "
                                   "--overwrite)")
    ap.add_argument("--figure", help="write the figure (PNG) here (an existing file is refused unless --overwrite)")
    outputs.add_overwrite_option(ap)
    ap.add_argument("--keep", help="keep the work folder (files, logs) here")
    ap.add_argument("--table-from", nargs="+", metavar="JSON",
                    help="print the table (and --figure) of earlier runs' --json files instead of running")
    args = ap.parse_args(argv)
    try:  # before any work: the outputs can be written, and exist only where --overwrite lets them be replaced
        if args.json:
            outputs.check_file(args.json, "--json", [".json"], overwrite=args.overwrite)
        if args.figure:
            outputs.check_file(args.figure, "--figure", [".png"], overwrite=args.overwrite)
    except InputError as exc:
        print(f"bench_hosts: {exc}", file=sys.stderr)
        return 2
    if args.table_from:
        rows = [r for f in args.table_from for r in json.loads(Path(f).read_text())]
        print(table(rows))
        if args.figure and rows:
            save_figure(rows, args.figure)
        return 0
    import signal

    signal.signal(signal.SIGTERM, lambda *a: sys.exit(143))  # unwind: namespaces and cgroups are deleted
    reason = netns_unavailable_reason()
    if reason:
        print(f"bench_hosts: cannot run here: {reason}", file=sys.stderr)
        return 2
    modes = [m for m in args.modes.split(",") if m]
    bad = [m for m in modes if m not in HOST_MODES]
    if bad:
        ap.error(f"unknown mode {bad[0]!r}; the modes are {', '.join(HOST_MODES)}")
    rates = [float(r) for r in args.rates.split(",") if r]
    if args.repeats < 1:
        ap.error(f"--repeats must be at least 1, got {args.repeats}")
    rows = []
    try:
        with work_folder(args.keep, "dqm-hosts-") as wd:
            for name in [d for d in args.data.split(",") if d]:
                data = load(name)
                if data is None:
                    continue
                label, X, ids = data
                for m in [int(a) for a in args.agents.split(",") if a]:
                    bench(label, X, ids, m, rates, modes, wd / f"{name}-{m}", args.timeout,
                          lambda text: print(text, file=sys.stderr, flush=True), rows,
                          lambda: args.json and save_rows(rows, args.json),
                          repeats=args.repeats, engine=args.engine)
    except NamespacesUnavailable as exc:
        print(f"bench_hosts: cannot run here: {exc}", file=sys.stderr)
        return 2
    print(table(rows))
    if args.figure and rows:
        save_figure(rows, args.figure)
    return 0


def save_rows(rows: list, path: str) -> None:
    """The rows as JSON at ``path``, whole: the first write takes the name (checked before any work), later ones
    replace this run's file (:mod:`dqm.outputs` rewrites what the process wrote), so a long benchmark keeps what
    it measured and never replaces another file."""
    try:
        outputs.write_text(path, json.dumps(rows, indent=1))
    except outputs.OutputTaken as exc:  # made meanwhile by another program: left, this run's rows beside it
        print(f"bench_hosts: {exc}", file=sys.stderr, flush=True)


def save_figure(rows: list, path: str) -> None:
    """:func:`figure` written whole under its checked name."""
    with outputs.atomic_output(path) as tmp:
        figure(rows, Path(tmp))


if __name__ == "__main__":
    sys.exit(main())
