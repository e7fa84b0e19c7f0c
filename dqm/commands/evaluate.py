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
    dqm evaluate --clusters clusters.npz graf         # score a CLUSTERS file (dqm match, dqm run)
    dqm evaluate --clusters clusters.npz              # ... against its own point_ids (generated data)

Outputs in --out-dir: evaluation.md (settings with the command line that
regenerates it, table, findings), evaluation.json (every number and curve),
pr_<data>.png, and with --figures also matches_<data>.png (QuickMatch's matches
of images 1-2, green = correct) and clusters_<data>.png / sizes_<data>.png.
<data> is the data-set name made safe for file names (scene:3 -> scene-3).

--clusters scores the clusters of a file as they are, with the code that scores
the QuickMatch row: against the file's point_ids, or with one DATA (homography
data: an Oxford-layout folder, graf ..., scene:SEED) against that data set's
homographies at the file's keypoints, after checking that the file's images are
the data set's (count, order, sizes). It prints the table row (P, R, F1, C1/C2)
and writes evaluation_<file>[_<data>].json (evaluation.json's layout).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import platform
import shlex
import time
from pathlib import Path

import numpy as np

from .. import __version__, benchmark, evaluation, outputs
from ..core import DEFAULT_RHO
from ..validation import InputError
from ..vision import baselines
from ..vision.features import DEFAULT_PRESET, EXTERNAL_PRESETS, PRESET_NAMES, PRESETS

LOG = logging.getLogger("dqm.commands")

NAME = "evaluate"
HELP = "QuickMatch vs BF / FLANN (pairs and tracks) on ground truth: table + PR curves"


def add_arguments(p) -> None:
    p.add_argument("data", nargs="*", metavar="DATA",
                   help="graf | wall | boat | bikes | hotel | scene[:SEED] | FOLDER (default: all + scene)")
    p.add_argument("--data-root", default=None, help="folder holding oxford/ and cmu_hotel/")
    p.add_argument("--out-dir", default=None,
                   help="where evaluation.md, evaluation.json and plots go (default ./dqm-out/evaluate; "
                        "--out-dir docs --overwrite regenerates the committed docs)")
    outputs.add_overwrite_option(p, help="replace the evaluation files and plots of an earlier run in --out-dir")
    p.add_argument("--methods", default=",".join(benchmark.METHODS),
                   help="comma-separated subset of: " + ", ".join(benchmark.METHODS))
    p.add_argument("--rho", type=float, default=DEFAULT_RHO, help="QuickMatch's operating point")
    p.add_argument("--ratio", type=float, default=baselines.DEFAULT_RATIO, help="Lowe ratio operating point")
    p.add_argument("--rhos", default=",".join(f"{r:g}" for r in benchmark.DEFAULT_RHOS),
                   help="QuickMatch's PR-curve thresholds (comma-separated)")
    p.add_argument("--ratios", default=",".join(f"{r:g}" for r in benchmark.DEFAULT_RATIOS),
                   help="BF / FLANN PR-curve thresholds (comma-separated)")
    p.add_argument("--tol", type=float, default=5.0, help="pixel tolerance of a correct match (homographies)")
    p.add_argument("--preset", choices=sorted(PRESET_NAMES), default=DEFAULT_PRESET, help="SIFT settings")
    p.add_argument("--max-features", type=int, default=0, help="SIFT features per image, 0 = no limit")
    p.add_argument("--seed", type=int, default=0, help="seed of FLANN's randomised trees")
    p.add_argument("--figures", action="store_true", help="also draw matches, clusters and size histograms")
    p.add_argument("--clusters", default=None, metavar="CLUSTERS.npz",
                   help="score this CLUSTERS file (dqm match, dqm run / coordinator) instead of running the methods: "
                        "against its point_ids (generated data), or with one DATA (Oxford-layout folder, graf ..., "
                        "scene:SEED) against that data set's homographies at its keypoints; prints one table row "
                        "and writes evaluation_<file>[_<data>].json in --out-dir")
    p.add_argument("--quiet", action="store_true", help="no per-dataset tables, no notes about skipped datasets")


def _preset_words(preset: str) -> str:
    """What a SIFT preset is, from its settings: detector parameters and descriptor kind."""
    from ..vision.features import ROOT_PRESETS

    if preset in EXTERNAL_PRESETS:
        return EXTERNAL_PRESETS[preset] + ", RootSIFT (L1-root) descriptors"
    params = PRESETS[preset]
    det = ", ".join(f"{k} {v:g}" for k, v in params.items()) if params else "OpenCV's default detector parameters"
    return det + (", RootSIFT descriptors" if preset in ROOT_PRESETS else ", plain SIFT descriptors")


def _option_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dqm evaluate", add_help=False)
    add_arguments(p)
    return p


def changed_options(args) -> list[tuple[str, object]]:
    """(long option, value) of every option of ``args`` that differs from its default, in parser order."""
    out = []
    for act in _option_parser()._actions:
        if act.option_strings and getattr(args, act.dest, act.default) != act.default:
            out.append((act.option_strings[-1], getattr(args, act.dest)))
    return out


def command_line(args) -> str:
    """The ``dqm evaluate`` command line that reproduces ``args``: DATA and every non-default option, quoted."""
    parts = ["dqm", "evaluate", *args.data]
    for opt, val in changed_options(args):
        parts += [opt] if isinstance(val, bool) else [opt, str(val)]
    return " ".join(shlex.quote(x) for x in parts)


def _markdown(args, methods, results, benches, skipped, plots, total_s, load) -> str:
    cpu = os.cpu_count()
    default = " (the default)"
    verify = [
        (f"- {benchmark.METHODS['quickmatch-verify']}: the QuickMatch clusters at rho {args.rho:g}, then per image "
        "pair OpenCV USAC (MAGSAC++) fits a fundamental matrix and a homography to the matches the clusters imply "
        "(4 px, the model chosen as COLMAP does, a pair verified with >= 15 inliers) and members that the verified "
        f"pairs reject are split off (dqm.vision.verify, OpenCV RNG seed {args.seed}). One operating point: no "
        "threshold sweep, so no best-threshold F1 and no PR AUC (\"-\"); its time is clustering plus verification.")
    ] if "quickmatch-verify" in methods else []
    from ..vision import guided as g

    guided = [
        (f"- {benchmark.METHODS['quickmatch-guided']}: the QuickMatch clusters verified as above, then per verified "
         "pair the features without a match in the other image are linked to their mutual nearest descriptor among "
         f"the other image's features that fit the pair's model within {g.DEFAULT_LINK_THRESHOLD:g} px (Lowe ratio "
         f"{g.DEFAULT_RATIO:g} among those, distance <= {g.DEFAULT_MAX_SIGMA:g} sigma; on a planar-or-panoramic pair "
         "the descriptors compared are made again from the images in one frame, upright: dqm.vision.rectify), and "
         "clusters join along the links where C2 and every verified pair allow (dqm.vision.guided; docs/sfm.md). "
         "One operating point; its time is clustering, verification and growth.")
    ] if "quickmatch-guided" in methods else []
    ours = [
        (f"- QuickMatch: rho {args.rho:g}{default if args.rho == DEFAULT_RHO else ''}, Gaussian kernel; PR curve over "
         f"rho {args.rhos}.")
    ] if "quickmatch" in methods else [
        f"- QuickMatch: rho {args.rho:g}{default if args.rho == DEFAULT_RHO else ''}, Gaussian kernel."
    ] if any(m.startswith("quickmatch-") for m in methods) else []
    pairwise = ([
        (f"- BF / FLANN: every image pair (i < j, queries from i), Euclidean 2-NN, Lowe ratio {args.ratio:g}"
        f"{default if args.ratio == baselines.DEFAULT_RATIO else ''}; "
        f"FLANN kd-trees {baselines.FLANN_INDEX_PARAMS['trees']} trees, {baselines.FLANN_SEARCH_PARAMS['checks']} "
        f"checks, seed {args.seed}; PR curve over ratio {args.ratios}."),
        ("- Tracks: union-find of the pairwise matches; a track holding two features of one image is dropped "
        "whole (OpenMVG) or keeps the first-listed feature per image (Theia)."),
    ] if any(not m.startswith("quickmatch") for m in methods) else [])
    if not any("-drop-" in m for m in methods):
        pairwise = pairwise[:1]
    lines = [
        "# QuickMatch vs pairwise matching on ground truth",
        "",
        (f"Generated by `{command_line(args)}` (dqm {__version__}, {platform.python_implementation()} "
        f"{platform.python_version()}, {platform.machine()}, {cpu} CPU threads, load average {load} at the "
        f"start: times are noisy on a shared machine) in {total_s:.0f} s. "
        "Regenerate rather than edit; interpretation: `docs/evaluation-notes.md`."),
        "",
        "## Settings",
        "",
        "- Methods (rows, in this order): "
        f"{'; '.join(benchmark.METHODS[m] for m in benchmark.METHODS if m in methods)}.",
        (f"- SIFT: {'pycolmap' if args.preset in EXTERNAL_PRESETS else 'OpenCV'}, preset `{args.preset}` "
        f"({'the default: ' if args.preset == DEFAULT_PRESET else ''}{_preset_words(args.preset)}), "
        f"max features per image: {args.max_features or 'no limit'}; "
        "hotel (any preset): OpenCV SIFT described at the 30 labelled landmarks of every frame "
        "(24 px upright patches)."),
        *ours,
        *verify,
        *guided,
        *pairwise,
        (f"- Truth: Oxford / generated scenes: a pair is correct if the homography maps one keypoint within "
        f"{args.tol:g} px of the other; recall against the greedy one-to-one correspondences within {args.tol:g} px "
        "of every image pair. Hotel: same landmark; recall against all same-landmark pairs."),
        ("- P, R, F1 count pairs of features (a cluster / track of k features implies k(k-1)/2 pairs). "
        "PR AUC: trapezoid area under the curve, extended flat to recall 0 (see dqm/evaluation.py)."),
        ("- C1 features: features not matched to every other-image feature of their connected component "
        "(matching not transitive); C2 tracks: components holding two features of one image. "
        "Counted on each method's output matches; clusters satisfy both by construction."),
        ("- Time: matching only (QuickMatch call; all-pairs 2-NN search, + track building), seconds, "
        "on the machine above. SIFT extraction time is listed per dataset below."),
        "",
        "## Results",
        "",
        benchmark.markdown_table(results, benches),
        ("Bold: best of the dataset. best F1 (at): the highest F1 along the method's threshold sweep and the "
        "threshold giving it (an oracle choice; the other columns are at the default threshold)."),
        "",
        "## Where QuickMatch wins and loses against the pairwise baselines (computed from the table)",
        "",
        ("Each QuickMatch variant against the best pairwise-baseline row of each measure (never one QuickMatch "
         "variant against another); what geometric verification changes in QuickMatch is listed separately.")
        if any(not m.startswith("quickmatch") for m in methods)
        else "No BF / FLANN method in this run: nothing to compare QuickMatch with.",
        "",
        *benchmark.findings(results),
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


@contextlib.contextmanager
def _no_figures_without_their_tables(plot_files: dict):
    """A stopped or failed evaluation removes the figures it wrote (``plot_files``: data set -> files): without
    the tables they belong to they would only block the rerun (its --out-dir check refuses pr_*.png)."""
    try:
        yield
    except BaseException:
        written = [outputs.written(f) for files in plot_files.values() for f in files]
        for f in written:
            f.unlink(missing_ok=True)
        if written:
            LOG.info("removed the %d figure(s) of this unfinished evaluation", len(written))
        raise


def _figures(bench: benchmark.Benchmark, out_dir: Path, rho: float, stem: str) -> list[Path]:
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
    files.append(plots.save(fig, out_dir / f"matches_{stem}.png"))
    big = [c for c in r.clusters(min_size=3)]
    big.sort(key=lambda c: (-len(c), int(c.min())))
    if big:
        fig = plots.clusters_figure(bench.images, bench.keypoints, ids, big[:6],
                                    point_ids=bench.point_ids,
                                    title=f"{bench.name}: the six largest QuickMatch clusters")
        files.append(plots.save(fig, out_dir / f"clusters_{stem}.png"))
    fig = plots.cluster_sizes_figure(r.labels, ids, title=f"{bench.name}: QuickMatch cluster sizes (rho {rho:g})")
    files.append(plots.save(fig, out_dir / f"sizes_{stem}.png"))
    return files


def _floats(text: str, name: str) -> list[float]:
    try:
        vals = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"{name} must be comma-separated numbers, got {text!r}") from None
    if not vals or any(not (np.isfinite(v) and v > 0) for v in vals):
        raise InputError(f"{name} must be positive numbers, got {text!r}")
    return vals


#: the options that apply to --clusters (the others choose how the methods run)
CLUSTERS_OPTIONS = ("--clusters", "--data-root", "--out-dir", "--tol", "--quiet", "--overwrite")
#: what dqm evaluate writes in --out-dir, refused there unless --overwrite
EVALUATION_FILES = ("evaluation.md", "evaluation.json", "pr_*.png", "matches_*.png", "clusters_*.png", "sizes_*.png")


def _load_clusters(path: str) -> dict:
    import zipfile

    from .. import io

    p = Path(path)
    if p.exists() and not zipfile.is_zipfile(p):
        raise InputError(f"--clusters {p}: not an .npz clusters file (an .npz is a zip archive of numpy arrays)")
    try:
        return io.load_clusters(p)
    except InputError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise InputError(f"--clusters {p}: not a readable clusters file ({type(exc).__name__}: {exc})") from None


def run_clusters(args) -> int:
    """``dqm evaluate --clusters``: score one CLUSTERS file (see :func:`dqm.benchmark.evaluate_clusters`)."""
    other = [opt for opt, _ in changed_options(args) if opt not in CLUSTERS_OPTIONS]
    if other:
        raise InputError(f"--clusters scores the file's clusters as they are; {', '.join(other)} "
                         f"{'does' if len(other) == 1 else 'do'} not apply (only {', '.join(CLUSTERS_OPTIONS[1:])})")
    if len(args.data) > 1:
        raise InputError(f"--clusters is scored against one DATA set, got {len(args.data)}: {' '.join(args.data)}")
    if not args.tol > 0:
        raise InputError(f"--tol must be positive (pixels), got {args.tol}")
    stem = benchmark.file_stem(Path(args.clusters).stem)
    out_dir = outputs.check_dir(args.out_dir or outputs.default_dir("evaluate"), "--out-dir",
                                (f"evaluation_{stem}.json", f"evaluation_{stem}_*.json"), overwrite=args.overwrite,
                                default=not args.out_dir)
    cl = _load_clusters(args.clusters)
    if not args.data and "point_ids" not in cl:
        raise InputError(f"--clusters {args.clusters} has no point_ids (ground truth of generated data); name the "
                         "data set it was matched from (DATA: an Oxford-layout folder, graf ..., scene:SEED)")
    source = benchmark.locate(args.data[0], args.data_root) if args.data else None
    bench, row = benchmark.evaluate_clusters(cl, source, tol=args.tol, origin=args.clusters)
    truth = (f"{bench.name}'s homographies, {args.tol:g} px" if bench.kind == "homography" else
             "the file's point_ids" if source is None else f"the file's point_ids ({bench.name})")
    s, v = row.scores, row.violations
    print(benchmark.markdown_table({bench.name: [row]}, {bench.name: bench}), end="")
    print(f"{args.clusters} against {truth}: precision {s.precision:.3f}, recall {s.recall:.3f}, F1 {s.f1:.3f} "
          f"({s.n_correct} of {s.n_predicted} implied pairs correct, {s.n_truth} true pairs); "
          f"C1 features {v.c1_features}, C2 tracks {v.c2_tracks}")
    out = out_dir / (f"evaluation_{stem}" + (f"_{benchmark.file_stem(bench.name)}" if source else "") + ".json")
    payload = {
        "dqm_version": __version__,
        "clusters": {"path": str(Path(args.clusters).resolve()), "params": cl.get("params", {})},
        "settings": {"tol": args.tol, "truth": bench.kind, "data": args.data[0] if args.data else None},
        "datasets": {bench.name: {"n_features": len(bench), "n_images": bench.n_images, "kind": bench.kind,
                                  "methods": [row.as_dict()]}},
    }
    outputs.write_json(out, payload)
    print(f"wrote {out}")
    return 0


def run(args) -> int:
    from .. import plots

    if args.quiet:  # errors only from the dqm loggers (-v narrates the steps)
        logging.getLogger("dqm").setLevel(logging.ERROR)
    if args.clusters:
        return run_clusters(args)
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
    out_dir = outputs.check_dir(args.out_dir or outputs.default_dir("evaluate"), "--out-dir", EVALUATION_FILES,
                                overwrite=args.overwrite, default=not args.out_dir)
    results: dict[str, list[benchmark.MethodResult]] = {}
    benches: dict[str, benchmark.Benchmark] = {}
    skipped = []
    plot_files: dict[str, list[Path]] = {}
    stems: dict[str, str] = {}  # data-set name -> its part of file names, unique in out_dir
    with _no_figures_without_their_tables(plot_files):
        for spec in specs:
            try:
                LOG.info("loading %s", spec)
                bench = benchmark.load_benchmark(spec, args.data_root, preset=args.preset,
                                                 max_features=args.max_features, tol=args.tol)
            except InputError as exc:
                if explicit:
                    raise
                LOG.warning("note: %s skipped: %s", spec, exc)  # shown by default; also listed in evaluation.md
                skipped.append((spec, str(exc)))
                continue
            name = bench.name if bench.name not in results else f"{bench.name}-{len(results)}"
            stems[name] = benchmark.file_stem(name, stems.values())
            rows = benchmark.evaluate(bench, methods, rho=args.rho, ratio=args.ratio, rhos=rhos, ratios=ratios,
                                      seed=args.seed)
            results[name] = rows
            benches[name] = bench
            fig = plots.pr_figure([r.curve for r in rows],
                                  {r.method: (r.scores.recall, r.scores.precision) for r in rows},
                                  labels=benchmark.METHODS,
                                  title=f"{name}: {len(bench)} features, {bench.n_images} images")
            plot_files[name] = [plots.save(fig, out_dir / f"pr_{stems[name]}.png")]
            if args.figures:
                plot_files[name] += _figures(bench, out_dir, args.rho, stems[name])
            if not args.quiet:
                print(benchmark.markdown_table({name: rows}, {name: bench}), flush=True)
        if not results:
            raise InputError("no dataset could be loaded: " + "; ".join(f"{s}: {w}" for s, w in skipped))
        total = time.perf_counter() - t0
        out_dir.mkdir(parents=True, exist_ok=True)
        md = _markdown(args, methods, results, benches, skipped, plot_files, total, load)
        outputs.write_text(out_dir / "evaluation.md", md)
        payload = {
            "dqm_version": __version__,
            "settings": {k: getattr(args, k) for k in ("rho", "ratio", "tol", "preset", "max_features", "seed")},
            "datasets": {name: {"n_features": len(benches[name]), "n_images": benches[name].n_images,
                                "kind": benches[name].kind, "stats": benches[name].stats,
                                "methods": [r.as_dict() for r in rows]} for name, rows in results.items()},
            "skipped": dict(skipped),
        }
        payload["settings"].update(methods=methods, command=command_line(args))
        outputs.write_text(out_dir / "evaluation.json", json.dumps(payload, indent=1))
        print(f"wrote {out_dir / 'evaluation.md'}, {out_dir / 'evaluation.json'} and "
              f"{sum(len(v) for v in plot_files.values())} plot(s) in {total:.0f} s")
        return 0
