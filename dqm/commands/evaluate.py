"""Compare QuickMatch with OpenCV BF / FLANN pairwise matching and their union-find tracks
on data with ground truth; write a markdown table, a JSON file and PR-curve plots.

DATA are dataset names (graf, wall, boat, bikes: Oxford homography sequences;
hotel: CMU hotel landmarks; scene or scene:SEED: a generated scene, no
download) or folders in the Oxford or CMU-hotel layout. Named datasets are
looked up under --data-root (default: $DQM_SHARED/data or ../shared/data).
Without DATA: all five real datasets plus a generated scene; real ones that
are absent are skipped with a note.

    dqm evaluate                          # the table in docs/evaluation.md
    dqm evaluate scene:3 --out-dir /tmp/ev
    dqm evaluate my_sequence/ --tol 3 --max-features 2000

Outputs in --out-dir: evaluation.md (settings, table, findings), evaluation.json
(every number and curve), pr_<data>.png, and with --figures also
matches_<data>.png (QuickMatch's matches of images 1-2, green = correct) and
clusters_<data>.png / sizes_<data>.png.
"""
from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Dict, List

import numpy as np

from .. import __version__, benchmark, evaluation, outputs
from ..vision import baselines
from ..core import DEFAULT_RHO
from ..vision.features import DEFAULT_PRESET, PRESETS
from ..validation import InputError

NAME = "evaluate"
HELP = "QuickMatch vs BF / FLANN (pairs and tracks) on ground truth: table + PR curves"


def add_arguments(p) -> None:
    p.add_argument("data", nargs="*", metavar="DATA",
                   help="graf | wall | boat | bikes | hotel | scene[:SEED] | FOLDER (default: all + scene)")
    p.add_argument("--data-root", default=None, help="folder holding oxford/ and cmu_hotel/")
    p.add_argument("--out-dir", default=None,
                   help="where evaluation.md, evaluation.json and plots go (default ./dqm-out/evaluate; "
                        "--out-dir docs regenerates the committed docs)")
    p.add_argument("--methods", default=",".join(benchmark.METHODS),
                   help="comma-separated subset of: " + ", ".join(benchmark.METHODS))
    p.add_argument("--rho", type=float, default=DEFAULT_RHO, help="QuickMatch's operating point")
    p.add_argument("--ratio", type=float, default=baselines.DEFAULT_RATIO, help="Lowe ratio operating point")
    p.add_argument("--rhos", default=",".join(f"{r:g}" for r in benchmark.DEFAULT_RHOS),
                   help="QuickMatch's PR-curve thresholds (comma-separated)")
    p.add_argument("--ratios", default=",".join(f"{r:g}" for r in benchmark.DEFAULT_RATIOS),
                   help="BF / FLANN PR-curve thresholds (comma-separated)")
    p.add_argument("--tol", type=float, default=5.0, help="pixel tolerance of a correct match (homographies)")
    p.add_argument("--preset", choices=sorted(PRESETS), default=DEFAULT_PRESET, help="SIFT settings")
    p.add_argument("--max-features", type=int, default=0, help="SIFT features per image, 0 = no limit")
    p.add_argument("--seed", type=int, default=0, help="seed of FLANN's randomised trees")
    p.add_argument("--figures", action="store_true", help="also draw matches, clusters and size histograms")
    p.add_argument("--quiet", action="store_true", help="no progress messages")


def _findings(results: Dict[str, List[benchmark.MethodResult]]) -> List[str]:
    """Computed (not hand-written) statements on where QuickMatch wins and loses."""
    out = []
    for name, rows in results.items():
        qm = next((r for r in rows if r.method == "quickmatch"), None)
        others = [r for r in rows if r.method != "quickmatch"]
        if qm is None or not others:
            continue
        tracks = [r for r in others if "-drop-" in r.method]
        bf1 = max(others, key=lambda r: r.scores.f1)
        bauc = max(others, key=lambda r: r.curve.auc())
        bor = max(others, key=lambda r: r.curve.best_f1()[0])
        qf, qat = qm.curve.best_f1()

        def word(win: bool) -> str:
            return "**wins**" if win else "**loses**"
        line = (f"- **{name}**: at the defaults QuickMatch {word(qm.scores.f1 > bf1.scores.f1)} in F1 "
                f"({qm.scores.f1:.3f} vs {bf1.scores.f1:.3f}, {bf1.label}); at each method's best threshold it "
                f"{word(qf > bor.curve.best_f1()[0])} ({qf:.3f} at rho {qat:g} vs {bor.curve.best_f1()[0]:.3f}, "
                f"{bor.label}); in PR AUC it {word(qm.curve.auc() > bauc.curve.auc())} "
                f"({qm.curve.auc():.3f} vs {bauc.curve.auc():.3f}, {bauc.label}).")
        if tracks:
            lost = [r.label for r in tracks if qm.scores.f1 <= r.scores.f1]
            line += (f" Default F1 against the {len(tracks)} track variants: beats {len(tracks) - len(lost)}"
                     + (f", loses to {'; '.join(lost)}" if lost else "") + ".")
            line += (f" Precision {qm.scores.precision:.3f} vs {max(r.scores.precision for r in tracks):.3f} "
                     f"(most precise track), recall {qm.scores.recall:.3f} vs "
                     f"{max(r.scores.recall for r in tracks):.3f} (highest-recall track).")
        fastest = min(rows, key=lambda r: r.time_s)
        if fastest.method != "quickmatch" and fastest.time_s < 0.8 * qm.time_s:
            line += f" Faster than QuickMatch ({qm.time_s:.2f} s): {fastest.label} ({fastest.time_s:.2f} s)."
        out.append(line)
    return out


def _markdown(args, results, benches, skipped, plots, total_s, load) -> str:
    cpu = os.cpu_count()
    cmd = "dqm evaluate " + " ".join(sys.argv[2:]) if sys.argv[1:2] == ["evaluate"] else "dqm evaluate"
    lines = [
        "# QuickMatch vs pairwise matching on ground truth",
        "",
        f"Generated by `{cmd}` (dqm {__version__}, {platform.python_implementation()} "
        f"{platform.python_version()}, {platform.machine()}, {cpu} CPU threads, load average {load} at the "
        f"start: times are noisy on a shared machine) in {total_s:.0f} s. "
        "Regenerate rather than edit; interpretation: `docs/evaluation-notes.md`.",
        "",
        "## Settings",
        "",
        f"- SIFT: OpenCV, preset `{args.preset}`, max features per image: {args.max_features or 'no limit'}; "
        "hotel (any preset): OpenCV SIFT described at the 30 labelled landmarks of every frame "
        "(24 px upright patches).",
        f"- QuickMatch: rho {args.rho:g} (default), Gaussian kernel; PR curve over rho {args.rhos}.",
        f"- BF / FLANN: every image pair (i < j, queries from i), Euclidean 2-NN, Lowe ratio {args.ratio:g}; "
        f"FLANN kd-trees {baselines.FLANN_INDEX_PARAMS['trees']} trees, {baselines.FLANN_SEARCH_PARAMS['checks']} "
        f"checks, seed {args.seed}; PR curve over ratio {args.ratios}.",
        "- Tracks: union-find of the pairwise matches; a track holding two features of one image is dropped "
        "whole (OpenMVG) or keeps the first-listed feature per image (Theia).",
        f"- Truth: Oxford / generated scenes: a pair is correct if the homography maps one keypoint within "
        f"{args.tol:g} px of the other; recall against the greedy one-to-one correspondences within {args.tol:g} px "
        "of every image pair. Hotel: same landmark; recall against all same-landmark pairs.",
        "- P, R, F1 count pairs of features (a cluster / track of k features implies k(k-1)/2 pairs). "
        "PR AUC: trapezoid area under the curve, extended flat to recall 0 (see dqm/evaluation.py).",
        "- C1 features: features not matched to every other-image feature of their connected component "
        "(matching not transitive); C2 tracks: components holding two features of one image. "
        "Counted on each method's output matches; clusters satisfy both by construction.",
        "- Time: matching only (QuickMatch call; all-pairs 2-NN search, + track building), seconds, "
        "on the machine above. SIFT extraction time is listed per dataset below.",
        "",
        "## Results",
        "",
        benchmark.markdown_table(results, benches),
        "Bold: best of the dataset. best F1 (at): the highest F1 along the method's threshold sweep and the "
        "threshold giving it (an oracle choice; the other columns are at the default threshold).",
        "",
        "## Where QuickMatch wins and loses (computed from the table)",
        "",
        *_findings(results),
        "",
        "## Data",
        "",
    ]
    for name, b in benches.items():
        lines.append(f"- {name}: {len(b)} features in {b.n_images} images "
                     f"(extraction {b.stats.get('time_extract', float('nan')):.1f} s)")
    for name, why in skipped:
        lines.append(f"- {name}: skipped ({why})")
    if plots:
        lines += ["", "## Plots", ""]
        for name, files in plots.items():
            lines.append(f"### {name}")
            lines.append("")
            for f in files:
                lines.append(f"![{name} {f.stem}]({f.name})")
            lines.append("")
    return "\n".join(lines).rstrip() + "\n"


def _figures(bench: benchmark.Benchmark, out_dir: Path, rho: float) -> List[Path]:
    from .. import plots
    from ..core import quickmatch

    r = quickmatch(bench.descriptors, bench.image_ids, rho=rho)
    files = []
    ids = bench.image_ids
    a, b = evaluation.cluster_pairs(r.labels, ids)
    sel = ((ids[a] == 0) & (ids[b] == 1)) | ((ids[a] == 1) & (ids[b] == 0))
    pa, pb = np.where(ids[a[sel]] == 0, a[sel], b[sel]), np.where(ids[a[sel]] == 0, b[sel], a[sel])
    fig = plots.pair_figure(bench.images[0], bench.images[1], bench.keypoints[pa, :2], bench.keypoints[pb, :2],
                            bench.correct(pa, pb), title=f"{bench.name}: QuickMatch (rho {rho:g}), images 0-1")
    files.append(plots.save(fig, out_dir / f"matches_{bench.name}.png"))
    big = [c for c in r.clusters(min_size=3)]
    big.sort(key=lambda c: (-len(c), int(c.min())))
    if big:
        fig = plots.clusters_figure(bench.images, bench.keypoints, ids, big[:6],
                                    point_ids=bench.point_ids,
                                    title=f"{bench.name}: the six largest QuickMatch clusters")
        files.append(plots.save(fig, out_dir / f"clusters_{bench.name}.png"))
    fig = plots.cluster_sizes_figure(r.labels, ids, title=f"{bench.name}: QuickMatch cluster sizes (rho {rho:g})")
    files.append(plots.save(fig, out_dir / f"sizes_{bench.name}.png"))
    return files


def _floats(text: str, name: str) -> List[float]:
    try:
        vals = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"{name} must be comma-separated numbers, got {text!r}") from None
    if not vals or any(not (np.isfinite(v) and v > 0) for v in vals):
        raise InputError(f"{name} must be positive numbers, got {text!r}")
    return vals


def run(args) -> int:
    from .. import plots

    t0 = time.perf_counter()
    load = f"{os.getloadavg()[0]:.1f}" if hasattr(os, "getloadavg") else "unknown"
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in benchmark.METHODS]
    if unknown or not methods:
        raise InputError(f"unknown method(s) {unknown}; choose from {', '.join(benchmark.METHODS)}")
    if args.max_features < 0:
        raise InputError("--max-features must be >= 0")
    rhos, ratios = _floats(args.rhos, "--rhos"), _floats(args.ratios, "--ratios")
    explicit = bool(args.data)
    specs = args.data or list(benchmark.DATASETS) + ["scene"]
    say = (lambda s: None) if args.quiet else (lambda s: print(s, file=sys.stderr, flush=True))
    out_dir = outputs.check_dir(args.out_dir or outputs.default_dir("evaluate"), "--out-dir")
    results: Dict[str, List[benchmark.MethodResult]] = {}
    benches: Dict[str, benchmark.Benchmark] = {}
    skipped = []
    plot_files: Dict[str, List[Path]] = {}
    for spec in specs:
        try:
            say(f"loading {spec}")
            bench = benchmark.load_benchmark(spec, args.data_root, preset=args.preset,
                                             max_features=args.max_features, tol=args.tol)
        except InputError as exc:
            if explicit:
                raise
            say(f"note: {spec} skipped: {exc}")
            skipped.append((spec, str(exc)))
            continue
        name = bench.name if bench.name not in results else f"{bench.name}-{len(results)}"
        rows = benchmark.evaluate(bench, methods, rho=args.rho, ratio=args.ratio, rhos=rhos, ratios=ratios,
                                  seed=args.seed, log=say)
        results[name] = rows
        benches[name] = bench
        fig = plots.pr_figure([r.curve for r in rows],
                              {r.method: (r.scores.recall, r.scores.precision) for r in rows},
                              labels=benchmark.METHODS,
                              title=f"{name}: {len(bench)} features, {bench.n_images} images")
        plot_files[name] = [plots.save(fig, out_dir / f"pr_{name}.png")]
        if args.figures:
            plot_files[name] += _figures(bench, out_dir, args.rho)
        if not args.quiet:
            print(benchmark.markdown_table({name: rows}, {name: bench}), flush=True)
    if not results:
        raise InputError("no dataset could be loaded: " + "; ".join(f"{s}: {w}" for s, w in skipped))
    total = time.perf_counter() - t0
    out_dir.mkdir(parents=True, exist_ok=True)
    md = _markdown(args, results, benches, skipped, plot_files, total, load)
    (out_dir / "evaluation.md").write_text(md)
    payload = {
        "dqm_version": __version__,
        "settings": {k: getattr(args, k) for k in ("rho", "ratio", "tol", "preset", "max_features", "seed")},
        "datasets": {name: {"n_features": len(benches[name]), "n_images": benches[name].n_images,
                            "kind": benches[name].kind, "stats": benches[name].stats,
                            "methods": [r.as_dict() for r in rows]} for name, rows in results.items()},
        "skipped": dict(skipped),
    }
    (out_dir / "evaluation.json").write_text(json.dumps(payload, indent=1))
    print(f"wrote {out_dir / 'evaluation.md'}, {out_dir / 'evaluation.json'} and "
          f"{sum(len(v) for v in plot_files.values())} plot(s) in {total:.0f} s")
    return 0
