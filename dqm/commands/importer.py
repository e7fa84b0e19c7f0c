"""Bring features made elsewhere into dqm: a COLMAP database or hloc's feature file.

    dqm import colmap database.db --out features.npz --image-dir images/
    dqm import h5 feats-superpoint.h5 --out features.npz --image-dir images/
    dqm match features.npz --out clusters.npz

COLMAP: keypoints (converted to OpenCV's pixel convention), uint8 descriptors and image names.
hloc: every image group's keypoints and descriptors (any dimension, e.g. SuperPoint's 256).
--image-dir prefixes the stored names, so the FEATURES file names the image files. Needs
pycolmap (colmap) or h5py (h5): pip install 'dqm[colmap]'.
"""
from __future__ import annotations

import logging
import time

import numpy as np

from .. import io, outputs
from ..wording import count

NAME = "import"
HELP = "convert a COLMAP database or an hloc .h5 feature file to a FEATURES .npz"

LOG = logging.getLogger("dqm.commands")


def add_arguments(p) -> None:
    p.add_argument("format", choices=("colmap", "h5"), help="colmap: a COLMAP database; h5: hloc's features")
    p.add_argument("source", metavar="FILE", help="database.db or features.h5")
    p.add_argument("--out", required=True, help="FEATURES.npz to write")
    outputs.add_overwrite_option(p)
    p.add_argument("--image-dir", default=None, metavar="DIR", help="folder the stored image names are relative to")


def run(args) -> int:
    t0 = time.perf_counter()
    out = outputs.check_file(args.out, "--out", (".npz",), overwrite=args.overwrite)
    LOG.info("import %s: reading the features of %s", args.format, args.source)
    if args.format == "colmap":
        from ..vision.colmap import import_database, require_pycolmap

        require_pycolmap(what="dqm import colmap")

        fs = import_database(args.source, image_dir=args.image_dir)
    else:
        from ..vision.hloc import read_h5_features

        fs = read_h5_features(args.source, image_dir=args.image_dir)
    io.save_features(out, fs)
    print(f"wrote {len(fs)} features ({fs.descriptors.shape[1]}-D {fs.descriptors.dtype}) of "
          f"{count(len(np.unique(fs.image_ids)), 'image')} to {out} ({time.perf_counter() - t0:.1f} s)")
    return 0
