"""Export QuickMatch clusters to the tools structure-from-motion users run next: COLMAP and hloc.

    dqm export colmap clusters.npz --database model/database.db
    dqm export colmap clusters.npz --database model/database.db --camera-model OPENCV --single-camera
    python -c "import pycolmap; pycolmap.incremental_mapping('model/database.db', IMAGE_DIR, 'model/sparse')"

    dqm export hloc clusters.npz --matches out/matches.h5 --pairs out/pairs.txt --features out/features.h5
    # then hloc: reconstruction.main(sfm_dir, IMAGE_DIR, pairs, features, matches)

COLMAP, --database: a new database gets the cameras (one per image by default, COLMAP's SIMPLE_RADIAL model
unless --camera-model; --single-camera / --single-camera-per-folder share one, as COLMAP's
ImageReader.single_camera / single_camera_per_folder; EXIF focal length when the image has one,
otherwise COLMAP's default 1.2 x the larger side, or --camera-params for all), the keypoints,
the matches the clusters imply for every image pair (every two members of a cluster) and
two-view geometries verified by COLMAP itself, so incremental mapping runs with no further step.
--into-database instead writes the matches and geometries into the existing database the clusters
were matched from (dqm match database.db), as COLMAP's matchers do: its cameras and features stay.

hloc: matches.h5 in hloc's match_features layout (a group per image pair, matches0 and
matching_scores0), pairs.txt (one "name0 name1" line per image pair with a match) and, with
--features, hloc's local-features file (keypoints, descriptors, image sizes). Image names are
relative to --image-dir (default: the images' common folder): give the image folder that
hloc's reconstruction / triangulation will read, and the names in its features file if it has one.

--tracks also writes the clusters of 2+ features as a TRACKS CSV (docs/formats.md). Every
option and output is checked before any work; an existing database or hloc file is never replaced. Needs
pycolmap (colmap) or h5py (hloc): pip install 'dqm[colmap]'.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from .. import io, outputs
from ..validation import InputError

NAME = "export"
HELP = "export clusters as a COLMAP database or hloc matches / pairs / features files, and tracks"

#: the options that only one format takes (dest name -> format)
_ONLY_FOR = {"database": "colmap", "into_database": "colmap", "no_verify": "colmap", "camera_model": "colmap",
             "camera_params": "colmap", "single_camera": "colmap", "single_camera_per_folder": "colmap",
             "partners": "colmap", "matches": "hloc", "pairs": "hloc", "features": "hloc"}

LOG = logging.getLogger("dqm.commands")


def add_camera_sharing_options(group) -> None:
    """--single-camera and --single-camera-per-folder, which exclude each other (dqm export colmap, dqm sfm)."""
    shared = group.add_mutually_exclusive_group()
    shared.add_argument("--single-camera", action="store_true",
                        help="one camera for all images (they must have one size: a video's frames), as COLMAP's "
                             "ImageReader.single_camera")
    shared.add_argument("--single-camera-per-folder", action="store_true",
                        help="one camera per folder of the image names (one size each: a video a folder), as "
                             "COLMAP's ImageReader.single_camera_per_folder")


def add_cluster_matches_option(group) -> None:
    """--cluster-matches: which members of a cluster the mapper gets as matches (dqm export colmap and hloc, dqm
    sfm), default :data:`dqm.vision.colmap.DEFAULT_CLUSTER_MATCHES`."""
    from ..vision.colmap import CLUSTER_MATCHES, DEFAULT_CLUSTER_MATCHES, SEQUENCE_FILL, SEQUENCE_FROM

    group.add_argument("--cluster-matches", choices=CLUSTER_MATCHES, default=DEFAULT_CLUSTER_MATCHES,
                       help=f"auto (default): every two members of a cluster, but log-spaced members in a track "
                            f"through a run of frames (more than {SEQUENCE_FROM} members, in "
                            f"{SEQUENCE_FILL * 100:.0f}%% or more of the images from its first to its last: a "
                            f"video's; the mapper's input and time cut, docs/sfm.md); all: every two members; log: "
                            f"each member with those 1, 2, 4, ... places after it in image order, at most s log2 s "
                            f"matches for a cluster of s, one track still")


def camera_sharing(args) -> str:
    """The camera sharing those options ask for: ``single``, ``per-folder`` or ``per-image``
    (:data:`dqm.vision.colmap.CAMERA_MODES`)."""
    return "single" if args.single_camera else "per-folder" if args.single_camera_per_folder else "per-image"


def add_arguments(p) -> None:
    p.add_argument("format", choices=("colmap", "hloc"), help="what to write")
    p.add_argument("clusters", metavar="CLUSTERS", help="CLUSTERS.npz from dqm match (with keypoints and images)")
    p.add_argument("--image-dir", default=None, metavar="DIR",
                   help="folder COLMAP / hloc will read the images from; image names are relative to it "
                        "(default: the images' common folder)")
    p.add_argument("--tracks", default=None, metavar="CSV", help="also write the tracks (clusters of 2+) as CSV")
    p.add_argument("--quiet", action="store_true", help="no progress bar (there is none when output is piped)")
    outputs.add_overwrite_option(p)
    g = p.add_argument_group("colmap")
    g.add_argument("--database", default=None, metavar="DB", help="COLMAP database (.db) to create")
    g.add_argument("--into-database", default=None, metavar="DB",
                   help="instead of creating one: write the matches and COLMAP-verified geometries into this "
                        "existing COLMAP database, the one the clusters were matched from (dqm match DB), as COLMAP's "
                        "matchers do; its cameras and features stay (the camera options do not apply); refused if it "
                        "already holds matches, unless --overwrite")
    g.add_argument("--partners", type=int, default=0, metavar="N",
                   help="write only each image's N image pairs with the most shared clusters (and the pairs where it "
                        "is among the other image's N): pairs that grow with the images, as dqm sfm's default 100 "
                        "(default 0: every pair)")
    g.add_argument("--no-verify", action="store_true",
                   help="write matches only, no two-view geometries (run COLMAP's verification yourself)")
    g.add_argument("--camera-model", default=None, metavar="MODEL",
                   help="COLMAP camera model of every camera: SIMPLE_RADIAL (default, as COLMAP's), "
                        "SIMPLE_PINHOLE, PINHOLE, RADIAL, OPENCV, FULL_OPENCV, OPENCV_FISHEYE, ...")
    g.add_argument("--camera-params", default=None, metavar="P1,P2,...",
                   help="the model's parameters for every camera, comma-separated in COLMAP's order "
                        "(e.g. f,cx,cy,k for SIMPLE_RADIAL), as COLMAP's ImageReader.camera_params; marked as "
                        "a prior (default: EXIF or 1.2 x the larger side, image centre, no distortion)")
    add_camera_sharing_options(g)
    g = p.add_argument_group("colmap and hloc")
    add_cluster_matches_option(g)
    g = p.add_argument_group("hloc")
    g.add_argument("--matches", default=None, metavar="H5", help="hloc matches file (.h5) to write")
    g.add_argument("--pairs", default=None, metavar="TXT", help="hloc pairs file (.txt) to write")
    g.add_argument("--features", default=None, metavar="H5",
                   help="also write hloc's local-features file (keypoints, descriptors, image sizes; must not "
                        "exist); leave out to use the features file the clusters were imported from")


def _check_options(args) -> None:
    """One line for an option that the chosen format does not take, or a missing required one."""
    for dest, fmt in _ONLY_FOR.items():
        value = getattr(args, dest)
        if fmt != args.format and value not in (None, False):
            option = "--" + dest.replace("_", "-")
            raise InputError(f"{option} is an option of dqm export {fmt}, not of dqm export {args.format}")
    if args.format == "colmap":
        if (args.database is None) == (args.into_database is None):
            raise InputError("dqm export colmap needs one of --database (a new database) or --into-database (the "
                             "existing one the clusters were matched from)")
        camera = [o for o in ("camera_model", "camera_params", "single_camera", "single_camera_per_folder")
                  if getattr(args, o) not in (None, False)]
        if args.into_database is not None and camera:
            raise InputError(f"--{camera[0].replace('_', '-')} makes the cameras of a new database; --into-database "
                             "keeps the database's own cameras")
        if args.partners < 0:
            raise InputError(f"--partners must be >= 0 (0: every image pair), got {args.partners}")
        return
    for dest in ("matches", "pairs"):
        if getattr(args, dest) is None:
            raise InputError(f"dqm export {args.format} needs --{dest}")




def _load(args, needs: tuple) -> dict:
    """The CLUSTERS file, with the arrays the export ``needs`` (one line naming a missing one)."""
    LOG.info("export %s: reading %s", args.format, args.clusters)
    c = io.load_clusters(args.clusters)
    for key in needs:
        if key not in c:
            raise InputError(f"{args.clusters}: no {key!r} array; the export needs keypoints and image names "
                             "(match images, or FEATURES with keypoints and image_names)")
    if "image_ids" in c:
        io.check_one_feature_an_image(c["labels"], c["image_ids"], c.get("image_names"), args.clusters,
                                      f"dqm export {args.format}")
    return c


def run(args) -> int:
    t0 = time.perf_counter()
    _check_options(args)
    if args.tracks:
        outputs.check_file(args.tracks, "--tracks", (".csv",), overwrite=args.overwrite)
    if args.format == "colmap":
        c, image_dir = _run_colmap(args, t0)
    else:
        c, image_dir = _run_hloc(args, t0)
    if args.tracks:
        n = io.save_tracks_csv(args.tracks, c["labels"], c["image_ids"], c.get("keypoints"), c["image_names"])
        print(f"wrote {n} tracks to {args.tracks}")
    if args.format == "colmap":
        database = args.database if args.database is not None else args.into_database
        print(f"reconstruct: pycolmap.incremental_mapping({str(database)!r}, {str(image_dir)!r}, OUTPUT_DIR)")
    else:
        features = args.features or "FEATURES_H5"
        print(f"reconstruct: hloc.reconstruction.main(Path(SFM_DIR), Path({str(image_dir)!r}), "
              f"Path({args.pairs!r}), Path({features!r}), Path({args.matches!r}))")
    return 0


def _run_colmap(args, t0: float):
    from ..vision import colmap

    colmap.require_pycolmap(what="dqm export colmap")
    if args.into_database is not None:
        return _run_colmap_into(args, t0)
    camera = colmap.camera_options(args.camera_model or colmap.DEFAULT_CAMERA_MODEL, camera_sharing(args),
                                   args.camera_params)
    db = outputs.check_file(args.database, "--database", (".db", ".sqlite", ".sqlite3"), overwrite=args.overwrite)
    if args.tracks:
        outputs.check_distinct(("--database", db), ("--tracks", args.tracks))
    c = _load(args, ("keypoints", "image_names", "image_ids"))
    paths = colmap.resolve_images(c["image_names"], args.image_dir)
    s = colmap.export_database(db, c["keypoints"], c["image_ids"], paths, c["labels"],
                               image_dir=args.image_dir, descriptors=c.get("descriptors"),
                               verify=not args.no_verify, camera=camera, partners=args.partners,
                               cluster_matches=args.cluster_matches,
                               progress=not args.quiet)
    print(f"wrote {db}: {s.n_images} images, {s.n_cameras} {camera.model} camera(s), {s.n_keypoints} keypoints, "
          f"{s.pairs_line()}"
          + ("" if args.no_verify else f", {s.verified_line()}")
          + f" ({time.perf_counter() - t0:.1f} s)")
    return c, s.image_dir


def _run_colmap_into(args, t0: float):
    """--into-database: the clusters' matches and COLMAP's verified geometries into the database they were
    matched from (:func:`dqm.vision.colmap.write_matches`)."""
    from ..vision import colmap

    db = colmap.check_matches_target(args.into_database, overwrite=args.overwrite)
    if args.tracks:
        outputs.check_distinct(("--into-database", db), ("--tracks", args.tracks))
    c = _load(args, ("image_names", "image_ids"))
    s = colmap.write_matches(db, c["labels"], c["image_ids"], overwrite=args.overwrite, verify=not args.no_verify,
                             names=[str(n) for n in c["image_names"]], partners=args.partners,
                             cluster_matches=args.cluster_matches,
                             progress=not args.quiet)
    verified = "" if args.no_verify else f", {s.verified_line()}"
    print(f"wrote into {db}: {s.pairs_line()}{verified} "
          f"({time.perf_counter() - t0:.1f} s)")
    return c, args.image_dir or "IMAGE_DIR"


def _run_hloc(args, t0: float):
    from ..vision import colmap, hloc

    hloc.require_h5py()
    outs = {"--matches": outputs.check_file(args.matches, "--matches", (".h5",), overwrite=args.overwrite),
            "--pairs": outputs.check_file(args.pairs, "--pairs", (".txt",), overwrite=args.overwrite)}
    if args.features:
        outs["--features"] = outputs.check_file(args.features, "--features", (".h5",), overwrite=args.overwrite)
    outputs.check_distinct(*outs.items(), *((("--tracks", args.tracks),) if args.tracks else ()))
    c = _load(args, ("image_names", "image_ids") + (("keypoints",) if args.features else ()))
    paths = []
    for name in c["image_names"].tolist():  # a relative name not found as given is taken under --image-dir
        p = Path(str(name))
        if args.image_dir is not None and not p.is_absolute() and not p.exists():
            p = Path(args.image_dir) / p
        paths.append(p)
    image_dir, names = colmap.image_folder(paths, None if args.image_dir is None else Path(args.image_dir))
    names = hloc.check_pair_names(names)
    if args.features:
        described = "descriptors" in c  # a distributed job's CLUSTERS file has none
        fs = io.FeatureSet(descriptors=c["descriptors"] if described else np.zeros((len(c["labels"]), 1), np.uint8),
                           image_ids=c["image_ids"], keypoints=c["keypoints"],
                           image_names=np.array([str(p) for p in paths]))
        hloc.write_h5_features(outs["--features"], fs, names=names, with_descriptors=described)
        if not described:
            print(f"note: {args.clusters} holds no descriptors (a distributed job's clusters): {args.features} has "
                  "keypoints only, which is what hloc's reconstruction and triangulation read")
    m = hloc.write_h5_matches(outs["--matches"], c["labels"], c["image_ids"], names, matches=args.cluster_matches)
    hloc.write_pairs(outs["--pairs"], m.pairs)
    wrote = ", ".join(str(p) for p in outs.values())
    print(f"wrote {wrote}: {len(names)} images under {image_dir}, {m.n_matches} matches in {len(m.pairs)} "
          f"image pairs ({time.perf_counter() - t0:.1f} s)")
    return c, image_dir
