"""Structure from motion from dqm's tracks against COLMAP's own pipeline (issue 13's proof).

On ../shared/data/sacre_coeur (10 internet photos), reconstruct with pycolmap's incremental
mapper from:

  (a) dqm QuickMatch clusters, default parameters (SIFT preset --preset, default rootsift);
  (b) the same with geometric verification (dqm match --verify);
  (c) COLMAP's pipeline on the same images: its SIFT, exhaustive matching and verification;
  (d) BF ratio-test tracks (OpenCV BF, ratio 0.75, union-find, drop-track) on dqm's SIFT;
  (e) dqm QuickMatch on COLMAP's SIFT of (c), read with dqm import colmap;

and print a markdown table: registered images, 3-D points, mean track length, mean
reprojection error and matching time, plus a figure of (a)'s sparse model.

    python scripts/bench_sfm.py [--images DIR] [--out-dir DIR] [--preset rootsift] [--quick] [--pipelines a,c]

--quick: the last 5 images only. --pipelines: only these rows (CI runs a,c: dqm's tracks and
COLMAP's, side by side, in about a third of the time of all five). Nothing is written into the
repository unless --out-dir points there.
"""
from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_IMAGES = ROOT.parent / "shared" / "data" / "sacre_coeur"


def reconstruct(pycolmap, db: Path, image_dir: Path, out: Path):
    """The largest reconstruction of incremental mapping (or None) and the mapping time."""
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    recs = pycolmap.incremental_mapping(str(db), str(image_dir), str(out))
    dt = time.perf_counter() - t0
    if not recs:
        return None, dt
    return max(recs.values(), key=lambda r: (r.num_reg_images(), r.num_points3D())), dt


def row(name, rec, t_match, n_images):
    if rec is None:
        return f"| {name} | 0 / {n_images} | 0 | - | - | {t_match:.1f} |", {}
    m = {"registered": rec.num_reg_images(), "points": rec.num_points3D(),
         "track": rec.compute_mean_track_length(), "reproj": rec.compute_mean_reprojection_error()}
    return (f"| {name} | {m['registered']} / {n_images} | {m['points']:,} | {m['track']:.3f} | "
            f"{m['reproj']:.3f} | {t_match:.1f} |"), m


def model_figure(rec, path: Path, title: str):
    """A sparse model from the front (the points' two main axes) and from above (main and depth axes)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    P = np.array([p.xyz for p in rec.points3D.values()])
    C = np.array([im.projection_center() for im in rec.images.values() if im.has_pose])
    centre = np.median(P, axis=0)
    _, _, vt = np.linalg.svd(P - centre, full_matrices=False)
    p3, c3 = (P - centre) @ vt.T, (C - centre) @ vt.T
    lim = np.percentile(np.abs(p3), 98, axis=0) * 1.2
    fig, (front, top) = plt.subplots(1, 2, figsize=(11, 5), dpi=110)
    front.scatter(p3[:, 0], p3[:, 1], s=2, c="#4575b4", alpha=0.7)
    front.set_xlim(-lim[0], lim[0])
    front.set_ylim(-lim[1], lim[1])
    front.set_title(f"front: {len(P):,} 3-D points")
    top.scatter(p3[:, 0], p3[:, 2], s=2, c="#4575b4", alpha=0.7, label="3-D points")
    top.scatter(c3[:, 0], c3[:, 2], s=45, c="#d73027", marker="^", label=f"{len(C)} cameras")
    top.set_title("from above, with the cameras")
    top.legend(loc="best")
    for ax, yl in ((front, "main axis 2"), (top, "depth axis")):
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel("main axis 1 (model units)")
        ax.set_ylabel(yl)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=Path, default=DEFAULT_IMAGES, help="image folder (default: sacre_coeur)")
    ap.add_argument("--out-dir", type=Path, default=None, help="where the table and figure go (default: a temp dir)")
    ap.add_argument("--preset", default="rootsift", help="dqm SIFT preset for (a), (b), (d)")
    ap.add_argument("--quick", action="store_true", help="last 5 images only")
    ap.add_argument("--pipelines", default="a,b,c,d,e", help="the rows to run, comma-separated letters a..e")
    args = ap.parse_args()
    chosen = {x.strip() for x in args.pipelines.split(",") if x.strip()}
    if not chosen or not chosen <= set("abcdef"):
        sys.exit(f"bench_sfm: --pipelines takes letters a..f separated by commas, got {args.pipelines!r}")
    try:
        import pycolmap
    except ImportError:
        sys.exit("bench_sfm: needs pycolmap (pip install 'dqm[colmap]')")
    import dqm
    from dqm.vision import baselines, colmap, features
    from dqm.vision.guided import guided_labels
    from dqm.vision.verify import verify_clusters

    colmap.require_pycolmap()
    if not args.images.is_dir():
        sys.exit(f"bench_sfm: no image folder {args.images}")
    work = Path(tempfile.mkdtemp(prefix="dqm-sfm-"))
    out_dir = args.out_dir or work
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = features.collect_images([str(args.images)])
    if args.quick:
        paths = paths[-5:]
    image_dir = work / "images"
    image_dir.mkdir()
    for p in paths:  # the mapper reads one folder; link the chosen images there
        (image_dir / p.name).symlink_to(p.resolve())
    paths = sorted(image_dir.iterdir())
    n = len(paths)
    t0 = time.perf_counter()
    D, ids, kp = features.extract_many(paths, preset=args.preset)
    t_extract = time.perf_counter() - t0
    print(f"dqm SIFT ({args.preset}): {len(D):,} features of {n} images in {t_extract:.1f} s", flush=True)

    methods = {}
    vs = None
    gs = None
    if chosen & {"a", "b", "f"}:
        t0 = time.perf_counter()
        r = dqm.quickmatch(D, ids)
        t_qm = time.perf_counter() - t0
        if "a" in chosen:
            methods["(a) dqm QuickMatch"] = (r.labels, t_qm)
        print(f"QuickMatch: {t_qm:.1f} s", flush=True)
        if "b" in chosen:
            t0 = time.perf_counter()
            lab_v, vs = verify_clusters(r.labels, ids, kp)
            methods["(b) dqm QuickMatch --verify"] = (lab_v, t_qm + time.perf_counter() - t0)
        if "f" in chosen:
            t0 = time.perf_counter()
            lab_g, gs = guided_labels(r, kp, D)
            methods["(f) dqm QuickMatch --guided"] = (lab_g, t_qm + time.perf_counter() - t0)
    if "d" in chosen:
        t0 = time.perf_counter()
        a, b = baselines.pairwise_matches(D, ids, "bf", baselines.DEFAULT_RATIO)
        lab_bf = baselines.build_tracks(a, b, ids, "drop-track")
        methods["(d) BF ratio tracks"] = (lab_bf, time.perf_counter() - t0)

    lines = ["| pipeline | registered | 3-D points | mean track length | mean reprojection error (px) | "
             "matching time (s) |", "|---|---|---|---|---|---|"]
    results = {}
    for name, (labels, t_match) in methods.items():
        db = work / f"{name[1]}.db"
        colmap.export_database(db, kp, ids, paths, labels, image_dir=image_dir, descriptors=D)
        rec, _ = reconstruct(pycolmap, db, image_dir, work / f"sparse_{name[1]}")
        line, results[name] = row(name, rec, t_match, n)
        lines.append(line)
        print(line, flush=True)
        if name.startswith("(a)") and rec is not None:
            model_figure(rec, out_dir / "sfm_model.png", f"sacre_coeur: dqm QuickMatch tracks, {rec.num_reg_images()}"
                         f" images, {rec.num_points3D():,} points")
    db = work / "c.db"
    t_cx = None
    if chosen & {"c", "e"}:
        t0 = time.perf_counter()
        pycolmap.extract_features(str(db), str(image_dir))
        t_cx = time.perf_counter() - t0
    if "c" in chosen:
        t0 = time.perf_counter()
        pycolmap.match_exhaustive(str(db))
        t_cm = time.perf_counter() - t0
        rec, _ = reconstruct(pycolmap, db, image_dir, work / "sparse_c")
        line, results["(c)"] = row("(c) COLMAP (its SIFT, exhaustive matching, verification)", rec, t_cm, n)
        lines.insert(2 + sum(1 for name in methods if name < "(c)"), line)
        print(line, flush=True)
    if "e" in chosen:  # QuickMatch on COLMAP's own SIFT, brought in with dqm import colmap
        fs = colmap.import_database(db)
        t0 = time.perf_counter()
        r_e = dqm.quickmatch(fs.descriptors, fs.image_ids)
        t_e = time.perf_counter() - t0
        names = [image_dir / str(nm) for nm in fs.image_names]
        colmap.export_database(work / "e.db", fs.keypoints, fs.image_ids, names, r_e.labels, image_dir=image_dir)
        rec, _ = reconstruct(pycolmap, work / "e.db", image_dir, work / "sparse_e")
        line, results["(e)"] = row("(e) dqm QuickMatch on COLMAP's SIFT (dqm import colmap)", rec, t_e, n)
        lines.append(line)
        print(line, flush=True)
    summary = f"\nExtraction: dqm SIFT {t_extract:.1f} s" + (f", COLMAP SIFT {t_cx:.1f} s" if t_cx else "") + "."
    if vs is not None:
        summary += f" Verification (b): {vs.n_verified}/{vs.n_pairs} pairs verified, {vs.n_split} features split off."
    if gs is not None:
        summary += f" Guided (f): {gs.summary()}."
    (out_dir / "sfm.md").write_text("\n".join(lines) + "\n" + summary + "\n")
    print(summary)
    figure = out_dir / "sfm_model.png"
    print(f"table: {out_dir / 'sfm.md'}" + (f"; figure: {figure}" if "a" in chosen and figure.exists() else ""))
    if args.out_dir is not None:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
