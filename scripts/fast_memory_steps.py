#!/usr/bin/env python
"""Where the fast engine's resident memory peaks, step by step, against its estimate (``memory.fast_bytes``).

Runs ``dqm.quickmatch(engine="fast")`` on generated SIFT-like features (``dqm.synthetic.sized``) with a thread
that samples the process's resident memory every 2 ms, and marks where each step of the engine starts and ends
(the lists' k-means and nearest lists, sigma, the set-up of the scan, the scan, the edges, the tree). Prints each
step's resident memory (at its end, and the most since the mark before), the peak above what the process held
before the call, the engine's own estimate and their ratio, and which steps were running at the peak.

    python scripts/fast_memory_steps.py 2000000 1000 --max-memory 5G
    python scripts/fast_memory_steps.py 1000000 500 --simd 2     # the float32 GEMM path, as without VNNI

``--simd 2`` caps the native kernels at AVX-512 without VNNI (``native.set_simd_level``), so the scan runs on the
float32 GEMM as on machines without VNNI.
"""
import argparse
import bisect
import functools
import gc
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import dqm
from dqm import synthetic
from dqm.core import clustering, inverted_lists, memory, native, pairs, tree

#: the steps marked: (module, function)
STEPS = [(inverted_lists, name) for name in ("kmeans", "scan", "_scanned_lists", "_lists_met_whole", "_scan_bits",
                                             "_probers", "nearest_above")]
STEPS += [(inverted_lists.NearestCandidates, "nearest"), (native, "U8Scan")]
STEPS += [(clustering, name) for name in ("_timed_sigma", "_edges_within_radius", "_truncated_result")]
STEPS += [(tree, name) for name in ("select_parents", "merge_clusters")]


def mark_steps(marks: list) -> None:
    """Wrap every step of :data:`STEPS` so that it appends ``(time, "+name")`` and ``(time, "-name")``."""
    for owner, name in STEPS:
        f = getattr(owner, name)

        def wrapped(*a, _f=f, _name=name, **k):
            marks.append((time.perf_counter(), "+" + _name))
            try:
                return _f(*a, **k)
            finally:
                marks.append((time.perf_counter(), "-" + _name))

        setattr(owner, name, functools.wraps(f)(wrapped))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("n", type=int, help="generated features")
    ap.add_argument("images", type=int, help="images they come from")
    ap.add_argument("--max-memory", default=None, help="the engine's memory budget (default: its own)")
    ap.add_argument("--simd", type=int, default=None, help="cap the native kernels' SIMD level (2: no VNNI)")
    args = ap.parse_args(argv)
    if args.n < 1000 or not 2 <= args.images <= args.n // 10:
        ap.error("give at least 1,000 features and 2 to n / 10 images")
    if args.simd is not None:
        native.set_simd_level(args.simd)
    ds = synthetic.sized(args.n, features_per_image=args.n // args.images)
    X, ids = ds.descriptors, ds.image_ids
    del ds
    marks: list = []
    mark_steps(marks)
    samples: list = []
    done = threading.Event()

    def sample() -> None:
        while not done.is_set():
            samples.append((time.perf_counter(), memory.process_bytes()))
            time.sleep(0.002)

    gc.collect()
    held = memory.process_bytes()
    sampler = threading.Thread(target=sample, daemon=True)
    t0 = time.perf_counter()
    sampler.start()
    result = dqm.quickmatch(X, ids, engine="fast", max_memory=args.max_memory)
    wall = time.perf_counter() - t0
    done.set()
    sampler.join()
    estimate = result.stats["memory_estimate"]  # the engine's own, as it checked its budget
    integer = pairs.Augmented(X).integer_kernel
    peak_at, peak = max(samples, key=lambda s: s[1])
    running: list = []
    for at, step in marks:
        if at > peak_at:
            break
        if step[0] == "+":
            running.append(step[1:])
        else:
            running.remove(step[1:])
    gib = 1 << 30
    print("| step | at s | resident GiB at it | most since the mark before GiB |\n|---|---|---|---|")
    times = [s[0] for s in samples]
    before = 0
    for at, step in marks:
        i = min(bisect.bisect_left(times, at), len(samples) - 1)
        most = max((s[1] for s in samples[before:i + 1]), default=0)
        print(f"| {step} | {at - t0:.2f} | {samples[i][1] / gib:.2f} | {most / gib:.2f} |")
        before = i
    path = "integer kernel (VNNI)" if integer else "float32 GEMM"
    print(f"\n{len(X):,} features, {args.images:,} images, {path}: {wall:.1f} s; held before the call "
          f"{held / gib:.2f} GiB, peak {peak / gib:.2f} GiB, {(peak - held) / gib:.2f} GiB above held; estimate "
          f"{estimate / gib:.2f} GiB; peak above held / estimate {(peak - held) / estimate:.2f}; at the peak "
          f"({peak_at - t0:.2f} s): {', '.join(running) or 'no marked step'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
