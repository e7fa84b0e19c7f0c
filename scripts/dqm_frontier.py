#!/usr/bin/env python
"""The frontier of Distributed QuickMatch: bytes, balance and fidelity, measured in one run.

For each data set (graf and wall SIFT from ../shared/data when present, and
generated SIFT-like sets of 50k and 100k features) it runs centralized
QuickMatch (quadratic kernel, default rho) once, then the in-process simulator
for every number of agents m and every mode, and records:

* identical: labels equal to centralized; F1: co-membership F1 against it;
* max_features_share: the most features any agent held at once (its source's before routing, its
  cell's, the copies received and not yet let go; measured by its driver at every message) / n;
* max_pair_share: the busiest agent's pair count / the centralized n(n-1)/2 (target <= 2.5/m);
* bytes_over_raw: metered bytes / raw descriptor bytes (n * dim * itemsize);
* ghosts (and sketches) per feature;
* the busiest agent's CPU seconds over the centralized CPU seconds, both measured here,
  single-threaded (so CPU seconds are work, not threads waiting);
* the largest cell over n/m.

Modes: ``balanced`` (one-way rule + sketch pre-filter, the default), ``one-way``
(balanced without sketches), ``two-way`` (balanced with the plain two-way
bisector halo, the baseline of the byte target), ``lean`` (the cascade),
``paper`` and ``fast`` (balanced with ``engine="fast"``: copies only where a pair
is likely, dqm.distributed.ghosts.likely_copies; its F1 is against the exact
centralized clusters). The paper mode's exact cell distances (a QP per feature and cell)
take hours on the large sets at large m; rows above ``--paper-max`` (n * m) are
listed as not run.

    python scripts/dqm_frontier.py                          # -> ./dqm-out/frontier/
    python scripts/dqm_frontier.py --out docs               # regenerate docs/dqm_frontier.md + figure
    python scripts/dqm_frontier.py --data graf --agents 2,8 --modes balanced,two-way
    python scripts/dqm_frontier.py --data features.npz --agents 4,8 --modes balanced   # your own photos
    python scripts/dqm_frontier.py --out docs --data graf,100000,sacre_coeur --agents 4,8 --modes balanced,fast

Rows already in the output's JSON are reused (``--fresh`` recomputes the
selected ones; rows of other modes or m are kept), so an interrupted run
resumes and one mode can be measured again alone.
"""
import argparse
import json
import os
import sys
import time
from pathlib import Path

# CPU seconds are the measure of work here: one thread everywhere (BLAS, the tile pool), so that
# idle threads spinning in BLAS do not count as work (they made the centralized time vary by 35%)
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "DQM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import dqm  # noqa: E402
from dqm import evaluation, synthetic  # noqa: E402
from dqm.distributed import DQMConfig, simulate  # noqa: E402

MODES = {
    "balanced": {"mode": "balanced"},
    "one-way": {"mode": "balanced", "sketch_dims": 0},
    "two-way": {"mode": "balanced", "ghost_rule": "two-way", "sketch_dims": 0},
    "lean": {"mode": "lean"},
    "paper": {"mode": "paper"},
    "fast": {"mode": "balanced", "engine": "fast"},
}
#: the fast balanced mode's targets (issue 62): F1 against exact, bytes / raw at m = 4 and 8, busiest features
FAST_F1 = 0.995
FAST_BYTES = {4: 1.5, 8: 2.0}
FAST_SHARE = 2.0


def load(name: str, shared: Path):
    """(descriptors, image_ids) of a named data set, or None when its files are absent."""
    if name in ("graf", "wall", "sacre_coeur"):
        from dqm.vision import datasets, features

        path = shared / "data" / ("oxford" if name != "sacre_coeur" else "") / name
        if not path.exists():
            print(f"skipping {name}: {path} is absent", file=sys.stderr)
            return None
        images = (datasets.load_homography_sequence(path).image_paths if name != "sacre_coeur"
                  else sorted(path.glob("*.jpg")))
        X, ids, _ = features.extract_many(images)  # OpenCV's SIFT at its defaults
        return X, ids
    if name.endswith(".npz"):  # a FEATURES file (dqm extract): real photos of one's own
        from dqm import io

        fs = io.load_features(name)
        return fs.descriptors, fs.image_ids
    ds = synthetic.sized(int(name))
    return ds.descriptors, ds.image_ids


def label(name: str, n: int) -> str:
    if name.endswith(".npz"):
        return f"{Path(name).stem} ({n})"
    return f"{name} ({n})" if name in ("graf", "wall", "sacre_coeur") else f"generated {n}"


def measure(X, ids, m: int, mode: str, central, central_cpu: float, seed: int) -> dict:
    cfg = DQMConfig(agents=m, seed=seed, **MODES[mode])
    t = time.perf_counter()
    r = simulate(X, ids, cfg)
    wall = time.perf_counter() - t
    s = r.stats
    return {
        "m": m, "mode": mode, "identical": bool(np.array_equal(r.labels, central.labels)),
        "f1": evaluation.comembership_scores(r.labels, central.labels).f1,
        "max_features_share": s["max_features_share"], "max_pair_share": s["max_pair_share"],
        "bytes_over_raw": s["bytes_over_raw"], "ghosts_per_feature": s.get("ghosts_per_feature", 0.0),
        "sketches_per_feature": s.get("sketches_per_feature", 0.0),
        "busiest_cpu_s": s["busiest_cpu_s"], "cpu_over_central": s["busiest_cpu_s"] / central_cpu,
        "largest_cell_share": s["largest_cell_share"], "arrival_check_failures": s["arrival_check_failures"],
        "transfers_per_feature": s["transfers_per_feature"], "wall_s": wall, "central_cpu_s": central_cpu,
        "bytes_by_kind": {k: v[0] for k, v in r.traffic.per_kind().items()},
    }


def table(results: dict) -> str:
    head = ("| data | m | mode | identical | F1 | max features share | max pair share (<= 2.5/m) | bytes / raw "
            "| ghosts / feature (sketches) | busiest CPU s (/ centralized) | largest cell | checks failed |")
    out = [head, "|" + "---|" * (head.count("|") - 1)]
    for data, d in results.items():
        for r in d["rows"]:
            if r.get("skipped"):
                out.append(f"| {data} | {r['m']} | {r['mode']} | not run: {r['skipped']} | | | | | | | | |")
                continue
            share_ok = "" if r["m"] not in (4, 8, 16) else (" ✓" if r["max_pair_share"] <= 2.5 / r["m"] else " ✗")
            sk = f" ({r['sketches_per_feature']:.2f})" if r["sketches_per_feature"] else ""
            out.append(
                f"| {data} | {r['m']} | {r['mode']} | {'yes' if r['identical'] else 'no'} | {r['f1']:.4f} | "
                f"{r['max_features_share']:.3f} | {r['max_pair_share']:.3f}{share_ok} | {r['bytes_over_raw']:.2f} | "
                f"{r['ghosts_per_feature']:.2f}{sk} | {r['busiest_cpu_s']:.2f} ({r['cpu_over_central']:.2f}) | "
                f"{r['largest_cell_share']:.2f} | {int(r['arrival_check_failures'])} |")
    return "\n".join(out)


def targets(results: dict) -> str:
    """The issue's targets, checked on the rows present (graf and 100k)."""
    lines = []
    for data, d in results.items():
        rows = {(r["mode"], r["m"]): r for r in d["rows"] if not r.get("skipped")}
        bal = [r for (mode, _), r in rows.items() if mode == "balanced"]
        if not bal:
            continue
        ident = all(r["identical"] for r in bal)
        share = [(r["m"], r["max_pair_share"], 2.5 / r["m"]) for r in bal if r["m"] in (4, 8, 16)]
        parts = [f"balanced labels identical at every m: {'yes' if ident else 'NO'}"]
        if share:
            parts.append("max_pair_share <= 2.5/m at m = 4, 8, 16: " + ", ".join(
                f"m={m} {s:.3f} {'<=' if s <= t else '>'} {t:.3f}" for m, s, t in share))
        if ("balanced", 8) in rows and ("two-way", 8) in rows:
            b, t = rows[("balanced", 8)]["bytes_over_raw"], rows[("two-way", 8)]["bytes_over_raw"]
            parts.append(f"bytes at m=8: {b:.2f}x raw vs plain two-way halo {t:.2f}x: "
                         f"{100 * (1 - b / t):.0f}% below (target >= 40%)")
        fast = sorted((r for (mode, _), r in rows.items() if mode == "fast"), key=lambda r: r["m"])
        if fast:
            parts.append("fast balanced " + ", ".join(
                f"m={r['m']}: F1 {r['f1']:.4f} {'>=' if r['f1'] >= FAST_F1 else '<'} {FAST_F1}, "
                f"{r['bytes_over_raw']:.2f}x raw"
                + (f" {'<=' if r['bytes_over_raw'] <= FAST_BYTES[r['m']] else '>'} {FAST_BYTES[r['m']]}"
                   if r["m"] in FAST_BYTES else "")
                + f", busiest features {r['max_features_share'] * r['m']:.2f}/m "
                f"{'<=' if r['max_features_share'] * r['m'] <= FAST_SHARE else '>'} {FAST_SHARE}/m" for r in fast))
        cells = max(r["largest_cell_share"] for r in bal)
        parts.append(f"largest cell <= {cells:.2f} n/m (target 1.25)")
        lines.append(f"* **{data}** (centralized {d['central_cpu_s']:.1f} CPU s): " + "; ".join(parts) + ".")
    return "\n".join(lines)


def summary_table(results: dict) -> str:
    """The compact frontier table of docs/distributed.md: balanced against lean and the two-way halo."""
    head = ("| data | m | balanced: bytes / raw | pair share | CPU / centralized | lean: bytes / raw | pair share "
            "| CPU / centralized | two-way halo: bytes / raw | one-way without sketch: bytes / raw "
            "| fast: bytes / raw | F1 | CPU / centralized |")
    out = [head, "|" + "---|" * (head.count("|") - 1)]
    for data, d in results.items():
        rows = {(r["mode"], r["m"]): r for r in d["rows"] if not r.get("skipped")}
        for m in sorted({r["m"] for r in d["rows"]}):
            def cell(mode, *fields, rows=rows, m=m):  # this row's (bound now: the loop moves on)
                r = rows.get((mode, m))
                return ["–"] * len(fields) if r is None else [f"{r[f]:.2f}" for f in fields]
            b = cell("balanced", "bytes_over_raw", "max_pair_share", "cpu_over_central")
            lean = cell("lean", "bytes_over_raw", "max_pair_share", "cpu_over_central")
            fast = cell("fast", "bytes_over_raw", "f1", "cpu_over_central")
            if rows.get(("fast", m)):
                fast[1] = f"{rows[('fast', m)]['f1']:.4f}"
            out.append(f"| {data} | {m} | " + " | ".join(b + lean + cell("two-way", "bytes_over_raw")
                                                          + cell("one-way", "bytes_over_raw") + fast) + " |")
    return "\n".join(out)


def fast_table(results: dict) -> str:
    """docs/distributed.md's table of the fast balanced mode, beside the exact mode's bytes and copies."""
    head = ("| data | M | F1 | bytes / raw (exact balanced) | busiest agent's features | copies per feature (exact) |")
    out = [head, "|" + "---|" * (head.count("|") - 1)]
    for data, d in results.items():
        rows = {(r["mode"], r["m"]): r for r in d["rows"] if not r.get("skipped")}
        for m in sorted(m for (mode, m) in rows if mode == "fast"):
            f, b = rows[("fast", m)], rows.get(("balanced", m))
            exact = (lambda key, b=b: "" if b is None else f" ({b[key]:.2f})")  # noqa: E731
            over = "**" if m in FAST_BYTES and f["bytes_over_raw"] > FAST_BYTES[m] else ""
            out.append(f"| {data} | {m} | {f['f1']:.4f} | {over}{f['bytes_over_raw']:.2f}{over}"
                       f"{exact('bytes_over_raw')} | {f['max_features_share'] * m:.2f} / M | "
                       f"{f['ghosts_per_feature']:.2f}{exact('ghosts_per_feature')} |")
    return "\n".join(out)


def update_block(path: Path, text: str, name: str = "frontier") -> None:
    """Replace what stands between the ``name`` markers in ``path`` (if it has them)."""
    begin, end = f"<!-- {name}: written by scripts/dqm_frontier.py -->", f"<!-- /{name} -->"
    if not path.exists():
        return
    doc = path.read_text()
    if begin in doc and end in doc:
        path.write_text(doc[:doc.index(begin) + len(begin)] + "\n" + text + "\n" + doc[doc.index(end):])


def figure(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = list(results)
    fig, axes = plt.subplots(2, len(data), figsize=(4.2 * len(data), 7.5), squeeze=False)
    styles = {"balanced": ("o-", "C0"), "one-way": ("^--", "C1"), "two-way": ("v:", "C2"), "lean": ("s-", "C3"),
              "paper": ("D-.", "C4"), "fast": ("P-", "C5")}
    for j, name in enumerate(data):
        rows = [r for r in results[name]["rows"] if not r.get("skipped")]
        top, bottom = axes[0, j], axes[1, j]
        for mode, (style, color) in styles.items():
            rs = sorted((r for r in rows if r["mode"] == mode), key=lambda r: r["m"])
            if not rs:
                continue
            top.loglog([r["bytes_over_raw"] for r in rs], [r["max_pair_share"] for r in rs], style, color=color,
                       label=mode)
            for r in rs:
                top.annotate(str(r["m"]), (r["bytes_over_raw"], r["max_pair_share"]), fontsize=7, color=color,
                             xytext=(3, 2), textcoords="offset points")
            bottom.semilogy([r["m"] for r in rs], [r["cpu_over_central"] for r in rs], style, color=color,
                            label=mode)
        ms = sorted({r["m"] for r in rows})
        bottom.semilogy(ms, [1.0 / m for m in ms], "k:", lw=0.8, label="1/m")
        top.set(title=name, xlabel="metered bytes / raw descriptor bytes",
                ylabel="busiest agent's pairs / centralized (m annotated)")
        from matplotlib.ticker import FixedLocator, NullFormatter, ScalarFormatter

        top.xaxis.set_major_locator(FixedLocator([1, 2, 5, 10, 20, 50]))
        top.xaxis.set_major_formatter(ScalarFormatter())
        top.xaxis.set_minor_formatter(NullFormatter())
        bottom.set(xlabel="agents m", ylabel="busiest agent's CPU s / centralized CPU s")
        for ax in (top, bottom):
            ax.grid(alpha=0.3, which="both")
        top.legend(fontsize=7)
        bottom.legend(fontsize=7)
    fig.suptitle("Distributed QuickMatch: bytes against balance (top) and the busiest agent's CPU (bottom)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_json(results: dict, out: Path) -> None:
    """The rows so far (a run that stops keeps them: the next one reuses them)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "dqm_frontier.json").write_text(json.dumps(results, indent=1))


def write(results: dict, out: Path, argv) -> None:
    write_json(results, out)
    figure(results, out / "img" / "dqm_frontier.png")
    text = [
        "# Distributed QuickMatch: the frontier between bytes, balance and fidelity",
        "",
        "Generated by `python scripts/dqm_frontier.py " + " ".join(argv) + "` "
        f"({time.strftime('%Y-%m-%d')}, {__import__('os').cpu_count()} cores). In-process simulator, "
        f"quadratic kernel, rho = {dqm.DEFAULT_RHO}, k-means seeds from the integer 1. The busiest agent's CPU "
        "seconds are divided by the centralized run's (dqm.quickmatch, same kernel), measured in the same "
        "invocation, single-threaded. Modes: "
        "`balanced` (one-way rule + 48-dim sketch pre-filter, where a pilot shows it can pay), `one-way` "
        "(no sketch), `two-way` (the plain "
        "two-way bisector halo: the byte target's baseline), `lean` (cascade), `paper`, `fast` (balanced with the "
        "fast engine: copies only where a pair is likely; F1 against the exact clusters). "
        "How to read it: docs/distributed.md.",
        "",
        targets(results),
        "",
        table(results),
        "",
        "![bytes against balance, and the busiest agent's CPU](img/dqm_frontier.png)",
    ]
    (out / "dqm_frontier.md").write_text("\n".join(text) + "\n")
    update_block(out / "distributed.md", targets(results) + "\n\n" + summary_table(results))
    update_block(out / "distributed.md", fast_table(results), "frontier-fast")


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="graf,wall,50000,100000",
                    help="graf, wall, generated sizes and/or FEATURES files (.npz, from dqm extract)")
    ap.add_argument("--agents", default="2,4,8,16,25")
    ap.add_argument("--modes", default="balanced,one-way,two-way,lean,paper")
    ap.add_argument("--seed", type=int, default=1, help="the partition integer")
    ap.add_argument("--paper-max", type=float, default=6e5, help="run paper mode only where n * m <= this")
    ap.add_argument("--shared", default=str(ROOT.parent / "shared"))
    ap.add_argument("--out", default="dqm-out/frontier")
    ap.add_argument("--fresh", action="store_true", help="recompute the selected rows even if the output JSON has them")
    args = ap.parse_args(argv)
    out = Path(args.out)
    old = {}
    if (out / "dqm_frontier.json").exists():
        old = json.loads((out / "dqm_frontier.json").read_text())
    results = {}
    ms = [int(v) for v in args.agents.split(",")]
    modes = args.modes.split(",")
    for name in args.data.split(","):
        got = load(name, Path(args.shared))
        if got is None:
            continue
        X, ids = got
        key = label(name, len(X))
        prev = {(r["mode"], r["m"]): r for r in old.get(key, {}).get("rows", [])}
        cached = {k for k, r in prev.items() if not r.get("skipped") and not args.fresh}
        todo = [(mode, m) for mode in modes for m in ms if (mode, m) not in cached
                and not (mode == "paper" and len(X) * m > args.paper_max)]
        central, central_cpu = None, old.get(key, {}).get("central_cpu_s")
        if todo or central_cpu is None:  # each row keeps the centralized CPU time of the run that made it
            step = max(1, len(X) // 500)
            dqm.quickmatch(X[::step], ids[::step], kernel="quadratic")  # warm-up: libraries, pools, pages
            t = time.process_time()
            central = dqm.quickmatch(X, ids, kernel="quadratic")
            central_cpu = time.process_time() - t
        rows = dict(prev)  # every row made before stays until a new one replaces it
        order = {name: i for i, name in enumerate(MODES)}

        def listed(rows=rows, order=order):  # this data set's rows (bound now: the loop moves on)
            return sorted(rows.values(), key=lambda e: (order.get(e["mode"], 99), e["m"]))

        for mode in modes:
            for m in ms:
                if (mode, m) in cached:
                    continue
                if mode == "paper" and len(X) * m > args.paper_max:
                    row = {"m": m, "mode": mode, "skipped": f"QP cell distances for {len(X)} features x {m} "
                                                            "cells take hours here"}
                else:
                    row = measure(X, ids, m, mode, central, central_cpu, args.seed)
                rows[(mode, m)] = row
                print(json.dumps({"data": key, **{k: v for k, v in row.items() if k != "bytes_by_kind"}}),
                      file=sys.stderr, flush=True)
                results[key] = {"n": len(X), "central_cpu_s": central_cpu, "rows": listed()}
                write_json(dict(old, **results), out)  # the figure and the tables once per data set
        results[key] = {"n": len(X), "central_cpu_s": central_cpu, "rows": listed()}
        write(dict(old, **results), out, argv)
    if not results:  # no data set found: the tables of the rows made before
        write(dict(old), out, argv)
    print((out / "dqm_frontier.md").read_text())


if __name__ == "__main__":
    main()
