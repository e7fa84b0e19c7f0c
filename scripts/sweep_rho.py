#!/usr/bin/env python
"""Sweep QuickMatch's rho on real and generated data; prints a markdown table.

Used to choose dqm's default rho (docs/quickmatch.md). Real data is read from
../shared/data (skipped with a note when absent).

    python scripts/sweep_rho.py [--shared ../shared] [--rhos 0.4,0.5,...]
"""
import argparse
import sys
from pathlib import Path

import numpy as np

import dqm
from dqm import evaluation, synthetic
from dqm.vision import datasets, features

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shared", default=str(ROOT.parent / "shared"))
    ap.add_argument("--rhos", default="0.4,0.5,0.6,0.67,0.75,0.8,0.9,1.0,1.1,1.25,1.5")
    ap.add_argument("--tol", type=float, default=5.0, help="homography tolerance in pixels")
    ap.add_argument("--sets", default="synthetic,hotel,graf,wall,boat,bikes")
    args = ap.parse_args(argv)
    rhos = [float(r) for r in args.rhos.split(",")]
    data = Path(args.shared) / "data"
    want = set(args.sets.split(","))
    sets = []
    ds = synthetic.sift_like(n_images=8, n_points=500, noise=0.35, seed=0)
    if "synthetic" in want:
        sets.append(("synthetic", ds.descriptors, ds.image_ids,
                     lambda a, b, ds=ds: evaluation.landmark_scores(a, b, ds.point_ids, ds.image_ids)))
    if "hotel" not in want:
        pass
    elif (data / "cmu_hotel").exists():
        seq = datasets.load_landmark_sequence(data / "cmu_hotel")
        D, ids, lm, _ = features.landmark_descriptors(seq)
        sets.append(("hotel", D, ids, lambda a, b, lm=lm, ids=ids: evaluation.landmark_scores(a, b, lm, ids)))
    else:
        print(f"note: {data / 'cmu_hotel'} absent, hotel skipped", file=sys.stderr)
    for name in ("graf", "wall", "boat", "bikes"):
        if name not in want:
            continue
        if not (data / "oxford" / name).exists():
            print(f"note: oxford/{name} absent, skipped", file=sys.stderr)
            continue
        seq = datasets.load_homography_sequence(data / "oxford" / name)
        D, ids, kp = features.extract_many(seq.image_paths)
        sets.append((name, D, ids, lambda a, b, kp=kp, ids=ids, seq=seq: evaluation.homography_scores(
            a, b, kp, ids, seq.homography, tol=args.tol)))
    print("| data | features | " + " | ".join(f"rho={r:g}" for r in rhos) + " |")
    print("|---|---|" + "---|" * len(rhos))
    mean_f1 = np.zeros(len(rhos))
    for name, D, ids, score in sets:
        cells = []
        for k, rho in enumerate(rhos):
            r = dqm.quickmatch(D, ids, rho=rho)
            a, b = evaluation.cluster_pairs(r.labels, ids)
            s = score(a, b)
            mean_f1[k] += s.f1 / len(sets)
            cells.append(f"P {s.precision:.3f} R {s.recall:.3f} F1 {s.f1:.3f}")
        print(f"| {name} | {len(D)} | " + " | ".join(cells) + " |", flush=True)
    print("| mean F1 | | " + " | ".join(f"{f:.3f}" for f in mean_f1) + " |")


if __name__ == "__main__":
    main()
