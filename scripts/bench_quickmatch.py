#!/usr/bin/env python
"""Benchmark dqm.quickmatch: wall time, peak memory, and ratios measured in one run.

For each data set (SIFT-like synthetic at 6,254 / 25k / 100k features; real SIFT
of ../shared/data/oxford/graf when present) it measures, each in a fresh
process so peak memory is that of the measured call alone:

* dqm.quickmatch (default parameters): wall time, peak RSS, phase times;
* the exact k-NN floor: one exact 2-NN pass over the same data (every feature
  against all), by faiss' IndexFlatL2 when faiss-cpu is installed and by a
  blocked numpy GEMM otherwise/also; the floor is the faster of the two;
* at 6,254 features, a dense numpy QuickMatch (n x n float64 distance matrix,
  the approach of the published Python port) as the slow baseline.

Prints a markdown table with ratios (quickmatch / floor, dense / quickmatch).

    python scripts/bench_quickmatch.py [--sizes 6254,25000,100000] [--repeat 3]
"""
import argparse
import json
import multiprocessing as mp
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def load(name):
    from dqm import synthetic

    if name == "graf":
        from dqm import datasets, features

        seq = datasets.load_homography_sequence(ROOT.parent / "shared" / "data" / "oxford" / "graf")
        D, ids, _ = features.extract_many(seq.image_paths)
        return D, ids
    ds = synthetic.sized(int(name))
    return ds.descriptors, ds.image_ids


def knn_numpy(X):
    """Exact 2-NN of every row against all rows: blocked float32 GEMM + argpartition."""
    X = X.astype(np.float32)
    nrm = (X * X).sum(1)
    out = np.empty((len(X), 2), np.int64)
    for s in range(0, len(X), 1024):
        G = nrm[s:s + 1024, None] + nrm[None, :] - 2.0 * (X[s:s + 1024] @ X.T)
        out[s:s + 1024] = np.argpartition(G, 1, axis=1)[:, :2]
    return out


def knn_faiss(X):
    import faiss

    X = np.ascontiguousarray(X, dtype=np.float32)
    index = faiss.IndexFlatL2(X.shape[1])
    index.add(X)
    return index.search(X, 2)[1]


def dense_quickmatch(X, ids, rho):
    """The dense approach (n x n float64 matrices), vectorised numpy."""
    from scipy.spatial.distance import cdist

    X = X.astype(np.float64)
    D = cdist(X, X)
    same = ids[:, None] == ids[None, :]
    S = np.where(same, D, np.inf)
    np.fill_diagonal(S, np.inf)
    sigma = S.min(1)
    del S
    dens = np.exp(-D ** 2 / (2 * (0.25 * sigma[:, None]) ** 2)).sum(0)
    rank = np.lexsort((np.arange(len(X)), -dens))
    pos = np.empty(len(X), int)
    pos[rank] = np.arange(len(X))
    A = np.where(pos[None, :] < pos[:, None], D, np.inf)
    parent = A.argmin(1)
    pd = A[np.arange(len(X)), parent]
    return parent, pd, sigma


def measure(task, q):
    name, what = task
    X, ids = load(name)
    import dqm

    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t = time.perf_counter()
    info = {}
    if what == "quickmatch":
        r = dqm.quickmatch(X, ids)
        info = {k: v for k, v in r.stats.items()}
        info["clusters"] = r.n_clusters
    elif what == "knn_numpy":
        knn_numpy(X)
    elif what == "knn_faiss":
        try:
            knn_faiss(X)
        except ImportError:
            q.put(None)
            return
    elif what == "dense":
        dense_quickmatch(X, ids, dqm.DEFAULT_RHO)
    wall = time.perf_counter() - t
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    q.put({"wall": wall, "peak_rss_mib": peak / 1024, "base_rss_mib": base / 1024, "n": len(X), **info})


def run(task, repeat=1):
    ctx = mp.get_context("spawn")
    best = None
    for _ in range(repeat):
        q = ctx.Queue()
        p = ctx.Process(target=measure, args=(task, q))
        p.start()
        res = q.get()
        p.join()
        if res is None:
            return None
        if best is None or res["wall"] < best["wall"]:
            best = res
    return best


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="6254,25000,100000")
    ap.add_argument("--repeat", type=int, default=3, help="runs per small case (best is kept); 1 for >= 50k")
    ap.add_argument("--no-graf", action="store_true")
    ap.add_argument("--json", help="also write the raw numbers here")
    args = ap.parse_args(argv)
    names = args.sizes.split(",")
    if not args.no_graf and (ROOT.parent / "shared" / "data" / "oxford" / "graf").exists():
        names.append("graf")
    rows, raw = [], {}
    for name in names:
        small = name == "graf" or int(name) < 50000
        rep = args.repeat if small else 1
        qm = run((name, "quickmatch"), rep)
        kn = run((name, "knn_numpy"), rep)
        kf = run((name, "knn_faiss"), rep)
        floor = min(x["wall"] for x in (kn, kf) if x)
        dense = run((name, "dense"), rep) if name in ("6254", "graf") else None
        raw[name] = {"quickmatch": qm, "knn_numpy": kn, "knn_faiss": kf, "dense": dense}
        rows.append((name, qm, kn, kf, floor, dense))
        print(f"{name}: quickmatch {qm['wall']:.2f}s, floor {floor:.2f}s", file=sys.stderr, flush=True)
    print("| data | n | quickmatch s | peak RSS MiB (base) | k-NN numpy s | k-NN faiss s | qm / floor | dense s | dense / qm |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, qm, kn, kf, floor, dense in rows:
        label = "graf (real SIFT)" if name == "graf" else "synthetic"
        print(f"| {label} | {qm['n']} | {qm['wall']:.3f} | {qm['peak_rss_mib']:.0f} ({qm['base_rss_mib']:.0f}) | "
              f"{kn['wall']:.3f} | {kf['wall'] if kf else float('nan'):.3f} | {qm['wall'] / floor:.2f} | "
              f"{dense['wall'] if dense else float('nan'):.2f} | "
              f"{(dense['wall'] / qm['wall']) if dense else float('nan'):.1f} |")
    print()
    print("phases (s): " + "; ".join(
        f"{name}: sigma {qm['time_sigma']:.2f}, pass {qm['time_pass']:.2f}, refine {qm['time_refine']:.2f} "
        f"({int(qm['n_refined'])} refined), tree {qm['time_tree']:.2f}" for name, qm, *_ in rows))
    if args.json:
        Path(args.json).write_text(json.dumps(raw, indent=1))


if __name__ == "__main__":
    main()
