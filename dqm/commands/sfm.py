"""Images to a sparse 3-D model in one command: SIFT, QuickMatch with guided growth, COLMAP export,
pycolmap's incremental mapper and a figure of the model.

    dqm sfm photos/ --out model/
    dqm sfm photos/ --out model/ --preset colmap --camera-model OPENCV --single-camera

MODEL_DIR (new or empty) receives clusters.npz (dqm's CLUSTERS file), database.db (the COLMAP
database: cameras, keypoints, the clusters' matches, verified geometries), sparse/0 ... (the
models pycolmap's mapper made, in COLMAP's binary format), model.png (the largest model from the
front and from above) and tracks.csv. It is the chain `dqm match` -> `dqm export colmap` ->
`pycolmap.incremental_mapping` with the same options (docs/sfm.md). Needs pycolmap:
pip install 'dqm[colmap]'.
"""
from __future__ import annotations

import time
from pathlib import Path

from .. import io, outputs
from ..validation import InputError
from .extract import add_image_options, extract
from .match import add_cluster_options, cluster

NAME = "sfm"
HELP = "images -> sparse 3-D model (extract, match with guided growth, export to COLMAP, pycolmap mapping)"


def add_arguments(p) -> None:
    p.add_argument("inputs", nargs="*", metavar="IMAGES",
                   help="image folders / globs / files (or none, with --image-list)")
    p.add_argument("--out", required=True, metavar="MODEL_DIR", help="folder to create (or an empty one)")
    add_image_options(p)
    add_cluster_options(p)
    p.add_argument("--camera-model", default=None, metavar="MODEL",
                   help="COLMAP camera model of every camera (default SIMPLE_RADIAL, as COLMAP's)")
    p.add_argument("--single-camera", action="store_true", help="one camera for all images (one size)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _out_dir(path: str) -> Path:
    """MODEL_DIR checked before any work: absent (created) or an empty folder; never overwritten."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} is a file; dqm sfm writes a folder")
    if out.is_dir() and any(out.iterdir()):
        raise InputError(f"--out {out} is not empty; dqm sfm writes into a new or empty folder")
    return outputs.check_dir(out, "--out")  # created, and probed for writing


def run(args) -> int:
    from ..vision import colmap
    from ..vision.sfm import model_figure, model_numbers, reconstruct

    t0 = time.perf_counter()
    colmap.require_pycolmap()
    camera = colmap.camera_options(args.camera_model or colmap.DEFAULT_CAMERA_MODEL,
                                   "single" if args.single_camera else "per-image", None)
    if not args.inputs and not args.image_list:
        raise InputError("no images: give image folders, globs or files, or --image-list")
    out = _out_dir(args.out)
    fs = extract(args, min_images=2)
    result, extra = cluster(args, fs, from_images=True)
    io.save_clusters(out / "clusters.npz", fs, result, extra)
    io.save_tracks_csv(out / "tracks.csv", result.labels, fs.image_ids, fs.keypoints, fs.image_names)
    paths = colmap.resolve_images(fs.image_names, None)
    s = colmap.export_database(out / "database.db", fs.keypoints, fs.image_ids, paths, result.labels,
                               descriptors=fs.descriptors, camera=camera)
    print(f"wrote {out / 'database.db'}: {s.n_images} images, {s.n_matches} matches in {s.n_image_pairs} image "
          f"pairs, {s.n_verified_pairs} verified; mapping ...", flush=True)
    rec, t_map = reconstruct(out / "database.db", s.image_dir, out / "sparse")
    m = model_numbers(rec)
    if rec is None:
        print(f"no model: pycolmap's mapper registered no image pair ({t_map:.1f} s); the clusters and the "
              f"database are in {out}")
        return 1
    model_figure(rec, out / "model.png", f"{m['registered']} of {s.n_images} images, {m['points']:,} points")
    print(f"model: {m['registered']} of {s.n_images} images registered, {m['points']:,} 3-D points, mean track "
          f"length {m['track']:.2f}, mean reprojection error {m['reproj']:.3f} px (mapping {t_map:.1f} s); "
          f"wrote {out}/sparse, {out / 'model.png'} ({time.perf_counter() - t0:.1f} s in all)")
    return 0
