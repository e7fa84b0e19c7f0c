"""Is FLANN matching repeatable whatever ran before it in the process?

For each benchmark set (Oxford, hotel, a generated scene), runs
``baselines.pairwise_candidates(matcher="flann")`` in fresh processes with different
histories (nothing before; FLANN on each other set before; BF before; OpenCV's RNG drawn
from; one OpenCV thread) and prints the number of ratio-test matches and a hash of every
candidate (indices, distances, ratios). Identical hashes mean the result depends only on
the input and the seed. Issue 12 measured the opposite on hotel before FLANN ran in a
thread of its own: 115,365 matches fresh, 115,362 after FLANN on the Oxford sets.

    python scripts/check_flann_repeatability.py [--sets graf,scene:0] [--ratio 0.8]
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
CACHE = Path(os.environ.get("TMPDIR", "/tmp")) / "dqm-bench-cache"
HISTORIES = ("fresh", "after-flann-on-others", "after-bf", "after-opencv-rng", "one-opencv-thread")


def _features(spec):
    """Descriptors and image ids of a benchmark set (Oxford name, hotel, scene:N), cached."""
    import numpy as np

    from dqm.benchmark import load_benchmark

    cache = CACHE / f"flann-{spec.replace(':', '-')}.npz"
    if cache.exists():
        z = np.load(cache)
        return z["D"], z["ids"]
    b = load_benchmark(spec, DATA)
    D, ids = np.asarray(b.descriptors), np.asarray(b.image_ids)
    CACHE.mkdir(parents=True, exist_ok=True)
    np.savez(cache, D=D, ids=ids)
    return D, ids


def _child(target, history, others, ratio):
    import cv2

    from dqm.vision.baselines import pairwise_candidates

    if history == "after-flann-on-others":
        for o in others:
            pairwise_candidates(*_features(o), matcher="flann")
    elif history == "after-bf":
        D, ids = _features(others[0])
        pairwise_candidates(D[ids < 2], ids[ids < 2], matcher="bf")
    elif history == "after-opencv-rng":
        import numpy as np

        cv2.randu(np.zeros((64, 64), np.float32), 0, 1)
    elif history == "one-opencv-thread":
        cv2.setNumThreads(1)
    c = pairwise_candidates(*_features(target), matcher="flann")
    h = hashlib.sha256(c.query.tobytes() + c.train.tobytes() + c.distance.tobytes() + c.ratio.tobytes())
    print(json.dumps({"candidates": len(c.query), "matches": int((c.ratio < ratio).sum()),
                      "hash": h.hexdigest()[:12]}))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default="graf,wall,boat,bikes,hotel,scene:0",
                    help="benchmark sets (Oxford names, hotel, scene:SEED), comma-separated")
    ap.add_argument("--ratio", type=float, default=0.8, help="ratio-test threshold for the match count")
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    sets = args.sets.split(",")
    if args.child:
        target, history = args.child
        _child(target, history, [s for s in sets if s != target] or [target], args.ratio)
        return
    if not DATA.exists():
        sys.exit(f"check_flann_repeatability: no shared data at {DATA}")
    for s in sets:
        _features(s)  # fill the cache once, outside the timed children
    print(f"| set | {' | '.join(HISTORIES)} | repeatable |")
    print("|---|" + "---|" * (len(HISTORIES) + 1))
    all_same = True
    for s in sets:
        cells, hashes = [], set()
        for h in HISTORIES:
            out = subprocess.run([sys.executable, __file__, "--sets", args.sets, "--ratio", str(args.ratio),
                                  "--child", s, h], capture_output=True, text=True, check=True).stdout
            r = json.loads(out.strip().splitlines()[-1])
            cells.append(f"{r['matches']:,} ({r['hash'][:6]})")
            hashes.add(r["hash"])
        all_same &= len(hashes) == 1
        print(f"| {s} | {' | '.join(cells)} | {len(hashes) == 1} |", flush=True)
    print(f"\nratio-test matches at {args.ratio} (hash of all candidates); "
          f"{'identical in every history' if all_same else 'DIFFERENT across histories'}")


if __name__ == "__main__":
    main()
