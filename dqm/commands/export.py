"""Export QuickMatch clusters to the tools structure-from-motion users run next.

    dqm export colmap clusters.npz --database model/database.db
    python -c "import pycolmap; pycolmap.incremental_mapping('model/database.db', IMAGE_DIR, 'model/sparse')"

The database gets one camera per image (EXIF focal length when the image has one, otherwise
COLMAP's default 1.2 x the larger side), the keypoints, the matches the clusters imply for
every image pair (every two members of a cluster) and two-view geometries verified by COLMAP
itself, so incremental mapping runs with no further step. --tracks also writes the clusters
of 2+ features as a TRACKS CSV (docs/formats.md). Needs pycolmap: pip install 'dqm[colmap]'.
"""
from __future__ import annotations

import time

from .. import io, outputs
from ..validation import InputError

NAME = "export"
HELP = "export clusters as a COLMAP database (keypoints, matches, verified geometries) and tracks"


def add_arguments(p) -> None:
    p.add_argument("format", choices=("colmap",), help="what to write")
    p.add_argument("clusters", metavar="CLUSTERS", help="CLUSTERS.npz from dqm match (with keypoints and images)")
    p.add_argument("--database", required=True, metavar="DB", help="COLMAP database to create (must not exist)")
    p.add_argument("--image-dir", default=None, metavar="DIR",
                   help="folder COLMAP will read the images from; names in the database are relative to it "
                        "(default: the images' common folder)")
    p.add_argument("--tracks", default=None, metavar="CSV", help="also write the tracks (clusters of 2+) as CSV")
    p.add_argument("--no-verify", action="store_true",
                   help="write matches only, no two-view geometries (run COLMAP's verification yourself)")


def run(args) -> int:
    from ..vision import colmap

    t0 = time.perf_counter()
    colmap.require_pycolmap()
    db = outputs.check_file(args.database, "--database")
    if db.exists():
        raise InputError(f"--database {db} exists; the export creates a new database (remove it or pick another)")
    if args.tracks:
        outputs.check_file(args.tracks, "--tracks")
    c = io.load_clusters(args.clusters)
    for key in ("keypoints", "image_names", "image_ids"):
        if key not in c:
            raise InputError(f"{args.clusters}: no {key!r} array; the export needs keypoints and image names "
                             "(match images, or FEATURES with keypoints and image_names)")
    paths = colmap.resolve_images(c["image_names"], args.image_dir)
    s = colmap.export_database(db, c["keypoints"], c["image_ids"], paths, c["labels"],
                               image_dir=args.image_dir, descriptors=c.get("descriptors"),
                               verify=not args.no_verify)
    print(f"wrote {db}: {s.n_images} images, {s.n_keypoints} keypoints, {s.n_matches} matches in "
          f"{s.n_image_pairs} image pairs" + ("" if args.no_verify else f", {s.n_verified_pairs} verified pairs")
          + f" ({time.perf_counter() - t0:.1f} s)")
    if args.tracks:
        n = io.save_tracks_csv(args.tracks, c["labels"], c["image_ids"], c["keypoints"], c["image_names"])
        print(f"wrote {n} tracks to {args.tracks}")
    print(f"reconstruct: pycolmap.incremental_mapping({str(db)!r}, {str(s.image_dir)!r}, OUTPUT_DIR)")
    return 0
