"""Cluster features of many images with QuickMatch.

INPUT is either a FEATURES .npz file (format: see dqm/io.py or docs/formats.md)
or images: a folder, a glob pattern, or several image files, from which SIFT
features are extracted first (OpenCV; --preset, --max-features).

    dqm match features.npz --out clusters.npz
    dqm match 'photos/*.jpg' --out clusters.npz --preset paper
"""
from __future__ import annotations

import glob
import time
from pathlib import Path

import numpy as np

from .. import io
from ..core import DEFAULT_RATIO_DENSITY, DEFAULT_RHO, KERNELS, PARENT_MODES, quickmatch
from ..progress import ProgressBar
from ..validation import InputError

NAME = "match"
HELP = "cluster features (from a .npz or from images) with QuickMatch"


def add_arguments(p) -> None:
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="FEATURES.npz, or an image folder / glob / files")
    p.add_argument("--out", required=True, help="CLUSTERS.npz to write")
    p.add_argument("--rho", type=float, default=DEFAULT_RHO, help=f"merge ratio (default {DEFAULT_RHO})")
    p.add_argument("--ratio-density", type=float, default=DEFAULT_RATIO_DENSITY,
                   help=f"Gaussian bandwidth / sigma (default {DEFAULT_RATIO_DENSITY})")
    p.add_argument("--kernel", choices=KERNELS, default="gaussian")
    p.add_argument("--parent", choices=PARENT_MODES, default="any",
                   help="'other-image': a feature's tree parent must come from another image")
    p.add_argument("--threads", type=int, default=None, help="worker threads (default: all cores)")
    p.add_argument("--preset", default="opencv", help="SIFT preset when INPUT are images: opencv | paper")
    p.add_argument("--max-features", type=int, default=0, help="SIFT features per image, 0 = no limit")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".ppm", ".pgm", ".bmp", ".tif", ".tiff")


def image_paths(inputs) -> list:
    """Expand folders / globs / files to a sorted list of image paths; error if none."""
    out = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            out += sorted(q for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES)
        elif any(ch in item for ch in "*?["):
            out += sorted(Path(q) for q in glob.glob(item) if Path(q).suffix.lower() in IMAGE_SUFFIXES)
        elif p.exists():
            out.append(p)
        else:
            raise InputError(f"input not found: {item}")
    if not out:
        raise InputError(f"no images found in {' '.join(inputs)}")
    return out


def load_input(args) -> io.FeatureSet:
    if len(args.inputs) == 1 and args.inputs[0].endswith(".npz"):
        return io.load_features(args.inputs[0])
    from ..features import extract_many

    paths = image_paths(args.inputs)
    if len(paths) < 2:
        raise InputError(f"need at least two images to match, got {len(paths)}: {paths[0]}")
    bar = ProgressBar("sift", force=False if args.quiet else None)
    D, ids, kp = extract_many(paths, preset=args.preset, max_features=args.max_features, progress=bar)
    empty = [str(paths[k]) for k in range(len(paths)) if not (ids == k).any()]
    if empty:
        print(f"note: no SIFT features in {len(empty)} image(s): {', '.join(empty[:5])}")
    return io.FeatureSet(D, ids, kp, np.array([str(p) for p in paths]))


def run(args) -> int:
    t0 = time.perf_counter()
    fs = load_input(args)
    n_images = len(np.unique(fs.image_ids))
    if len(fs) == 0:
        raise InputError("no features to match (empty input)")
    if n_images < 2:
        raise InputError(f"all {len(fs)} features come from one image; matching needs at least two images")
    bar = ProgressBar("quickmatch", force=False if args.quiet else None)
    result = quickmatch(fs.descriptors, fs.image_ids, rho=args.rho, ratio_density=args.ratio_density,
                        kernel=args.kernel, parent=args.parent, n_threads=args.threads, progress=bar)
    io.save_clusters(args.out, fs, result)
    print(result.summary())
    print(f"wrote {args.out} ({time.perf_counter() - t0:.2f} s in all)")
    return 0
