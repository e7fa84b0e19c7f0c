"""Images to a sparse 3-D model in one command: SIFT, QuickMatch, COLMAP export, pycolmap's mapper,
a figure of the model and, with --gt, its cameras against ground truth.

    dqm sfm photos/ --out model/
    dqm sfm photos/ --out model/ --gt gt_cameras/        # + pose errors and AUC (Strecha files or a COLMAP model)
    dqm sfm photos/ --out model/ --preset colmap --camera-model OPENCV --single-camera

MODEL_DIR (new or empty) receives clusters.npz (dqm's CLUSTERS file), database.db (the COLMAP
database: cameras, keypoints, the clusters' matches, verified geometries), sparse/0 ... (the
models the mapper made, in COLMAP's binary format), model.png (the largest model from the
front and from above), tracks.csv and sfm.json (the stage times, the model's numbers and, with
--gt, the pose scores). It is the chain `dqm match` -> `dqm export colmap` -> pycolmap's mapper
with the same options (docs/sfm.md). Every random choice is seeded (--seed): the same photos
and options give the same model. Needs pycolmap: pip install 'dqm[colmap]'.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from .. import io, outputs
from ..validation import InputError
from .extract import add_image_options, extract
from .match import add_cluster_options, cluster

NAME = "sfm"
HELP = "images -> sparse 3-D model (extract, QuickMatch, export to COLMAP, pycolmap mapping; --gt: pose accuracy)"


def add_arguments(p) -> None:
    from ..vision.features import SFM_PRESET
    from ..vision.sfm import DEFAULT_SEED, MAPPERS

    p.add_argument("inputs", nargs="*", metavar="IMAGES",
                   help="image folders / globs / files (or none, with --image-list)")
    p.add_argument("--out", required=True, metavar="MODEL_DIR", help="folder to create (or an empty one)")
    add_image_options(p, default_preset=SFM_PRESET)
    add_cluster_options(p)
    p.add_argument("--camera-model", default=None, metavar="MODEL",
                   help="COLMAP camera model of every camera (default SIMPLE_RADIAL, as COLMAP's)")
    p.add_argument("--single-camera", action="store_true", help="one camera for all images (one size)")
    p.add_argument("--mapper", choices=MAPPERS, default="incremental",
                   help="COLMAP's incremental mapper (default) or its global mapper (COLMAP 4, ex-GLOMAP)")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED,
                   help=f"random seed of the two-view verification and the mapper (default {DEFAULT_SEED})")
    p.add_argument("--mapper-threads", type=int, default=1, metavar="N",
                   help="threads of the mapper (default 1: the same model bit for bit on every run; 0: all cores, "
                        "faster on large jobs, the model then varies in its last digits)")
    p.add_argument("--triangulate", action=argparse.BooleanOptionalAction, default=True,
                   help="after mapping, match every two images that share points under the model's own geometry "
                        "(0.5 px of its epipolar lines, mutual nearest descriptors, ratio 0.8) and triangulate with "
                        "the cameras fixed: more 3-D points, the same cameras (default; --no-triangulate: the "
                        "mapper's model as it is)")
    p.add_argument("--gt", default=None, metavar="DIR",
                   help="ground-truth cameras (a folder of Strecha *.camera files, or a COLMAP model): print the "
                        "model's pose errors and pairwise pose AUC@1/2/5 degrees (docs/sfm.md)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _triangulate(rec, database: Path, export, fs, folder: Path, seed: int, mapper_threads: int, threads):
    """The model with the points that matches under its own geometry add (:mod:`dqm.vision.triangulation`),
    written over the mapper's model in ``folder``."""
    import numpy as np

    from ..vision.triangulation import triangulate

    by_name = {name: k for k, name in enumerate(export.names)}
    keypoints, descriptors = {}, {}
    for image_id, image in rec.images.items():
        if image.has_pose:
            rows = np.flatnonzero(fs.image_ids == by_name[image.name])
            keypoints[image_id], descriptors[image_id] = fs.keypoints[rows, :2], fs.descriptors[rows]
    return triangulate(rec, database, export.image_dir, folder, keypoints, descriptors, seed=seed,
                       num_threads=mapper_threads, n_threads=threads)


def _out_dir(path: str) -> Path:
    """MODEL_DIR checked before any work: absent (created) or an empty folder; never overwritten."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} is a file; dqm sfm writes a folder")
    if out.is_dir() and any(out.iterdir()):
        raise InputError(f"--out {out} is not empty; dqm sfm writes into a new or empty folder")
    return outputs.check_dir(out, "--out")  # probed for writing; created when the first file is written


def run(args) -> int:
    from ..vision import colmap, poses
    from ..vision.sfm import model_figure, model_numbers, reconstruct

    t0 = time.perf_counter()
    colmap.require_pycolmap(what="dqm sfm (COLMAP's mapper)")
    camera = colmap.camera_options(args.camera_model or colmap.DEFAULT_CAMERA_MODEL,
                                   "single" if args.single_camera else "per-image", None)
    if args.seed < 0 or args.mapper_threads < 0:
        raise InputError(f"--seed and --mapper-threads must be >= 0, got {args.seed} and {args.mapper_threads}")
    threads = args.mapper_threads or -1
    if not args.inputs and not args.image_list:
        raise InputError("no images: give image folders, globs or files, or --image-list")
    truth = None
    if args.gt:  # read and matched to the images' names before any work
        from ..vision.features import collect_images

        names = [p.name for p in collect_images(args.inputs, recursive=args.recursive, image_list=args.image_list)]
        truth = poses.restrict(poses.read_ground_truth(args.gt), names, f"--gt {args.gt}")
    out = _out_dir(args.out)
    times = {}
    t = time.perf_counter()
    fs = extract(args, min_images=2)
    times["extract"] = time.perf_counter() - t
    t = time.perf_counter()
    result, extra = cluster(args, fs)
    times["match"] = time.perf_counter() - t
    t = time.perf_counter()
    io.save_clusters(out / "clusters.npz", fs, result, extra)
    io.save_tracks_csv(out / "tracks.csv", result.labels, fs.image_ids, fs.keypoints, fs.image_names)
    paths = colmap.resolve_images(fs.image_names, None)
    s = colmap.export_database(out / "database.db", fs.keypoints, fs.image_ids, paths, result.labels,
                               descriptors=fs.descriptors, camera=camera, seed=args.seed)
    times["export"] = time.perf_counter() - t
    print(f"wrote {out / 'database.db'}: {s.n_images} images, {s.pairs_line()}, {s.n_verified_pairs} verified; "
          "mapping ...", flush=True)
    rec, times["map"], folder = reconstruct(out / "database.db", s.image_dir, out / "sparse", mapper=args.mapper,
                                            seed=args.seed, num_threads=threads)
    mapped = model_numbers(rec)
    if rec is not None and args.triangulate:
        t = time.perf_counter()
        rec, ts = _triangulate(rec, out / "database.db", s, fs, folder, args.seed, threads, args.threads)
        times["triangulate"] = time.perf_counter() - t
        print(ts.summary())
    m = model_numbers(rec)
    report = {"images": s.n_images, "features": len(fs), "options": {
        "preset": args.preset, "max_features": args.max_features, "guided": bool(args.guided),
        "verify": bool(args.verify), "mapper": args.mapper, "seed": args.seed,
        "mapper_threads": args.mapper_threads, "triangulate": bool(args.triangulate)}, "model": m,
        "model_before_triangulation": mapped}
    if rec is None:
        report["times"] = dict(times, total=time.perf_counter() - t0)
        outputs.write_text(out / "sfm.json", json.dumps(report, indent=1) + "\n")
        print(f"no model: pycolmap's mapper registered no image pair ({times['map']:.1f} s); the clusters and the "
              f"database are in {out}")
        return 1
    model_figure(rec, out / "model.png", f"{m['registered']} of {s.n_images} images, {m['points']:,} points")
    times["total"] = time.perf_counter() - t0
    report["times"] = times
    print(f"model: {m['registered']} of {s.n_images} images registered, {m['points']:,} 3-D points, mean track "
          f"length {m['track']:.2f}, mean reprojection error {m['reproj']:.3f} px; times: extraction "
          f"{times['extract']:.1f} s, matching {times['match']:.1f} s, export {times['export']:.1f} s, mapping "
          f"{times['map']:.1f} s" + (f", triangulation {times['triangulate']:.1f} s" if "triangulate" in times else "")
          + f", {times['total']:.1f} s in all")
    if truth is not None:
        scores = poses.evaluate_poses(poses.poses_of(rec), truth)
        report["poses"] = scores.as_dict()
        print(scores.line())
    outputs.write_text(out / "sfm.json", json.dumps(report, indent=1) + "\n")
    print(f"wrote {out}/sparse, {out / 'model.png'}, {out / 'sfm.json'}")
    return 0
