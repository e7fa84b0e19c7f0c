"""Cluster features of many images with QuickMatch.

INPUT is either a FEATURES .npz file (format: see dqm/io.py or docs/formats.md),
a COLMAP database (its keypoints, descriptors and image names, read directly:
no dqm import step; --image-dir names the folder its image names are relative
to), or images: a folder, a glob pattern, or several image files, from which SIFT
features are extracted first (OpenCV; --preset, --max-features; the default
preset is dqm sfm's). Where the features have keypoints, the clusters are then
verified and grown along the image pairs' geometry (guided growth: more complete
clusters; --no-guided keeps QuickMatch's own). --verify only splits off the
members that the geometry rejects. A COLMAP database as INPUT is not grown by
default: its matches go back to COLMAP's mapper, whose cameras growth worsens
(docs/sfm.md).

    dqm match features.npz --out clusters.npz
    dqm match database.db --out clusters.npz --image-dir images/   # COLMAP's features
    dqm match database.db --into-database  # matches + verified geometries into it, for COLMAP's mapper
    dqm match 'photos/*.jpg' --out clusters.npz --preset paper
    dqm match photos/ --out clusters.npz --max-features 2000 --tracks-csv tracks.csv
    dqm match big.npz --out clusters.npz --exact            # exact at any size

The CLUSTERS file keeps every feature's keypoint (x, y, size, angle) and the
image paths, so the tracks can be used directly (see dqm/io.py for the fields).
"""
from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from .. import io, outputs
from ..core import DEFAULT_NEIGHBORS, quickmatch
from ..core.clustering import ENGINES, FAST_FROM
from ..core.memory import parse_size
from ..core.params import DEFAULT_KERNEL, QuickMatchParams
from ..progress import ProgressBar
from ..validation import InputError, positive_int_arg
from ..vision.features import SFM_PRESET
from .extract import add_image_options, extract
from .param_options import add_quickmatch_params

NAME = "match"
HELP = "cluster features (from a .npz or from images) with QuickMatch"


def add_arguments(p) -> None:
    p.add_argument("inputs", nargs="*", metavar="INPUT",
                   help="FEATURES.npz file(s), a COLMAP database.db, or image folders / globs / files (or none, "
                        "with --image-list)")
    p.add_argument("--out", default=None, help="CLUSTERS.npz to write (needed unless --into-database)")
    p.add_argument("--image-dir", default=None, metavar="DIR",
                   help="with a COLMAP database: the folder its image names are relative to (the CLUSTERS file "
                        "then names the image files, for plot and export)")
    p.add_argument("--into-database", action="store_true",
                   help="with a COLMAP database as INPUT: write the matches the clusters imply and COLMAP's verified "
                        "two-view geometries of them into that database, as COLMAP's matchers do (its cameras and "
                        "features stay), so COLMAP's mapper runs next; one that already holds matches is refused "
                        "unless --overwrite (needs pycolmap)")
    add_cluster_options(p, "match")
    add_image_options(p, default_preset=SFM_PRESET)
    p.add_argument("--tracks-csv", default=None, metavar="CSV",
                   help="also write the multi-image tracks (clusters of 2+ features) with keypoints as CSV")
    outputs.add_overwrite_option(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def add_cluster_options(p, command: str = "match") -> None:
    """QuickMatch's options and the geometric steps after it (shared with dqm sfm, whose ``command`` is "sfm":
    no guided growth unless asked for)."""
    add_quickmatch_params(p, ("rho", "ratio_density", "kernel", "parent"), kernel_default=DEFAULT_KERNEL,
                          notes={"kernel": ": the reference code's Gaussian, or the finite quadratic one that dqm "
                                           "run and dqm stream use (docs/quickmatch.md)"})
    p.add_argument("--threads", type=positive_int_arg, default=None, help="worker threads (default: all cores)")
    p.add_argument("--max-memory", type=memory_size, default=None, metavar="SIZE",
                   help="memory budget of the whole process's peak, e.g. 8G or 512M, what it already holds included "
                        "(default: 70%% of the available memory); an exact run "
                        "whose candidate edges would not fit streams its parents instead (same clusters), and "
                        "an input that cannot fit at all is refused before any work")
    p.add_argument("--engine", choices=ENGINES, default="auto",
                   help=f"exact: every pair of features; fast: only pairs within each feature's nearest inverted "
                        f"lists (co-membership F1 >= 0.995 against exact on the sets of docs/quickmatch.md, 2-3x "
                        f"faster from ~50k features); auto (default): exact below {FAST_FROM:,} features, fast from "
                        f"there")
    p.add_argument("--exact", dest="engine", action="store_const", const="exact",
                   help="the exact engine whatever the size (same as --engine exact)")
    p.add_argument("--approximate", action="store_true",
                   help="approximate mode for very large sets (needs faiss-cpu): densities and parents from each "
                        "feature's --neighbors nearest neighbours; co-membership F1 >= 0.99 against exact in "
                        "our measurements (docs/quickmatch.md)")
    p.add_argument("--neighbors", type=int, default=DEFAULT_NEIGHBORS, metavar="K",
                   help=f"neighbours per feature with --approximate (default {DEFAULT_NEIGHBORS})")
    p.add_argument("--verify", action="store_true",
                   help="geometric verification: per image pair, RANSAC (OpenCV USAC) on the matches the clusters "
                        "imply: a fundamental matrix and a homography, the inliers of the one with more, as COLMAP "
                        "counts them; members that the verified pairs reject are split off (C1 and C2 still hold; "
                        "needs keypoints; no guided growth then)")
    p.add_argument("--guided", action=argparse.BooleanOptionalAction, default=None, help=GUIDED_HELP[command])
    p.set_defaults(grow_by_default=command == "match")


#: --guided's help per command: growth is dqm match's default, not dqm sfm's (docs/sfm.md, "One default for
#: matching, another for SfM")
GUIDED_HELP = {
    "match": "geometry-guided growth: the clusters are verified as with --verify, then each verified image pair "
             "links features that fit its geometry within 2 px (the homography of a planar pair, else the "
             "fundamental matrix) and are mutual nearest descriptors among those (ratio 0.8, <= 1.5 sigma; on a "
             "planar pair the descriptors are made again from the images, rectified into one frame, where the "
             "images are at hand, and links reach 4 px at <= 1.0 sigma); clusters join along the links where C2 "
             "and every verified pair allow. On by default wherever the "
             "features have keypoints (more complete clusters: higher F1 on every image set of "
             "docs/evaluation.md), except with --verify or a COLMAP database as INPUT (its matches go back to "
             "COLMAP's mapper, whose cameras growth worsens); --no-guided: QuickMatch's clusters as they are",
    "sfm": "geometry-guided growth before the mapper, as dqm match does it by default: off by default, because "
           "it worsens the cameras (docs/sfm.md); the model-guided triangulation after the mapper adds matches "
           "with the cameras known instead",
}


def engine_of(args) -> str:
    """The engine of the parsed options: --approximate is its own (k-nearest-neighbour) engine, so with it
    only an explicit --engine fast is a conflict."""
    if args.approximate and args.engine == "fast":
        raise InputError("--approximate and --engine fast are two different engines; give one")
    return "exact" if args.approximate else args.engine


def params_from(args) -> QuickMatchParams:
    """The QuickMatch parameters of the parsed options (:func:`add_cluster_options`)."""
    return QuickMatchParams(**{k: getattr(args, k) for k in QuickMatchParams.names()})


def memory_size(text: str) -> int:
    """argparse type of --max-memory: bytes, checked before any work."""
    try:
        return parse_size(text)
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def is_features_file(path) -> bool:
    """A FEATURES file is known by its content (a zip archive) or its .npz suffix, in any case."""
    return io.is_npz(path) or Path(path).suffix.lower() == ".npz"


def load_input(args) -> io.FeatureSet:
    """FEATURES .npz file(s), combined (each file numbers its own images: :func:`dqm.io.merge_features`),
    or SIFT of the images named by the inputs (progress bar per image); :func:`is_features_file` tells them apart."""
    from ..vision.colmap import is_database

    databases = [p for p in args.inputs if is_database(p)]
    if databases:
        if len(args.inputs) > 1 or getattr(args, "image_list", None):
            other = next((p for p in args.inputs if p != databases[0]), "--image-list")
            raise InputError(f"a COLMAP database ({databases[0]}) is matched on its own, not with {other}; "
                             "give one database, or FEATURES files, or images")
        from ..vision.colmap import import_database

        image_dir = getattr(args, "image_dir", None)
        if image_dir is not None:
            if not Path(image_dir).is_dir():
                raise InputError(f"--image-dir {image_dir}: no such folder")
            image_dir = Path(image_dir).resolve()  # CLUSTERS files name their images by absolute path
        return import_database(databases[0], image_dir=image_dir)
    if getattr(args, "image_dir", None):
        raise InputError("--image-dir names the folder of a COLMAP database's images; the inputs hold no database")
    features = [p for p in args.inputs if is_features_file(p)]
    if not features:
        if not args.inputs and not getattr(args, "image_list", None):
            raise InputError("no input: give FEATURES.npz file(s), images (folders, globs, files) or --image-list")
        return extract(args, min_images=2)
    if len(features) < len(args.inputs) or getattr(args, "image_list", None):
        others = [p for p in args.inputs if p not in features] or ["--image-list"]
        raise InputError(f"the inputs mix FEATURES files ({features[0]}) and images ({others[0]}); match either "
                         "FEATURES files or images (dqm extract turns images into FEATURES)")
    seen = {}
    for p in features:
        key = Path(p).resolve()
        if key in seen:
            raise InputError(f"{p} is given twice (as {seen[key]} and {p}); give each FEATURES file once")
        seen[key] = p
    fs, note = io.merge_features([io.load_features(p) for p in features], features)
    if note:
        print(f"note: {note}")
    return fs


def _target_database(args) -> Path | None:
    """The COLMAP database that --into-database writes into (checked before any work), or None without it."""
    if not args.into_database:
        if args.out is None:
            raise InputError("dqm match needs --out CLUSTERS.npz (or, with a COLMAP database as INPUT, "
                             "--into-database)")
        return None
    from ..vision.colmap import check_matches_target, is_database

    if len(args.inputs) != 1 or not is_database(args.inputs[0]) or getattr(args, "image_list", None):
        given = " ".join(args.inputs) or "--image-list"
        raise InputError(f"--into-database writes into the COLMAP database given as the only INPUT; got {given}")
    return check_matches_target(args.inputs[0], overwrite=args.overwrite)


def run(args) -> int:
    t0 = time.perf_counter()
    database = _target_database(args)
    if args.out is not None:
        outputs.check_file(args.out, "--out", (".npz",), overwrite=args.overwrite)
    if args.tracks_csv:
        outputs.check_file(args.tracks_csv, "--tracks-csv", (".csv",), overwrite=args.overwrite)
        outputs.check_distinct(*((("--out", args.out),) if args.out else ()), ("--tracks-csv", args.tracks_csv))
    fs = load_input(args)
    n_images = len(np.unique(fs.image_ids))
    if len(fs) == 0:
        raise InputError("no features to match (empty input)")
    if n_images < 2:
        raise InputError(f"all {len(fs)} features come from one image; matching needs at least two images")
    result, extra = cluster(args, fs)
    if args.out is not None:
        from ..vision.colmap import is_database

        extracted = not any(is_database(p) or is_features_file(p) for p in args.inputs)
        sift = {"preset": args.preset, "max_features": args.max_features} if extracted else {}
        io.save_clusters(args.out, fs, result, dict(extra or {}, **sift) or None)
    if args.tracks_csv:
        n = io.save_tracks_csv(args.tracks_csv, result.labels, fs.image_ids, fs.keypoints, fs.image_names)
        print(f"wrote {n} tracks to {args.tracks_csv}")
    if database is not None:
        from ..vision.colmap import write_matches

        s = write_matches(database, result.labels, fs.image_ids, overwrite=args.overwrite,
                          num_threads=args.threads or -1, progress=not args.quiet)
        print(f"wrote into {database}: {s.pairs_line()}, "
              f"{s.verified_line()} (COLMAP's geometric verification)")
        image_dir = repr(str(args.image_dir)) if args.image_dir else "IMAGE_DIR"  # else a placeholder, as OUTPUT_DIR
        print(f"reconstruct: pycolmap.incremental_mapping({str(database)!r}, {image_dir}, OUTPUT_DIR)")
    if args.out is not None:
        print(f"wrote {args.out} ({time.perf_counter() - t0:.2f} s in all)")
    else:  # what went into the database was said above
        print(f"done in {time.perf_counter() - t0:.2f} s")
    return 0


def grows_by_default(args, fs: io.FeatureSet) -> bool:
    """Whether the command grows the clusters by geometry when --guided / --no-guided is not given: dqm match
    does where the features have keypoints, unless --verify asks for verification alone or the input is a
    COLMAP database (its matches go back to COLMAP's mapper, with --into-database or dqm export colmap); dqm
    sfm does not (:data:`GUIDED_HELP`)."""
    from ..vision.colmap import is_database

    if not args.grow_by_default or args.verify or any(is_database(p) for p in args.inputs):
        return False
    if fs.keypoints is None:
        print("note: the features have no keypoints, so the clusters are not grown by geometry (--no-guided "
              "silences this)")
        return False
    return True


def cluster(args, fs: io.FeatureSet):
    """QuickMatch on the features with the command's options, then guided growth or verification when asked
    for; prints what each step did. Returns the result and its extra params."""
    for flag, on in (("verify", args.verify), ("guided", args.guided)):
        if on and fs.keypoints is None:
            raise InputError(f"--{flag} needs keypoints: the FEATURES file has none (match images, or add 'keypoints')")
    guided = grows_by_default(args, fs) if args.guided is None else bool(args.guided)
    bar = ProgressBar("quickmatch", force=False if args.quiet else None, unit="features")
    result = quickmatch(fs.descriptors, fs.image_ids, params=params_from(args), n_threads=args.threads,
                        progress=bar, max_memory=args.max_memory, approximate=args.approximate,
                        n_neighbors=args.neighbors, engine=engine_of(args))
    print(result.summary())
    extra = None
    if guided:
        from ..vision.guided import guided_labels

        bar = ProgressBar("geometry (verify, then link)", force=False if args.quiet else None, unit="pairs")
        images = None if fs.image_names is None else [str(name) for name in fs.image_names]
        labels, gs = guided_labels(result, fs.keypoints, fs.descriptors, n_threads=args.threads, progress=bar,
                                   images=images)
        result = dataclasses.replace(result, labels=labels)
        extra = {"verify": True, "guided": True}
        sizes = np.bincount(labels)
        print(f"{gs.summary()}: {len(sizes)} clusters, {int((sizes >= 2).sum())} of them span 2+ images")
    elif args.verify:
        from ..vision.verify import verify_clusters

        bar = ProgressBar("verification", force=False if args.quiet else None, unit="pairs")
        labels, vs = verify_clusters(result.labels, fs.image_ids, fs.keypoints, progress=bar)
        result = dataclasses.replace(result, labels=labels)
        extra = {"verify": True}
        print(f"verified {vs.n_verified} of {vs.n_pairs} image pairs ({vs.n_planar} planar or panoramic): "
              f"{vs.n_inliers} of {vs.n_matches} implied matches are inliers; {vs.n_split} features split off")
    return result, extra
