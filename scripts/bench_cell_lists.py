"""The fast balanced mode's cells with and without their lists (issue 62): one simulated job each, side by side.

With ``engine="fast"`` a balanced cell of enough own features (:func:`dqm.core.inverted_lists.lists_pay`, from
about 10,000) meets only the pairs its lists' scans meet (:class:`dqm.core.inverted_lists.CellLists`); smaller
cells meet every pair within reach (the exact cell pass). This runs the same job both ways in the simulator
(the cell pass forced exact for the second) and prints, for each: the wall time, the busiest agent's CPU
seconds, the most distances an agent computed (and the most pairs a cell holds), the bytes over raw, and
co-membership F1 against the exact centralized engine (and the centralized fast engine's F1 beside them).

    python scripts/bench_cell_lists.py --n 160000 --agents 4
    python scripts/bench_cell_lists.py --n 6000 --agents 2 --force     # the CI check: lists forced on small cells
"""
from __future__ import annotations

import argparse
import time

import dqm
from dqm import evaluation, synthetic
from dqm.core import inverted_lists
from dqm.distributed import DQMConfig, simulate


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=160_000, help="generated features (dqm.synthetic.sized)")
    ap.add_argument("--agents", type=int, default=4)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--force", action="store_true", help="lists on every cell, whatever its size")
    args = ap.parse_args(argv)
    ds = synthetic.sized(args.n)
    X, ids = ds.descriptors, ds.image_ids
    real = inverted_lists.lists_pay
    pays = (lambda n: True) if args.force else real
    runs = {}
    try:
        for name, rule in (("lists where they pay" if not args.force else "lists (forced)", pays),
                           ("exact cell pass", lambda n: False)):
            inverted_lists.lists_pay = rule  # read by the balanced agents when they meet their pairs
            t = time.perf_counter()
            runs[name] = (simulate(X, ids, DQMConfig(agents=args.agents, seed=args.seed, engine="fast")),
                          time.perf_counter() - t)
    finally:
        inverted_lists.lists_pay = real
    params = runs[name][0].config.params
    exact = dqm.quickmatch(X, ids, params=params).labels
    fast = dqm.quickmatch(X, ids, params=params, engine="fast").labels
    print(f"generated {len(X):,} features, {args.agents} agents, fast balanced (simulator, this machine's "
          "cores)\n")
    print("| cells | wall s | busiest agent CPU s | most distances of an agent (of its pairs) | bytes / raw | "
          "F1 vs exact |")
    print("|---|---|---|---|---|---|")
    for name, (r, wall) in runs.items():
        computed = max(p["pairs_computed"] for p in r.per_agent)
        f1 = evaluation.comembership_scores(r.labels, exact).f1
        print(f"| {name} | {wall:.1f} | {r.stats['busiest_cpu_s']:.2f} | "
              f"{computed:,.0f} of {max(p['pairs'] for p in r.per_agent):,.0f} | "
              f"{r.stats['bytes_over_raw']:.3f} | {f1:.5f} |")
    print(f"\ncentralized fast engine: F1 vs exact {evaluation.comembership_scores(fast, exact).f1:.5f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
