"""How much of the homography truth is chance, and what recall real correspondences allow (issue 61).

`dqm evaluate`'s homography truth is positional (dqm/evaluation.py): per image pair, the greedy
one-to-one pairs of keypoints within 5 px under the true homography. Where keypoints are dense, many of
those pairs are two unrelated keypoints that happen to lie within 5 px. This script counts them: the
same truth under the homography followed by a translation of 40-70 px (``CHANCE_SHIFTS``: every real
correspondence broken, the keypoints' density kept) gives the pairs chance alone makes, and
``real_truth_pairs`` bounds the real correspondences among the truth's pairs. Beside them, `dqm match`'s
clusters on the same features (QuickMatch and guided growth, the ``sfm`` preset: the grown row of
docs/match-defaults) with the truth pairs they find, and the F1 a matcher would have that finds every
real correspondence and nothing else (precision 1, recall = real / truth).

A second table checks the truth itself against the matches (``--fit``): per image pair, a homography
fitted to the matches `dqm match`'s clusters imply (USAC, MAGSAC++ at 4 px, as the verification fits;
15 inliers at least), how far its inliers lie from the truth, and whether it agrees with its own
compositions through every third image (H_kj H_ik against H_ij at the inliers: independent matches, so
a fitted homography that agrees with them is the images' own geometry, not a fit to wrong matches). The
pairs where the truth puts more than a fifth of such inliers beyond its 5 px are listed: there
precision counts correct matches as wrong.

A third table asks what a looser link rule of guided growth would add (``--links``): per rule
(``link_threshold`` px, ``max_sigma``; the defaults, 2 px and 1.5, first), with the links' descriptors
rectified from the images (dqm.vision.rectify, as `dqm match` compares them) and with the clustered
descriptors, the links the verified planar pairs
(on these sets nearly every pair) propose under their own homographies, and under the same homographies
followed by the shifts above (no real correspondence left: every link proposed there is chance, though chance
the truth may count as correct), and the scores `dqm evaluate` gives the grown clusters. Where a rule's extra
links under the true geometry are not many more than its extra links under the shifted one, what it adds is
mostly chance.

    python scripts/truth_chance.py graf wall boat bikes --fit --out docs/match-defaults/truth-chance.md
    python scripts/truth_chance.py graf wall boat bikes --links --out docs/match-defaults/growth-chance.md
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dqm import benchmark, evaluation  # noqa: E402


def chance_rows(bench: benchmark.Benchmark) -> dict:
    """The truth's pairs, chance's and the bounds on the real ones, summed over the image pairs (the truth is
    the benchmark's own, :meth:`Benchmark.truth`, which the scoring of dqm match's clusters reuses)."""
    truth = bench.truth()
    ids = truth.image_ids
    lower, upper = ids[truth.truth_keys // truth.n], ids[truth.truth_keys % truth.n]  # each truth pair's images
    total = chance = lo = hi = 0.0
    for (i, j), H in truth.H.items():
        xa, xb = truth.xy[ids == i], truth.xy[ids == j]
        n = int(np.count_nonzero((lower == i) & (upper == j)))
        c = evaluation.chance_truth_pairs(H, xa, xb, truth.tol)
        a, b = evaluation.real_truth_pairs(n, c, len(xa), len(xb))
        total, chance, lo, hi = total + n, chance + c, lo + a, hi + b
    return {"truth": int(total), "chance": chance, "real_lo": lo, "real_hi": hi}


def _apply(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    q = xy @ H[:, :2].T + H[:, 2]
    return q[:, :2] / q[:, 2:]


def fit_rows(bench: benchmark.Benchmark, labels: np.ndarray, threshold: float = 4.0, min_inliers: int = 15,
             seed: int = 0) -> list:
    """Per image pair: the homography fitted to the matches ``labels`` imply, its inliers' errors under the
    truth, and its disagreement with its compositions through the other images (module docstring)."""
    import cv2

    from dqm.vision.colmap import cluster_pairs

    truth = bench.truth()
    xy = truth.xy
    cv2.setRNGSeed(int(seed))
    fitted, inl = {}, {}
    for (i, j), m in sorted(cluster_pairs(labels, bench.image_ids).items()):
        if len(m) < min_inliers:
            continue
        H, mask = cv2.findHomography(xy[m[:, 0]].astype(np.float32), xy[m[:, 1]].astype(np.float32),
                                     cv2.USAC_MAGSAC, threshold, None, 10000, 0.999)
        if H is None or mask is None or mask.sum() < min_inliers:
            continue
        fitted[(i, j)], inl[(i, j)] = H / H[2, 2], m[mask.ravel().astype(bool)]

    def h(a: int, b: int):
        if (a, b) in fitted:
            return fitted[(a, b)]
        return np.linalg.inv(fitted[(b, a)]) if (b, a) in fitted else None

    images = sorted({k for pair in fitted for k in pair})
    rows = []
    for (i, j), m in inl.items():
        xa, xb = xy[m[:, 0]], xy[m[:, 1]]
        own = np.linalg.norm(_apply(fitted[(i, j)], xa) - xb, axis=1)
        err = evaluation.reprojection_error(truth.H[(i, j)], xa, xb)
        chain = [np.median(np.linalg.norm(_apply(h(k, j) @ h(i, k), xa) - _apply(fitted[(i, j)], xa), axis=1))
                 for k in images if k not in (i, j) and h(i, k) is not None and h(k, j) is not None]
        rows.append({"pair": (i, j), "inliers": len(m), "own_median": float(np.median(own)),
                     "truth_median": float(np.median(err)), "beyond": float(np.mean(err > truth.tol)),
                     "chain_median": float(np.median(chain)) if chain else float("nan"), "chains": len(chain)})
    return rows


#: guided growth's link rules the --links table compares: (link_threshold px, max_sigma); the defaults first
LINK_RULES = ((2.0, 1.5), (3.0, 1.5), (2.0, 2.0), (3.0, 2.0))


def link_rows(bench: benchmark.Benchmark, rules=LINK_RULES, seed: int = 0) -> list:
    """Per comparison (the descriptors rectified from the images, as `dqm match` compares them, with the ring of
    the verification's 4 px at :data:`dqm.vision.guided.RING_MAX_SIGMA`; the default rule rectified without that
    ring; the clustered descriptors) and link rule: the links the verified planar pairs propose under their
    homographies and under each :data:`dqm.evaluation.CHANCE_SHIFTS` after them (module docstring), and the grown
    clusters' scores."""
    from dataclasses import replace

    from dqm.core import quickmatch
    from dqm.vision import guided
    from dqm.vision.rectify import rectifier_for
    from dqm.vision.verify import DEFAULT_THRESHOLD, fit_and_split

    result = quickmatch(bench.descriptors, bench.image_ids)
    ids, kp = bench.image_ids, np.asarray(bench.keypoints, np.float64)
    labels, models, _ = fit_and_split(result.labels, ids, kp, seed=seed)
    planar = {pair: m.guide() for pair, m in models.items() if m.guide().kind == "H"}
    by_image = {int(k): np.flatnonzero(ids == k) for k in np.unique(ids)}
    sigma = np.where(np.isfinite(result.sigma), result.sigma, np.inf)
    rows = []
    runs = [("rectified", r, DEFAULT_THRESHOLD) for r in rules] + [("rectified, no ring", rules[0], 0.0)]
    runs += [("clustered", r, 0.0) for r in rules]
    for kind, (threshold, max_sigma), ring in runs:
        rectifier = None
        if kind != "clustered":  # a fresh one per rule: it counts the pairs it rectified
            rectifier, why = rectifier_for(bench.images, kp, bench.descriptors, ids)
            if rectifier is None:
                raise SystemExit(f"truth_chance: {bench.name}: {why}")
        counts = []
        for shift in ((0.0, 0.0), *evaluation.CHANCE_SHIFTS):
            T = np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]], [0.0, 0.0, 1.0]])
            shifted = {pair: replace(m, matrix=T @ m.matrix) for pair, m in planar.items()}
            li, _, _ = guided._propose_all(labels, by_image, shifted, bench.descriptors, kp, sigma, threshold,
                                           guided.DEFAULT_RATIO, max_sigma, 1, None, rectifier, ids, ring)
            counts.append(len(li))
        if kind == "rectified, no ring":
            grown = None  # growth rectifies with its ring: this row counts links only
        else:
            grown, _ = guided.guided_labels(result, kp, bench.descriptors, seed=seed, link_threshold=threshold,
                                            max_sigma=max_sigma, images=bench.images if rectifier else None)
        rows.append({"kind": kind, "threshold": threshold, "max_sigma": max_sigma, "planar_pairs": len(planar),
                     "links": counts[0], "chance": float(np.mean(counts[1:])),
                     "scores": None if grown is None else bench.score_labels(grown)})
    return rows


def f1(p: float, r: float) -> float:
    return 2 * p * r / (p + r) if p + r else 0.0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", nargs="+", help="homography data sets (graf, wall, boat, bikes, scene:N)")
    ap.add_argument("--preset", default="sfm", help="SIFT preset (default sfm: dqm match's on images)")
    ap.add_argument("--fit", action="store_true",
                    help="also check the truth against homographies fitted to dqm match's matches (second table)")
    ap.add_argument("--links", action="store_true",
                    help="also compare guided growth's link rules under the true and shifted geometry (third table)")
    ap.add_argument("--out", type=Path, default=None, help="also write the table to this markdown file")
    args = ap.parse_args(argv)
    rows, fits, links = [], [], []
    for name in args.data:
        bench = benchmark.load_benchmark(name, preset=args.preset)
        if bench.kind != "homography":
            sys.exit(f"truth_chance: {name} has landmark truth, not homographies")
        c = chance_rows(bench)
        labels = benchmark.grown_labels(bench)  # the grown row of `dqm evaluate`, scored as it scores them
        grown = bench.score_labels(labels)
        found = grown.recall * c["truth"]
        rows.append((name, len(bench), c, grown, found))
        if args.fit:
            fits.append((name, fit_rows(bench, labels)))
        if args.links:
            links.append((name, link_rows(bench)))
        print(f"{name}: {c['truth']} truth pairs, {c['chance']:.0f} by chance, real {c['real_lo']:.0f}-"
              f"{c['real_hi']:.0f}; dqm match finds {found:.0f} (F1 {grown.f1:.3f})", flush=True)
    lines = [f"Generated by `python scripts/truth_chance.py {' '.join(args.data)}"
             + (f" --preset {args.preset}" if args.preset != "sfm" else "") + (" --fit" if args.fit else "")
             + (" --links" if args.links else "")
             + (f" --out {args.out}`" if args.out else "`") + ". Truth: one-to-one keypoint pairs within 5 px "
             "under the true homography (`dqm evaluate`'s); chance: the same under the homography and a shift "
             "of 40-70 px (mean of four); real: bounds from `dqm.evaluation.real_truth_pairs`; dqm match: "
             "QuickMatch and guided growth, the `sfm` preset.", "",
             "| data | features | truth pairs | by chance | real (bounds) | real / truth | dqm match: truth pairs "
             "found (recall) | its precision / F1 | F1 of finding every real one and nothing else |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, n, c, g, found in rows:
        t = max(c["truth"], 1)
        lo, hi = c["real_lo"] / t, c["real_hi"] / t
        lines.append(f"| {name} | {n:,} | {c['truth']:,} | {c['chance']:,.0f} | {c['real_lo']:,.0f} - "
                     f"{c['real_hi']:,.0f} | {lo:.2f} - {hi:.2f} | {found:,.0f} ({g.recall:.3f}) | "
                     f"{g.precision:.3f} / {g.f1:.3f} | {f1(1.0, lo):.3f} - {f1(1.0, hi):.3f} |")
    if args.fit:
        lines += ["", "The truth against the matches' own homographies (`--fit`): image pairs (images numbered from 1) "
                  "where more than a fifth of the inliers of a homography fitted to `dqm match`'s matches lie beyond "
                  "the truth's 5 px. Chain: the median distance, at those inliers, between the fitted homography and "
                  "its compositions through each third image (median over the third images).", "",
                  "| data | image pair | inliers (4 px) | their residual under the fit, median px | under the truth: "
                  "median px, share beyond 5 px | chain, median px (third images) |", "|---|---|---|---|---|---|"]
        for name, fit in fits:
            off = [r for r in fit if r["beyond"] > 0.2]
            lines += [f"| {name} | {r['pair'][0] + 1}-{r['pair'][1] + 1} | {r['inliers']:,} | {r['own_median']:.2f} | "
                      f"{r['truth_median']:.1f}, {r['beyond']:.2f} | {r['chain_median']:.2f} ({r['chains']}) |"
                      for r in off]
            if not off:
                lines.append(f"| {name} | none of {len(fit)} | | | | |")
    if args.links:
        from dqm.vision import guided

        lines += ["", "Guided growth's link rule (`--links`): the links the verified planar pairs propose under their "
                  "own homographies and under those followed by a shift of 40-70 px (mean of four: every link there is "
                  "chance), and the grown clusters' scores; the links' descriptors rectified from the images "
                  "(`dqm match`'s comparison, dqm.vision.rectify: with the ring out to the verification's 4 px at "
                  f"{guided.RING_MAX_SIGMA:g} sigma, and the default rule without it) or the clustered ones. Extra: "
                  "against the default rule with the same descriptors (first row of each).", "",
                  "| data | descriptors | link px, max sigma | planar pairs | links | links under a shift (chance) | "
                  "extra links | extra under a shift | P / R / F1 |", "|---|---|---|---|---|---|---|---|---|"]
        for name, found in links:
            for r in found:
                base = next(b for b in found if b["kind"] == r["kind"].split(",")[0])
                sc = r["scores"]
                lines.append(f"| {name} | {r['kind']} | {r['threshold']:g}, {r['max_sigma']:g} | "
                             f"{r['planar_pairs']} | {r['links']:,} | {r['chance']:,.0f} | "
                             f"{r['links'] - base['links']:+,} | {r['chance'] - base['chance']:+,.0f} | "
                             + ("links only |" if sc is None else
                                f"{sc.precision:.3f} / {sc.recall:.3f} / {sc.f1:.3f} |"))
    table = "\n".join(lines) + "\n"
    print(table)
    if args.out is not None:
        args.out.write_text(table)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
