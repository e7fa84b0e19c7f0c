"""Structure from motion from dqm's tracks against COLMAP's own pipeline, side by side (issue 22's proof).

On ../shared/data/sacre_coeur (10 internet photos), reconstruct with pycolmap's incremental
mapper from:

  (a) dqm match's default pipeline: RootSIFT (--preset), QuickMatch, geometry-guided growth;
  (b) dqm QuickMatch alone (dqm match --no-guided);
  (c) COLMAP's pipeline on the same images: its SIFT, exhaustive matching and verification;
  (d) BF ratio-test tracks (OpenCV BF, ratio 0.75, union-find, drop-track) on dqm's SIFT;
  (e) dqm match --preset colmap: pycolmap's SIFT, QuickMatch, guided growth;
  (f) dqm match --verify: QuickMatch, verification without growth;

and print a markdown table: registered images, 3-D points, mean track length, mean
reprojection error and matching time, then each dqm row against COLMAP's (c) as ratios, plus a
figure of (a)'s sparse model.

    python scripts/bench_sfm.py [--images DIR] [--out-dir DIR] [--preset rootsift] [--quick] [--pipelines a,c]

--quick: the last 5 images only. --pipelines: only these rows (CI runs a,c: dqm's default
pipeline beside COLMAP's). Nothing is written into the repository unless --out-dir points there.
COLMAP's mapper runs multi-threaded, so its counts move by about 1% between runs.
"""
from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_IMAGES = ROOT.parent / "shared" / "data" / "sacre_coeur"
ROWS = {
    "a": "(a) dqm match (default: RootSIFT, QuickMatch, guided growth)",
    "b": "(b) dqm QuickMatch alone (--no-guided)",
    "c": "(c) COLMAP (its SIFT, exhaustive matching, verification)",
    "d": "(d) BF ratio tracks (ratio 0.75, drop-track)",
    "e": "(e) dqm match --preset colmap (pycolmap's SIFT, guided)",
    "f": "(f) dqm match --verify (no growth)",
}


def row(name, m, t_match, n_images):
    if not m["registered"]:
        return f"| {name} | 0 / {n_images} | 0 | - | - | {t_match:.1f} |"
    return (f"| {name} | {m['registered']} / {n_images} | {m['points']:,} | {m['track']:.3f} | "
            f"{m['reproj']:.3f} | {t_match:.1f} |")


def against_colmap(results: dict) -> list[str]:
    """Each dqm row against COLMAP's (c): points and track length as ratios, reprojection as a difference."""
    c = results.get("c")
    if not c or not c["registered"]:
        return []
    out = ["", "Against COLMAP (c), measured in this run (targets: points >= 1x, track >= 1x, reprojection "
           "<= +0.1 px, every image registered):", ""]
    for key, m in sorted(results.items()):
        if key == "c" or not m["registered"]:
            continue
        ok = lambda x: "met" if x else "missed"  # noqa: E731
        out.append(f"- {ROWS[key][:3]}: points x{m['points'] / c['points']:.2f} ({ok(m['points'] >= c['points'])}), "
                   f"track x{m['track'] / c['track']:.3f} ({ok(m['track'] >= c['track'])}), reprojection "
                   f"{m['reproj'] - c['reproj']:+.3f} px ({ok(m['reproj'] <= c['reproj'] + 0.1)}), registered "
                   f"{m['registered']} ({ok(m['registered'] == c['n'])}), matching time x{m['t'] / c['t']:.1f}")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=Path, default=DEFAULT_IMAGES, help="image folder (default: sacre_coeur)")
    ap.add_argument("--out-dir", type=Path, default=None, help="where the table and figure go (default: a temp dir)")
    ap.add_argument("--preset", default="rootsift", help="dqm SIFT preset for (a), (b), (d), (f)")
    ap.add_argument("--quick", action="store_true", help="last 5 images only")
    ap.add_argument("--pipelines", default="a,b,c,d,e,f", help="the rows to run, comma-separated letters a..f")
    args = ap.parse_args()
    chosen = {x.strip() for x in args.pipelines.split(",") if x.strip()}
    if not chosen or not chosen <= set(ROWS):
        sys.exit(f"bench_sfm: --pipelines takes letters a..f separated by commas, got {args.pipelines!r}")
    try:
        import pycolmap
    except ImportError:
        sys.exit("bench_sfm: needs pycolmap (pip install 'dqm[colmap]')")
    import dqm
    from dqm.vision import baselines, colmap, features
    from dqm.vision.guided import guided_labels
    from dqm.vision.sfm import model_figure, model_numbers, reconstruct
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
    notes = []
    sets = {}  # feature sets: preset -> (D, ids, kp)

    def feats(preset):
        if preset not in sets:
            t0 = time.perf_counter()
            sets[preset] = features.extract_many(paths, preset=preset)
            notes.append(f"SIFT `{preset}`: {len(sets[preset][0]):,} features in {time.perf_counter() - t0:.1f} s")
            print(notes[-1], flush=True)
        return sets[preset]

    def dqm_rows(keys, preset):
        """QuickMatch once per feature set; the rows that start from it."""
        D, ids, kp = feats(preset)
        t0 = time.perf_counter()
        r = dqm.quickmatch(D, ids)
        t_qm = time.perf_counter() - t0
        out = {}
        for key in keys:
            t0 = time.perf_counter()
            if key == "b":
                labels = r.labels
            elif key == "f":
                labels, vs = verify_clusters(r.labels, ids, kp)
                notes.append(f"{key}: verified {vs.n_verified} of {vs.n_pairs} image pairs, {vs.n_split} split off")
            else:
                labels, gs = guided_labels(r, kp, D)
                notes.append(f"{key}: {gs.summary()}; {gs.time_verify + gs.time_propose + gs.time_merge:.1f} s "
                             f"after QuickMatch's {t_qm:.1f} s")
            out[key] = (labels, t_qm + time.perf_counter() - t0, D, ids, kp)
        return out

    methods = {}
    if chosen & {"a", "b", "f"}:
        methods.update(dqm_rows(sorted(chosen & {"a", "b", "f"}), args.preset))
    if "e" in chosen:
        methods.update(dqm_rows(["e"], "colmap"))
    if "d" in chosen:
        D, ids, kp = feats(args.preset)
        t0 = time.perf_counter()
        a, b = baselines.pairwise_matches(D, ids, "bf", baselines.DEFAULT_RATIO)
        methods["d"] = (baselines.build_tracks(a, b, ids, "drop-track"), time.perf_counter() - t0, D, ids, kp)

    results = {}
    for key in sorted(methods):
        labels, t_match, D, ids, kp = methods[key]
        db = work / f"{key}.db"
        colmap.export_database(db, kp, ids, paths, labels, image_dir=image_dir, descriptors=D)
        rec, _ = reconstruct(db, image_dir, work / f"sparse_{key}")
        results[key] = dict(model_numbers(rec), t=t_match, n=n)
        print(row(ROWS[key], results[key], t_match, n), flush=True)
        if key == "a" and rec is not None:
            model_figure(rec, out_dir / "sfm_model.png", f"{args.images.name}: dqm match's tracks, "
                         f"{rec.num_reg_images()} images, {rec.num_points3D():,} points")
    if "c" in chosen:
        db = work / "c.db"
        t0 = time.perf_counter()
        pycolmap.extract_features(str(db), str(image_dir))
        notes.append(f"COLMAP SIFT: {time.perf_counter() - t0:.1f} s")
        t0 = time.perf_counter()
        pycolmap.match_exhaustive(str(db))
        t_cm = time.perf_counter() - t0
        rec, _ = reconstruct(db, image_dir, work / "sparse_c")
        results["c"] = dict(model_numbers(rec), t=t_cm, n=n)
        print(row(ROWS["c"], results["c"], t_cm, n), flush=True)
    lines = ["| pipeline | registered | 3-D points | mean track length | mean reprojection error (px) | "
             "matching time (s) |", "|---|---|---|---|---|---|"]
    lines += [row(ROWS[k], results[k], results[k]["t"], n) for k in sorted(results)]
    lines += against_colmap(results)
    lines += ["", "Notes: " + "; ".join(notes) + "."]
    (out_dir / "sfm.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines[len(results) + 2:]))
    figure = out_dir / "sfm_model.png"
    print(f"table: {out_dir / 'sfm.md'}" + (f"; figure: {figure}" if "a" in chosen and figure.exists() else ""))
    if args.out_dir is not None:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
