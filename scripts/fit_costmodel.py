#!/usr/bin/env python3
"""Fit the constants of dqm.distributed.costmodel to the emulated-host benchmark, and check the model.

Reads the rows of scripts/bench_hosts.py (docs/bench_hosts_graf.json, docs/bench_hosts_100k.json by
default), fits each mechanism's constants by non-negative least squares on the quantities the rows
measured, prints them as the ``CostConstants`` fields to paste into dqm/distributed/costmodel.py, then
for every row the predicted against the measured time to result, and for every (data, M, rate) group
the mode the model picks and whether that mode's measured time is within 10% of the best measured of
gather, lean and balanced. Two picks: as the benchmark ran (every mode's own start-up; the gather of
dqm.runtime.gather, whose gathering host keeps its own features), and as the coordinator of a
``--mode auto`` job picks (processes already started, agent 0 gathers the others' features) against
the measured times after start-up.

    .venv/bin/python scripts/fit_costmodel.py
    .venv/bin/python scripts/fit_costmodel.py --json docs/bench_hosts_graf.json docs/bench_hosts_100k.json
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import fields, replace
from pathlib import Path
from typing import Dict, List

import numpy as np
from scipy.optimize import nnls

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dqm.distributed import DQMConfig, costmodel  # noqa: E402
from dqm.distributed.costmodel import CostConstants, Hosts, JobShape  # noqa: E402

DEFAULT_JSON = [ROOT / "docs" / "bench_hosts_graf.json", ROOT / "docs" / "bench_hosts_100k.json",
                # the fast engine's rows (its constants are fitted on these alone; the exact ones above):
                # a 2-core Intel Xeon with AVX-512 VNNI and a 2-core AMD EPYC with AVX2 only, whose pair kernels
                # differ 10x while the fast engine's other work does not
                ROOT / "docs" / "bench_hosts_100k_fast.json", ROOT / "docs" / "bench_hosts_graf_fast.json",
                ROOT / "docs" / "bench_hosts_100k_engine_auto.json"]
#: the modes auto picks from, as the benchmark names them
MODES = ("gather", "balanced", "lean")
DIM = 128  # every benchmark row: uint8 SIFT


def read_rows(paths) -> List[dict]:
    """The rows of bench_hosts.py's JSON files, each with the index of its file (``file``): rows of one
    invocation are compared with each other only (the files may come from different machines)."""
    return [{**r, "file": k} for k, f in enumerate(paths) for r in json.loads(Path(f).read_text())]


def engine_of(r: dict) -> str:
    """The engine a row ran (``auto`` resolved as the job resolves it, from its features)."""
    e = r.get("engine", "exact")
    return DQMConfig(agents=int(r["m"]), engine=e).engine_for(int(r["n"])) if e == "auto" else e


def shown(mode: str, engine: str) -> str:
    """A mode as the tables show it: with its engine where that is not the exact one."""
    return mode if engine == "exact" else f"{mode} ({engine})"


def bytes_s(r: dict) -> float:
    return r["rate_mbit"] * 1e6 / 8


def job_of(r: dict) -> JobShape:
    """The row's job; its cells' share of their pairs as the row records it (bench_hosts.py writes ``cell_share``
    since the cells' lists run from about 10,000 features; rows without it ran the exact cell pass: every row
    of the default files, whose cells hold 12,523 features or fewer, was measured before)."""
    return JobShape(n=int(r["n"]), agents=int(r["m"]), dim=DIM, itemsize=1, engine=engine_of(r),
                    cell_share=float(r.get("cell_share", 1.0)))


def reference_kernel(rows: List[dict]) -> float:
    """The fit's ``kernel_cpu_s``: the median of the rows' measured kernel (bench_hosts.py records
    dqm.core.pairs.pair_cpu_s_here in every row); costmodel.FITTED's when no row has one."""
    have = [r["kernel_cpu_s"] for r in rows if r.get("kernel_cpu_s")]
    if have and len(have) != len(rows):
        raise SystemExit("fit_costmodel: some rows carry kernel_cpu_s and some do not: rows measured on "
                         "machines of unknown speed cannot be fitted with the others (rerun bench_hosts.py)")
    return float(np.median(have)) if have else costmodel.FITTED.kernel_cpu_s


def speed(r: dict, ref: float) -> float:
    """The row's pair work in the reference machine's time: its measured kernel over the reference."""
    return r["kernel_cpu_s"] / ref if r.get("kernel_cpu_s") else 1.0


def relative_nnls(A, b):
    """Non-negative least squares on relative residuals (each row over its measured value): a graf row of
    0.4 s weighs as much as a 100k row of 40 s, so that the picks of small jobs are fitted too."""
    b = np.asarray(b, float)
    return nnls(np.asarray(A, float) / b[:, None], np.ones_like(b))


def fit(rows: List[dict]) -> CostConstants:
    """The exact engine's constants fitted on its rows, then the fast engine's on its own (:func:`fit_fast`)."""
    exact = fit_exact([r for r in rows if engine_of(r) == "exact"])
    fast = [r for r in rows if engine_of(r) == "fast" and "error" not in r]
    return fit_fast(fast, exact) if fast else exact


def fit_fast(rows: List[dict], k: CostConstants) -> CostConstants:
    """The fast engine's constants, the exact engine's ``k`` kept (start-up, links and rounds are the modes'):

    * its centralized match (gather rows): ``match_s * cores = (fast_kernel_cpu_s * speed + fast_other_cpu_s)
      * (n / 1e5) ** fast_exponent``, ``speed`` the row's kernel over the fit's: the exponent on a grid,
      the two parts by non-negative least squares (machines of different pair kernels tell them apart);
    * fast balanced's busiest agent: its time after start-up less the fixed seconds and the link time,
      ``(fast_balanced_imbalance * pair_cpu_s * speed * cell_pair_work + fast_balanced_other_cpu_s * n / M / 1e4
      + fast_balanced_fixed_cpu_s) / cores``;
      its bytes: ``gather_bytes * (M - 1) / M + fast_copy_bytes * copies``;
    * lean: ``lean_work_share`` of the fast match at agent 0 (as for the exact engine: not fitted again).
    """
    ref = k.kernel_cpu_s
    g = [r for r in rows if r["mode"] == "gather"]
    best = None
    for p in np.arange(1.0, 1.61, 0.01):
        grow = [(r["n"] / 1e5) ** p for r in g]
        (kern, other), res = relative_nnls([[speed(r, ref) * x, x] for r, x in zip(g, grow)],
                                           [r["match_s"] * r["cpu_per_host"] for r in g])
        if best is None or res < best[0] - 1e-12:
            best = (res, float(p), float(kern), float(other))
    _, p, kern, other = best
    bal = [r for r in rows if r["mode"] == "balanced"]
    pair = k.pair_cpu_s
    left = [r["job_s"] - k.balanced_fixed_s - k.balanced_link_factor * r["bytes"] / r["m"] / bytes_s(r) for r in bal]
    (imb, other_b, fixed), _ = relative_nnls([[pair * speed(r, ref) * job_of(r).cell_pair_work / r["cpu_per_host"],
                                               r["n"] / r["m"] / 1e4 / r["cpu_per_host"], 1 / r["cpu_per_host"]]
                                              for r in bal], left)
    copy_bytes = float(np.mean([(r["bytes_over_raw"] - k.gather_bytes * (r["m"] - 1) / r["m"])
                                / job_of(r).copies_per_feature for r in bal]))
    return replace(k, fast_kernel_cpu_s=kern, fast_other_cpu_s=other, fast_exponent=round(p, 2),
                   fast_balanced_imbalance=float(imb), fast_balanced_other_cpu_s=float(other_b),
                   fast_balanced_fixed_cpu_s=float(fixed),
                   fast_copy_bytes=copy_bytes)


def fit_exact(rows: List[dict]) -> CostConstants:
    """Non-negative least squares per mechanism on what the rows measured (pair work scaled by each row's
    measured kernel over the reference: rows of several machines fit one model)."""
    ref = reference_kernel(rows)
    g = [r for r in rows if r["mode"] == "gather" and "error" not in r]
    # the centralized pass: match_s at the host's cores = pair_cpu_s * W + match_fixed_cpu_s
    (pair, match0), _ = relative_nnls([[job_of(r).pair_work * speed(r, ref), 1.0] for r in g],
                                      [r["match_s"] * r["cpu_per_host"] for r in g])
    # the gathering: gather_s = the sources' start-up skew / cores + factor * bytes / rate (into the gathering host)
    (g_skew, g_link), _ = relative_nnls([[1.0 / r["cpu_per_host"], r["bytes"] / bytes_s(r)] for r in g],
                                        [r["gather_s"] for r in g])
    # its wire bytes over the raw bytes of the features sent (agent 0 keeps its own)
    g_bytes = float(np.mean([r["bytes_over_raw"] * r["m"] / (r["m"] - 1) for r in g]))
    # start-up: the stand-alone gathering process, and dqm run's host 0 (CPU-seconds at one core)
    g_start = float(np.mean([(r["seconds"] - r["gather_s"] - r["match_s"]) * r["cpu_per_host"] for r in g]))
    run = [r for r in rows if r["mode"] in ("lean", "balanced") and "error" not in r]
    run_start = float(np.mean([(r["seconds"] - r["job_s"]) * r["cpu_per_host"] for r in run]))
    out = {}
    for mode in ("balanced", "lean"):
        rs = [r for r in rows if r["mode"] == mode and "error" not in r]
        if mode == "balanced":  # 1/M of the pairs per agent; one link's share of the bytes
            A = [[1.0, pair * speed(r, ref) * job_of(r).pair_work / r["m"] / r["cpu_per_host"], 1 / r["cpu_per_host"],
                  r["bytes"] / r["m"] / bytes_s(r)] for r in rs]
        else:  # agent 0: all the pairs (times a share), all the bytes into its link
            A = [[1.0, pair * speed(r, ref) * job_of(r).pair_work / r["cpu_per_host"], 1 / r["cpu_per_host"],
                  r["bytes"] / bytes_s(r)] for r in rs]
        out[mode], _ = relative_nnls(A, [r["job_s"] for r in rs])
        per = [r["bytes_over_raw"] / (r["m"] if mode == "balanced" else (r["m"] - 1) / r["m"]) for r in rs]
        out[mode + "_bytes"] = float(np.mean(per))
    b, lean = out["balanced"], out["lean"]
    return replace(costmodel.FITTED, pair_cpu_s=float(pair), kernel_cpu_s=ref, gather_bytes=g_bytes,
                   match_fixed_cpu_s=float(match0),
                   gather_skew_cpu_s=float(g_skew), gather_link_factor=float(g_link), gather_start_cpu_s=g_start,
                   run_start_cpu_s=run_start, balanced_fixed_s=float(b[0]), balanced_imbalance=float(b[1]),
                   balanced_fixed_cpu_s=float(b[2]), balanced_link_factor=float(b[3]),
                   balanced_bytes_per_agent=out["balanced_bytes"], lean_fixed_s=float(lean[0]),
                   lean_work_share=float(lean[1]), lean_fixed_cpu_s=float(lean[2]), lean_link_factor=float(lean[3]),
                   lean_bytes=out["lean_bytes"])


def hosts_of(r: dict) -> Hosts:
    return Hosts.of([bytes_s(r)] * int(r["m"]), r["cpu_per_host"], kernel_cpu_s=r.get("kernel_cpu_s"))


def predicted(r: dict, k: CostConstants, started: bool = False) -> costmodel.Prediction:
    """The row's mode as the benchmark ran it (the stand-alone gather keeps host 0's features there)."""
    return costmodel.predict(job_of(r), hosts_of(r), k, started=started)[r["mode"]]


def after_start_up(r: dict) -> float:
    return r["job_s"] if "job_s" in r else r["gather_s"] + r["match_s"]


def report(rows: List[dict], k: CostConstants) -> bool:
    """Print every row and every group's picks; True if every pick is within 10% of the best measured."""
    print("\n| data | M | Mbit/s | mode | measured s | predicted s | pred / meas | start + fixed + transfer + "
          "compute |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        if r["mode"] not in MODES:
            continue
        p = predicted(r, k)
        parts = " + ".join(f"{p.parts[x]:.1f}" for x in ("start", "fixed", "transfer", "compute"))
        meas = "failed" if "error" in r else f"{r['seconds']:.1f}"
        ratio = "" if "error" in r else f"{p.seconds / r['seconds']:.2f}"
        avail = "" if p.available else " (unavailable)"
        print(f"| {r['data']} | {r['m']} | {r['rate_mbit']:g} | {shown(r['mode'], engine_of(r))} | {meas} | "
              f"{p.seconds:.1f}{avail} | {ratio} | {parts} |")
    groups: Dict[tuple, Dict[str, dict]] = {}
    for r in rows:
        if r["mode"] in MODES:
            groups.setdefault((r["data"], r["m"], r["rate_mbit"], engine_of(r), r.get("file")), {})[r["mode"]] = r
    print("\n| data | M | Mbit/s | measured best | pick (as benchmarked) | pick / best | within 10% | "
          "coordinator's pick (started) | after start-up: pick / best | within 10% |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    ok_all = True
    for (data, m, rate, engine, _), by_mode in groups.items():  # rows of one invocation (one file) together
        ran = {mode: r for mode, r in by_mode.items() if "error" not in r}
        if not ran:
            continue
        best = min(ran, key=lambda x: ran[x]["seconds"])
        any_row = next(iter(by_mode.values()))
        modes = tuple(x for x in MODES if x in by_mode)
        pick = costmodel.choose(job_of(any_row), hosts_of(any_row), k, started=False,
                                modes=modes).mode
        ratio = ran[pick]["seconds"] / ran[best]["seconds"] if pick in ran else float("inf")
        ok = ratio <= 1.10
        ok_all &= ok
        coord = costmodel.choose(job_of(any_row), hosts_of(any_row), k, started=True, modes=modes).mode
        warm = {x: after_start_up(r) for x, r in ran.items() if "job_s" in r or "gather_s" in r}
        if warm and coord in warm:
            w_ratio = warm[coord] / min(warm.values())
            w_text, w_ok = f"{w_ratio:.2f}", ("yes" if w_ratio <= 1.10 else "NO")
        else:
            w_text, w_ok = ("failed" if coord not in ran else "n/a"), ("NO" if coord not in ran else "n/a")
        print(f"| {data} | {m} | {rate:g} | {shown(best, engine)} {ran[best]['seconds']:.1f} s | {pick} | "
              f"{ratio:.2f} | {'yes' if ok else 'NO'} | {coord} | {w_text} | {w_ok} |")
    return ok_all


def constants_text(k: CostConstants) -> str:
    return "\n".join(f"    {f.name}: float = {getattr(k, f.name):.4g}" for f in fields(k))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", nargs="+", default=[str(p) for p in DEFAULT_JSON], help="bench_hosts.py rows")
    args = ap.parse_args(argv)
    rows = read_rows(args.json)
    k = fit(rows)
    print("CostConstants fitted (paste into dqm/distributed/costmodel.py):")
    print(constants_text(k))
    differ = [f.name for f in fields(k) if not np.isclose(getattr(k, f.name), getattr(costmodel.FITTED, f.name),
                                                            rtol=2e-3, atol=1e-12)]
    print("costmodel.FITTED " + ("differs in: " + ", ".join(differ) if differ else "holds these constants"))
    ok = report(rows, k)
    print(f"\nevery pick as benchmarked within 10% of the best measured mode: {'yes' if ok else 'no'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
