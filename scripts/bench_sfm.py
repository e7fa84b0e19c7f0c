"""Structure from motion, end to end: dqm sfm against COLMAP's own pipeline, judged by the cameras (issue 35).

Every pipeline runs on the same photos in one run. COLMAP's is what a user gets from pycolmap with
its defaults (its SIFT, exhaustive matching and verification, the incremental mapper); dqm's are
``dqm sfm`` command lines (a subprocess each, timed from start to exit). With ``--gt DIR``
(Strecha ``*.camera`` files, or a COLMAP model) the cameras are compared with the ground truth:
the model is aligned by a similarity, and the table reports registered images, the median
rotation and centre errors, the pairwise pose AUC at 1, 2 and 5 degrees
(:mod:`dqm.vision.poses`), 3-D points, mean track length, mean reprojection error and the time
of each stage (extraction, matching, mapping, dqm's model-guided triangulation) and in all, then
each dqm row against COLMAP's as ratios and differences.

    python scripts/bench_sfm.py --images ../shared/data/strecha/entry-P10/images \\
        --gt ../shared/data/strecha/entry-P10/gt_cameras --out-dir docs/sfm/entry-P10 --subsets "0-3;3-6;all"
    python scripts/bench_sfm.py --images ../shared/data/sacre_coeur --out-dir docs/sfm/sacre_coeur
    python scripts/bench_sfm.py ... --pipelines colmap,dqm --seeds 0,1,2,3,4   # the spread over seeds

Pipelines are named configurations (:data:`PIPELINES`); ``--pipelines`` picks some (default:
:data:`DEFAULT_PIPELINES`), and a name ``dqm OPTIONS`` runs ``dqm sfm`` with those options.
``--seeds``: run every pipeline once per seed (COLMAP's
verification and mapper seeded too) and report each run and the mean, for the measurements
whose run-to-run spread matters. ``--max-images N``: the first N photos only (CI's small run).
Writes ``sfm.md`` (the table), ``sfm.json`` (every run) and ``sfm_poses.png`` (the cumulative
pose-error curves, with --gt) into ``--out-dir`` (default: a temporary folder).

Several ``--images`` folders make a **collection** of several scenes (issue 59): their photos are linked
into one folder, a sub-folder a scene, and every pipeline matches and maps them at once. Each scene is
scored in the model that holds most of its photos (registered, its cameras against that scene's
``--gt``, the model's points); over all models, the 3-D points seen in photos of two scenes, the image
pairs COLMAP's verification kept within and across scenes, dqm's clusters across scenes before
verification, and dqm's peak memory per stage.

    python scripts/bench_sfm.py --images ../shared/data/dtu/scan24/images ../shared/data/nerf_lego/images \\
        ../shared/data/strecha/entry-P10/images ../shared/data/sacre_coeur --gt ../shared/data/dtu/scan24/gt_cameras \\
        ../shared/data/nerf_lego/gt_cameras ../shared/data/strecha/entry-P10/gt_cameras - --pipelines colmap,dqm
"""
from __future__ import annotations

import argparse
import json
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: the pipelines: None = COLMAP's own; a list = the options of a ``dqm sfm`` command line
PIPELINES: dict[str, list[str] | None] = {
    "colmap": None,
    "dqm": [],
    "dqm --preset colmap": ["--preset", "colmap"],
    "dqm --mapper global": ["--mapper", "global"],
    "dqm --verify": ["--verify"],
    "dqm --guided": ["--guided"],
    "dqm --preset rootsift": ["--preset", "rootsift"],
    "dqm --preset rootsift --guided (the default before)": ["--preset", "rootsift", "--guided"],
    "colmap --mapper global": None,
    "colmap --single-camera": None,
}
#: what runs without --pipelines
DEFAULT_PIPELINES = ["colmap", "dqm", "dqm --preset colmap", "dqm --guided",
                     "dqm --preset rootsift --guided (the default before)"]
AUC_KEYS = ("1", "2", "5")


def run_colmap(name: str, images: Path, work: Path, seed: int | None, truth) -> dict:
    from dqm.vision import poses
    from dqm.vision.sfm import colmap_pipeline, model_numbers

    t0 = time.perf_counter()
    models, times = colmap_pipeline(images, work, seed=seed, mapper="global" if "global" in name else "incremental",
                                    single_camera="--single-camera" in name)
    times["total"] = time.perf_counter() - t0
    rec = models[0].rec if models else None
    out = {"model": model_numbers(rec), "times": times}
    if truth is not None and rec is not None:
        out["poses"] = poses.evaluate_poses(poses.poses_of(rec), truth).as_dict()
    return out


class PipelineFailed(SystemExit):
    """A pipeline of the run failed: the run stops, and its working folder (what the pipelines wrote) is kept."""


def run_dqm(options: list[str], images: Path, work: Path, seed: int | None, gt: Path | None) -> dict:
    cmd = [sys.executable, "-m", "dqm", "sfm", str(images), "--out", str(work), "--quiet", *options]
    if seed is not None:
        cmd += ["--seed", str(seed)]
    if gt is not None:
        cmd += ["--gt", str(gt)]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    report = work / "sfm.json"
    if not report.exists():
        raise PipelineFailed(f"bench_sfm: {' '.join(cmd)} failed (exit {p.returncode}): {p.stderr.strip()[-500:]}")
    out = json.loads(report.read_text())
    out["times"]["total"] = wall  # start to exit, Python's start and imports included
    return out


def fmt(x, spec: str, missing: str = "-") -> str:
    return missing if x is None or x != x else format(x, spec)


def table(results: dict, with_gt: bool, n_images: int) -> list[str]:
    """The markdown table: one row per run (the mean row per pipeline when there are several seeds)."""
    head = ["pipeline", "registered"]
    if with_gt:
        head += ["rot. err. (°)", "centre err.", "AUC@1°", "AUC@2°", "AUC@5°"]
    head += ["3-D points", "track", "reproj. (px)", "extract s", "match s", "map s", "triang. s", "total s"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, runs in results.items():
        for label, r in ([(f"{name} (seed {r['seed']})", r) for r in runs] if len(runs) > 1 else []) + \
                [(name if len(runs) == 1 else f"**{name}: mean of {len(runs)}**", mean_run(runs))]:
            m, t = r["model"], r["times"]
            cells = [label, f"{m['registered']} / {n_images}"]
            if with_gt:
                p = r.get("poses") or {}
                auc = p.get("auc", {})
                cells += [fmt(p.get("median_rotation_deg"), ".3f"), fmt(p.get("median_centre_error"), ".4f")]
                cells += [fmt(auc.get(k), ".3f") for k in AUC_KEYS]
            cells += [f"{m['points']:,}", fmt(m["track"], ".2f"), fmt(m["reproj"], ".3f")]
            match = t.get("match", 0.0) + t.get("export", 0.0)  # dqm's export runs COLMAP's verification
            cells += [fmt(t.get("extract"), ".1f"), fmt(match, ".1f"), fmt(t.get("map"), ".1f"),
                      fmt(t.get("triangulate"), ".1f"), fmt(t["total"], ".1f")]
            lines.append("| " + " | ".join(cells) + " |")
    return lines


def mean_run(runs: list[dict]) -> dict:
    """The mean of several runs of one pipeline (every number averaged; registered: the fewest)."""
    if len(runs) == 1:
        return runs[0]
    import numpy as np

    out = {"model": {}, "times": {}}
    for k in runs[0]["model"]:
        vals = [np.nan if r["model"][k] is None else r["model"][k] for r in runs]  # None: no model (sfm.json)
        out["model"][k] = min(vals) if k == "registered" else (
            int(round(np.mean(vals))) if k == "points" else float(np.mean(vals)))
    for k in runs[0]["times"]:
        out["times"][k] = float(np.mean([r["times"].get(k, 0.0) for r in runs]))
    if all("poses" in r for r in runs):
        p0 = runs[0]["poses"]
        out["poses"] = {k: float(np.mean([r["poses"][k] for r in runs])) for k in p0 if k != "auc"}
        out["poses"]["auc"] = {k: float(np.mean([r["poses"]["auc"][k] for r in runs])) for k in p0["auc"]}
    return out


def against_colmap(results: dict, with_gt: bool) -> list[str]:
    """Each dqm pipeline against COLMAP's (means over seeds), measured in this run, with the issue's targets."""
    if "colmap" not in results:
        return []
    c = mean_run(results["colmap"])
    if not c["model"]["registered"]:
        return []
    ok = lambda x: "met" if x else "missed"  # noqa: E731
    out = ["", "Against COLMAP, measured in this run (targets: pose AUC >= COLMAP's at 1, 2 and 5 degrees, 3-D "
           "points >= 1x, every image registered, reprojection error <= COLMAP's + 0.1 px, end-to-end time <= 1x):", ""]
    for name, runs in results.items():
        if name.startswith("colmap"):
            continue
        r = mean_run(runs)
        m, cm = r["model"], c["model"]
        if not m["registered"]:
            out.append(f"- {name}: no model")
            continue
        parts = []
        if with_gt and "poses" in r and "poses" in c:
            for k in AUC_KEYS:
                a, b = r["poses"]["auc"][k], c["poses"]["auc"][k]
                parts.append(f"AUC@{k}° {a:.3f} vs {b:.3f} ({ok(a >= b)})")
        parts.append(f"points x{m['points'] / max(cm['points'], 1):.2f} ({ok(m['points'] >= cm['points'])})")
        parts.append(f"track x{m['track'] / cm['track']:.3f} ({ok(m['track'] >= cm['track'])})")
        parts.append(f"reprojection {m['reproj'] - cm['reproj']:+.3f} px ({ok(m['reproj'] <= cm['reproj'] + 0.1)})")
        parts.append(f"registered {m['registered']} ({ok(m['registered'] >= cm['registered'])})")
        t, ct = r["times"]["total"], c["times"]["total"]
        parts.append(f"time x{t / ct:.2f} ({ok(t <= ct)}; mapping {r['times']['map']:.1f} s vs "
                     f"{c['times']['map']:.1f} s)")
        out.append(f"- {name}: " + ", ".join(parts))
    return out


def pose_figure(results: dict, truth, path: Path, title: str) -> None:
    """The cumulative pairwise pose error of each pipeline's first run (the AUC is the area up to 1/2/5°)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    for name, runs in results.items():
        errors = runs[0].get("pair_errors")
        if errors is None:
            continue
        e = np.sort(np.asarray(errors, float))
        ax.step(np.r_[0, e], np.r_[0, np.arange(1, len(e) + 1) / len(e)], where="post", label=name)
    for t in (1, 2, 5):
        ax.axvline(t, color="0.8", lw=0.8, zorder=0)
    ax.set_xlim(0, 5)
    ax.set_ylim(0, 1)
    ax.set_xlabel("pairwise pose error, max(rotation, translation direction) (degrees)")
    ax.set_ylabel("fraction of image pairs")
    ax.set_title(title)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=Path, required=True, nargs="+",
                    help="the photos (one folder); several folders: a collection of several scenes, matched and "
                         "mapped at once (one sub-folder a scene), each scene scored in the model that holds most of "
                         "its photos")
    ap.add_argument("--gt", type=Path, default=None, nargs="+",
                    help="ground-truth cameras: Strecha *.camera files or a COLMAP model; with several --images, "
                         "one per folder in their order ('-' for none)")
    ap.add_argument("--out-dir", type=Path, default=None, help="where sfm.md, sfm.json, sfm_poses.png go "
                                                               "(default: a temporary folder)")
    ap.add_argument("--pipelines", default=None,
                    help="comma-separated names of PIPELINES (default: " + ", ".join(DEFAULT_PIPELINES) + ")")
    ap.add_argument("--seeds", default=None, help="comma-separated seeds: one run of every pipeline per seed")
    ap.add_argument("--max-images", type=int, default=0, help="the first N photos only")
    ap.add_argument("--subsets", default=None,
                    help="also run every pipeline on these subsets of the photos, e.g. '0-3;3-6;0,2,4,6,8;all' "
                         "(indices in name order), and tabulate AUC@1 (points without --gt) per subset")
    args = ap.parse_args()
    chosen = DEFAULT_PIPELINES if args.pipelines is None else [x.strip() for x in args.pipelines.split(",")
                                                               if x.strip()]
    for c in chosen:  # any other dqm sfm command line: "dqm --rho 1.0 --preset rootsift"
        if c not in PIPELINES and c.split()[:1] == ["dqm"]:
            PIPELINES[c] = shlex.split(c)[1:]
    unknown = [c for c in chosen if c not in PIPELINES]
    if unknown or not chosen:
        sys.exit(f"bench_sfm: unknown pipeline(s) {unknown}; choose from: " + "; ".join(PIPELINES)
                 + "; or any 'dqm OPTIONS' of dqm sfm")
    try:
        seeds = [None] if args.seeds is None else [int(s) for s in args.seeds.split(",")]
    except ValueError:
        sys.exit(f"bench_sfm: --seeds takes integers separated by commas, got {args.seeds!r}")
    try:
        import pycolmap  # noqa: F401
    except ImportError:
        sys.exit("bench_sfm: needs pycolmap (pip install 'dqm[colmap]')")

    for folder in args.images:
        if not folder.is_dir():
            sys.exit(f"bench_sfm: no image folder {folder}")
    gts = [None if g is None or str(g) == "-" else g for g in (args.gt or [None] * len(args.images))]
    if len(gts) != len(args.images):
        sys.exit(f"bench_sfm: {len(args.images)} image folders and {len(gts)} --gt folders: give one each ('-': none)")
    if len(args.images) > 1 and (args.subsets or args.max_images):
        sys.exit("bench_sfm: --subsets and --max-images take one image folder")
    if args.out_dir is not None and args.out_dir.exists() and any(args.out_dir.iterdir()):
        sys.exit(f"bench_sfm: --out-dir {args.out_dir} is not empty")
    work = Path(tempfile.mkdtemp(prefix="dqm-bench-sfm-"))
    out_dir = args.out_dir or work / "out"
    out_dir.mkdir(parents=True, exist_ok=True)
    kept = False
    try:
        if len(args.images) > 1:
            return collection_main(chosen, seeds, args.images, gts, work, out_dir)
        args.images, args.gt = args.images[0], gts[0]
        return single_main(chosen, seeds, args, work, out_dir)
    except PipelineFailed as failed:  # what the pipelines computed before the failure stays, for a look
        kept = True
        raise PipelineFailed(f"{failed.code}\nbench_sfm: the run's working folder is kept: {work}") from None
    finally:
        if args.out_dir is not None and not kept:
            shutil.rmtree(work, ignore_errors=True)


def single_main(chosen, seeds, args, work: Path, out_dir: Path) -> int:
    """One image folder (``args.images``, its cameras ``args.gt``): every pipeline, seed and subset on it, the
    tables and the figure into ``out_dir``."""
    from dqm.vision import features

    paths = features.collect_images([str(args.images)])
    if args.max_images:
        paths = paths[: args.max_images]
    subsets = parse_subsets(args.subsets, len(paths)) if args.subsets else [list(range(len(paths)))]
    full = None
    for k, subset in enumerate(subsets):
        chosen_paths = [paths[i] for i in subset]
        results, truth = run_pipelines(chosen, seeds, chosen_paths, args.gt, work / f"subset{k}")
        label = subset_label(subset, len(paths))
        full = (results, truth, chosen_paths) if len(subset) == len(paths) or full is None else full
        if args.subsets:
            SUBSET_RESULTS.append((label, results))
    results, truth, chosen_paths = full
    cpu = platform_line()
    lines = table(results, truth is not None, len(chosen_paths))
    lines += against_colmap(results, truth is not None)
    if args.subsets:
        lines += ["", f"Every pipeline on {len(subsets)} subsets of the photos (image indices in name order):", ""]
        lines += subset_table(SUBSET_RESULTS, truth is not None)
    lines += ["", f"One run per pipeline and seed on {cpu}; dqm's times are whole `dqm sfm` processes, "
                  f"COLMAP's its three pycolmap calls in this process. Match s: dqm's QuickMatch plus the "
                  f"export with COLMAP's verification; COLMAP's exhaustive matching with its verification."]
    (out_dir / "sfm.md").write_text("\n".join(lines) + "\n")
    (out_dir / "sfm.json").write_text(json.dumps({"images": str(args.images), "n_images": len(chosen_paths),
                                                   "gt": None if args.gt is None else str(args.gt),
                                                   "machine": cpu, "results": results,
                                                   "subsets": SUBSET_RESULTS}, indent=1) + "\n")
    if truth is not None:
        pose_figure(results, truth, out_dir / "sfm_poses.png", f"{args.images.parent.name}/{args.images.name}: "
                                                               "cameras against ground truth")
    print("\n".join(lines))
    print(f"wrote {out_dir / 'sfm.md'}, {out_dir / 'sfm.json'}"
          + (f", {out_dir / 'sfm_poses.png'}" if truth is not None else ""))
    return 0


#: (subset label, results) of every subset, with --subsets
SUBSET_RESULTS: list = []


def parse_subsets(text: str, n: int) -> list[list[int]]:
    """``"0-3;0,2,4;all"``: image indices (name order) and ranges, one subset per ``;``-separated item."""
    out = []
    for item in text.split(";"):
        item = item.strip()
        if item == "all":
            out.append(list(range(n)))
            continue
        idx = []
        try:
            for part in item.split(","):
                a, _, b = part.partition("-")
                idx += list(range(int(a), int(b) + 1)) if b else [int(a)]
        except ValueError:
            sys.exit(f"bench_sfm: --subsets item {item!r}: indices like 0-3 or 0,2,4, or all")
        if len(idx) < 2 or min(idx) < 0 or max(idx) >= n:
            sys.exit(f"bench_sfm: --subsets item {item!r}: needs 2+ indices in 0..{n - 1}")
        out.append(sorted(set(idx)))
    return out


def subset_label(subset: list[int], n: int) -> str:
    if len(subset) == n:
        return f"all {n}"
    runs, start = [], subset[0]
    for a, b in zip(subset, subset[1:] + [None]):
        if b != a + 1:
            runs.append(str(start) if start == a else f"{start}-{a}")
            start = b
    return ",".join(runs)


def subset_table(subsets: list, with_gt: bool) -> list[str]:
    """AUC@1° (or points without ground truth) of every pipeline on every subset, with the mean, the
    minimum and the number of subsets where it is at least COLMAP's."""
    names = list(subsets[0][1])
    key = "AUC@1°" if with_gt else "3-D points"

    def value(results, name):
        r = mean_run(results[name])
        if with_gt:
            return (r.get("poses") or {}).get("auc", {}).get("1", 0.0)
        return r["model"]["points"]

    head = ["pipeline"] + [label for label, _ in subsets] + ["mean", "min", "mean AUC@2°/5°" if with_gt else "",
                                                             ">= COLMAP's"]
    lines = [f"{key} per subset:", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name in names:
        vals = [value(results, name) for _, results in subsets]
        cells = [name] + [fmt(v, ".3f" if with_gt else ",.0f") for v in vals]
        spec = ".3f" if with_gt else ",.0f"
        cells += [fmt(sum(vals) / len(vals), spec), fmt(min(vals), spec)]
        if with_gt:
            m2 = [mean_run(res[name]).get("poses", {}).get("auc", {}) for _, res in subsets]
            a2, a5 = (sum(a.get(k, 0) for a in m2) / len(m2) for k in ("2", "5"))
            cells.append(f"{a2:.3f} / {a5:.3f}")
        else:
            cells.append("")
        if "colmap" in names and name != "colmap":
            wins = sum(value(res, name) >= value(res, "colmap") for _, res in subsets)
            cells.append(f"{wins} of {len(subsets)}")
        else:
            cells.append("")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def read_truth(gt, names):
    """The ground-truth cameras of these photos (``poses.restrict``), or the script's exit with its one line."""
    from dqm.validation import InputError
    from dqm.vision import poses

    try:
        return poses.restrict(poses.read_ground_truth(gt), names, f"--gt {gt}")
    except InputError as exc:
        sys.exit(f"bench_sfm: {exc}")


def each_run(chosen, seeds, work: Path, image_dir: Path, truth=None, gt=None, options=()):
    """``(name, run_dir, run)`` of every chosen pipeline once per seed on ``image_dir``: COLMAP's pipeline (scored
    against ``truth``) or ``dqm sfm`` with its options and ``options`` (``--gt gt``), each in its own folder."""
    for name in chosen:
        for seed in seeds:
            run_dir = work / f"run{len(list(work.iterdir()))}"
            if PIPELINES[name] is None:
                r = run_colmap(name, image_dir, run_dir, seed, truth)
            else:
                r = run_dqm(PIPELINES[name] + list(options), image_dir, run_dir, seed, gt)
            r["seed"] = seed
            yield name, run_dir, r


def run_pipelines(chosen, seeds, paths, gt, work: Path):
    """Every chosen pipeline (once per seed) on these photos: {name: [run, ...]} and the ground truth used."""
    from dqm.vision import poses

    work.mkdir(parents=True)
    image_dir = work / "images"
    image_dir.mkdir()
    for p in paths:  # the mappers read one folder; link the chosen photos there
        (image_dir / p.name).symlink_to(p.resolve())
    truth = read_truth(gt, [p.name for p in paths]) if gt is not None else None
    results: dict[str, list[dict]] = {}
    for name, run_dir, r in each_run(chosen, seeds, work, image_dir, truth, gt):
        if truth is not None:
            model = run_dir / "sparse"
            best = max(model.iterdir(), key=lambda d: len(poses.read_colmap_model(d))) \
                if model.is_dir() and any(model.iterdir()) else None
            est = poses.read_colmap_model(best) if best is not None else {}
            r["pair_errors"] = poses.relative_errors(est, truth, sorted(truth)).tolist()
        results.setdefault(name, []).append(r)
        m, t, seed = r["model"], r["times"], r["seed"]
        auc = r.get("poses", {}).get("auc", {})
        print(f"[{len(paths)} images] {name}" + ("" if seed is None else f" (seed {seed})")
              + f": {m['registered']}/{len(paths)} registered, {m['points']:,} points, track "
              + f"{fmt(m['track'], '.2f')}, "
              + (f"AUC@1/2/5 {'/'.join(fmt(auc.get(k), '.3f') for k in AUC_KEYS)}, " if auc else "")
              + f"{t['total']:.1f} s", flush=True)
    return results, truth


def platform_line() -> str:
    """The CPU and its SIMD level, for the record (machines differ between sessions)."""
    import os
    import platform

    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    flags = ""
    try:
        text = Path("/proc/cpuinfo").read_text()
        flags = "AVX-512 VNNI" if "avx512_vnni" in text else "AVX-512" if "avx512f" in text else \
            "AVX2" if "avx2" in text else "no AVX2"
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} cores, {flags}"



# ---------------------------------------------------------------------------------------------------------------------
# A collection of several scenes in one folder (--images A B C ...): one model per scene expected


def scene_name(folder: Path) -> str:
    """A short name for a scene's photo folder: its path's last parts without ``images`` (``dtu/scan24``)."""
    parts = [p for p in folder.resolve().parts if p != "images"]
    return "-".join(parts[-2:]) if parts[-2:-1] and parts[-2] in ("dtu", "strecha") else parts[-1]


def link_collection(folders: list[Path], image_dir: Path) -> dict[str, str]:
    """Every folder's photos linked under ``image_dir/<scene>/``; ``{image name: scene}`` (names as the mappers
    give them, relative to ``image_dir``)."""
    from dqm.vision import features

    scene_of = {}
    for folder in folders:
        scene = scene_name(folder)
        (image_dir / scene).mkdir(parents=True)
        for p in features.collect_images([str(folder)]):
            (image_dir / scene / p.name).symlink_to(p.resolve())
            scene_of[f"{scene}/{p.name}"] = scene
    return scene_of


def verified_by_scene_pair(database: Path, scene_of: dict[str, str]) -> dict[str, int]:
    """Image pairs COLMAP's verification kept (15+ inliers: dqm.vision.colmap.verified_pairs), counted by scene
    pair (``a|b``, a <= b)."""
    from dqm.vision.sfm import verified_name_pairs

    out: dict[str, int] = {}
    for a, b, _ in verified_name_pairs(database):
        key = "|".join(sorted((scene_of[a], scene_of[b])))
        out[key] = out.get(key, 0) + 1
    return out


def run_clusters(run_dir: Path, scene_of: dict[str, str]):
    """dqm's clusters (its CLUSTERS file), every feature's scene (an index into the sorted scene names) and those
    names, read once for :func:`clusters_across_scenes` and :func:`mapper_input_by_scene`; the images named as
    the run's database names them (dqm's image k is the database's image k + 1)."""
    import numpy as np
    import pycolmap

    z = np.load(run_dir / "clusters.npz", allow_pickle=False)
    db = pycolmap.Database.open(str(run_dir / "database.db"))
    try:
        names = [im.name for im in sorted(db.read_all_images(), key=lambda im: im.image_id)]
    finally:
        db.close()
    scenes = sorted(set(scene_of.values()))
    code = np.array([scenes.index(scene_of[n]) for n in names])
    return z["labels"], z["image_ids"], code[z["image_ids"]], scenes


def clusters_across_scenes(labels, scene) -> dict:
    """dqm's clusters with members in images of two scenes or more, before verification (:func:`run_clusters`'
    arrays)."""
    import numpy as np

    from dqm.vision.sfm import clusters_across

    return {"clusters": int(len(clusters_across(labels, scene))),
            "of_multi_image_clusters": int((np.bincount(labels) > 1).sum())}


def mapper_input_by_scene(labels, image_ids, scene, scenes, rule: str = "all") -> dict:
    """Per scene (:func:`run_clusters`' arrays), what dqm's clusters hand the mapper (the matches of ``rule``, the
    run's ``--cluster-matches``: dqm.vision.colmap.cluster_pairs, each cluster cut to its members in the scene):
    its features, the observations in clusters of 2+, the matches, their ratio, the largest cluster and the share
    of the matches in clusters of 10 or more; and ``apart``: the share of one pair scan over all the features that
    matching each scene apart would cost, sum(n_s^2) / (sum n_s)^2."""
    import numpy as np

    from dqm.vision.colmap import cluster_pairs

    out: dict = {"rule": rule, "scenes": {}}
    for k, name in enumerate(scenes):
        mine = scene == k
        lab, ids = labels[mine], image_ids[mine]
        _, inverse, sizes = np.unique(lab, return_inverse=True, return_counts=True)
        pairs = cluster_pairs(lab, ids, rule)
        firsts = np.concatenate([m[:, 0] for m in pairs.values()]) if pairs else np.zeros(0, np.int64)
        of_pair = sizes[inverse.ravel()[firsts]]  # each match's cluster size
        out["scenes"][name] = {"features": int(len(lab)), "observations": int(sizes[sizes > 1].sum()),
                               "matches": int(len(firsts)), "largest": int(sizes.max(initial=0)),
                               "matches_in_clusters_of_10": float((of_pair >= 10).sum() / max(len(firsts), 1))}
    n = np.array([e["features"] for e in out["scenes"].values()], np.float64)
    out["apart"] = float((n ** 2).sum() / max(n.sum() ** 2, 1.0))
    return out


def score_collection(run_dir: Path, scene_of: dict[str, str], truths: dict, folders: list[str] | None = None) -> dict:
    """Per scene: the model holding most of its photos, its photos registered there, its cameras against the
    scene's ground truth (pairs among the scene's photos) and its points; over all models: points seen in
    photos of two scenes, models made."""
    import pycolmap

    from dqm.vision import poses

    # dqm sfm's report names its models' folders (a scene redone alone: scenes/<k>/sparse/0); else sparse/*
    dirs = [run_dir / f for f in folders] if folders is not None else \
        sorted(d for d in (run_dir / "sparse").iterdir() if d.is_dir()) if (run_dir / "sparse").is_dir() else []
    models = [pycolmap.Reconstruction(str(d)) for d in dirs]
    mixed = 0
    for rec in models:
        names = {i: im.name for i, im in rec.images.items()}
        for point in rec.points3D.values():
            if len({scene_of[names[el.image_id]] for el in point.track.elements}) > 1:
                mixed += 1
    out = {"models": len(models), "points_seen_from_two_scenes": mixed, "scenes": {}}
    for scene in sorted(set(scene_of.values())):
        photos = [n for n, s in scene_of.items() if s == scene]
        best, held = None, 0
        for rec in models:
            k = sum(1 for im in rec.images.values() if im.has_pose and scene_of[im.name] == scene)
            if k > held:
                best, held = rec, k
        entry = {"photos": len(photos), "registered": held,
                 "points": best.num_points3D() if best is not None else 0,
                 "model_images": best.num_reg_images() if best is not None else 0}
        if scene in truths:
            est = {n.split("/", 1)[1]: p for n, p in (poses.poses_of(best).items() if best is not None else [])
                   if scene_of[n] == scene}
            entry["poses"] = poses.evaluate_poses(est, truths[scene]).as_dict() if est else None
        out["scenes"][scene] = entry
    return out


def run_collection(chosen, seeds, folders: list[Path], gts: list, work: Path) -> tuple[dict, dict]:
    """Every chosen pipeline on the photos of all the folders at once (one folder of links, one sub-folder a
    scene): {name: [run, ...]}, each run with its per-scene scores, and the scenes' photo counts."""
    work.mkdir(parents=True)
    image_dir = work / "images"
    scene_of = link_collection(folders, image_dir)
    truths = {}
    for folder, gt in zip(folders, gts):
        if gt is not None:
            scene = scene_name(folder)
            truths[scene] = read_truth(gt, [n.split("/", 1)[1] for n, s in scene_of.items() if s == scene])
    results: dict[str, list[dict]] = {}
    for name, run_dir, r in each_run(chosen, seeds, work, image_dir, options=["--recursive"]):
        if (run_dir / "clusters.npz").exists():  # dqm's runs
            labels, image_ids, scene, scenes = run_clusters(run_dir, scene_of)
            r["clusters_across_scenes"] = clusters_across_scenes(labels, scene)
            rule = json.loads((run_dir / "sfm.json").read_text())["options"].get("cluster_matches", "all")
            r["mapper_input"] = mapper_input_by_scene(labels, image_ids, scene, scenes, rule)
        folders = [m["folder"] for m in r["models"]] if "models" in r else None  # dqm's runs
        r["collection"] = score_collection(run_dir, scene_of, truths, folders)
        r["verified_pairs"] = verified_by_scene_pair(run_dir / "database.db", scene_of)
        results.setdefault(name, []).append(r)
        c = r["collection"]
        print(f"[collection of {len(scene_of)} photos] {name}: {c['models']} models, " + "; ".join(
            f"{s} {e['registered']}/{e['photos']}" for s, e in c["scenes"].items())
            + f", {c['points_seen_from_two_scenes']} points seen from two scenes, {r['times']['total']:.1f} s",
            flush=True)
    counts = {s: sum(1 for v in scene_of.values() if v == s) for s in sorted(set(scene_of.values()))}
    return results, counts


def collection_main(chosen, seeds, folders, gts, work: Path, out_dir: Path) -> int:
    """The collection run: its tables into sfm.md, every run into sfm.json."""
    results, counts = run_collection(chosen, seeds, folders, gts, work / "collection")
    cpu = platform_line()
    lines = [f"{sum(counts.values())} photos of {len(counts)} scenes in one folder: "
             + ", ".join(f"{s} ({n})" for s, n in counts.items()), ""]
    lines += collection_table(results, counts)
    lines += ["", f"One run per pipeline on {cpu}; dqm's times are whole `dqm sfm` processes, COLMAP's its three "
                  "pycolmap calls in this process. Each scene is scored in the model that holds most of its photos; "
                  "its AUC over the pairs of its photos with ground truth (an unregistered photo's pairs count as "
                  "wrong)."]
    (out_dir / "sfm.md").write_text("\n".join(lines) + "\n")
    (out_dir / "sfm.json").write_text(json.dumps({"images": [str(f) for f in folders], "scenes": counts,
                                                   "gt": [None if g is None else str(g) for g in gts],
                                                   "machine": cpu, "results": results}, indent=1) + "\n")
    print("\n".join(lines))
    print(f"wrote {out_dir / 'sfm.md'}, {out_dir / 'sfm.json'}")
    return 0


def collection_table(results: dict, counts: dict) -> list[str]:
    """Per scene and pipeline: registered, AUC@1/2/5, points; then per pipeline the totals and the checks."""
    lines = ["| scene | pipeline | registered | AUC@1° | AUC@2° | AUC@5° | 3-D points (its model) |",
             "|---|---|---|---|---|---|---|"]
    for scene, n in counts.items():
        for name, runs in results.items():
            e = runs[0]["collection"]["scenes"][scene]
            auc = (e.get("poses") or {}).get("auc", {})
            lines.append(f"| {scene} | {name} | {e['registered']} / {n} | "
                         + " | ".join(fmt(auc.get(k), ".3f") for k in AUC_KEYS) + f" | {e['points']:,} |")
    lines += ["", "| pipeline | models | points seen from two scenes | verified pairs within scenes | verified pairs "
                  "across scenes | clusters across scenes (before verification) | extract s | match s | map s | "
                  "triang. s | total s | peak memory by stage |", "|" + "---|" * 12]
    for name, runs in results.items():
        r = runs[0]
        c, t, v = r["collection"], r["times"], r["verified_pairs"]
        within = sum(k for key, k in v.items() if key.split("|")[0] == key.split("|")[1])
        across = sum(v.values()) - within
        ca = r.get("clusters_across_scenes")
        peaks = r.get("peak_memory_bytes") or {}
        peak = ", ".join(f"{k} {b / (1 << 30):.1f} GiB" for k, b in peaks.items()) or "-"
        match = t.get("match", 0.0) + t.get("export", 0.0)
        lines.append(f"| {name} | {c['models']} | {c['points_seen_from_two_scenes']:,} | {within:,} | {across:,} | "
                     + (f"{ca['clusters']:,} of {ca['of_multi_image_clusters']:,}" if ca else "-")
                     + f" | {fmt(t.get('extract'), '.1f')} | {fmt(match, '.1f')} | {fmt(t.get('map'), '.1f')} | "
                     f"{fmt(t.get('triangulate'), '.1f')} | {t['total']:.1f} | {peak} |")
    for name, runs in results.items():
        mi = runs[0].get("mapper_input")
        if not mi:
            continue
        rule = mi.get("rule", "all")
        lines += ["", f"What {name}'s clusters hand the mapper, by scene (`--cluster-matches {rule}`, each cluster "
                      "cut to its members in the scene):", "",
                  "| scene | features | observations in clusters of 2+ | matches | matches / observations | "
                  "largest cluster | matches in clusters of 10+ |", "|---|---|---|---|---|---|---|"]
        for scene, e in mi["scenes"].items():
            ratio = e["matches"] / e["observations"] if e["observations"] else 0.0
            lines.append(f"| {scene} | {e['features']:,} | {e['observations']:,} | {e['matches']:,} | {ratio:.2f} | "
                         f"{e['largest']} | {e['matches_in_clusters_of_10']:.2f} |")
        lines += ["", f"- Matching each scene apart would cost {mi['apart']:.2f} of {name}'s one pair scan over all "
                      "the features (sum of the scenes' squared feature counts over the square of their sum)."]
    if "colmap" in results:
        c0 = results["colmap"][0]
        for name, runs in results.items():
            if name.startswith("colmap"):
                continue
            lines.append("")
            lines.append(f"- {name} / COLMAP time: x{runs[0]['times']['total'] / c0['times']['total']:.2f}")
    return lines


if __name__ == "__main__":
    sys.exit(main())
