"""Extract SIFT features from images into a FEATURES file (the input of dqm match and dqm run).

IMAGES: folders, glob patterns or image files (image id k is the k-th image), and/or
--image-list FILE (one image path a line, relative to the list's folder; blank lines and
# comments ignored). A folder's images come in natural order (img2 before img10); its
sub-folders are read only with --recursive (COLMAP and hloc always recurse into the image
folder; dqm keeps a folder flat unless asked), and a glob's ** matches any depth.
The FEATURES format is in docs/formats.md.

    dqm extract photos/ --out features.npz
    dqm extract dataset/ --recursive --out features.npz       # dataset/seq1/*.jpg, dataset/seq2/*.jpg ...
    dqm extract --image-list train.txt --out features.npz
    dqm extract 'frames/*.png' --out features.npz --preset paper --max-features 2000
    dqm match features.npz --out clusters.npz
"""
from __future__ import annotations

import logging
import sys
import time

from .. import io, outputs
from ..progress import ProgressBar
from ..vision.features import DEFAULT_PRESET, PRESET_NAMES, SFM_PRESET
from ..wording import count

LOG = logging.getLogger("dqm.commands")

NAME = "extract"
HELP = "SIFT features of images into a FEATURES .npz"


def add_image_options(p, default_preset: str = DEFAULT_PRESET, auto: str = "", auto_max_features: str = "") -> None:
    """Image-input and SIFT options shared by the commands that read images (see :func:`extract`). ``auto``:
    what ``--preset auto`` chooses, for a command that offers it (the command resolves it before extracting);
    ``auto_max_features``: what an absent ``--max-features`` means there (its default is then ``None``, which
    the command resolves with the preset)."""
    p.add_argument("--image-list", default=None, metavar="FILE",
                   help="also read the images named in FILE, one path a line (relative paths from FILE's "
                        "folder; blank lines and # comments ignored), in the list's order")
    p.add_argument("--recursive", action="store_true",
                   help="read the images of the given folders' sub-folders too (natural order of the paths "
                        "below each folder), as COLMAP and hloc read an image folder")
    words = {"sfm": "OpenCV's SIFT at contrast threshold 0.03 with RootSIFT descriptors (about 1.3x rootsift's "
                    "features; the best cameras in docs/sfm.md)",
             "rootsift": "OpenCV's SIFT with RootSIFT descriptors (Hellinger-normalised, as COLMAP stores them; "
                         "better F1 than plain SIFT on every dataset of docs/evaluation.md)",
             "colmap": "pycolmap's own SIFT with COLMAP's defaults (needs pycolmap; about 4x the extraction time)",
             "budget": "OpenCV's SIFT at contrast threshold 0.02, each image's 8,192 strongest locations (every "
                       "orientation kept: COLMAP's budget), RootSIFT descriptors (more 3-D points on small scenes, "
                       "fewer on large ones: docs/sfm.md)",
             "opencv": "OpenCV's plain SIFT",
             **({"auto": auto} if auto else {}),
             "paper": "the seed paper's settings (nOctaveLayers=6, contrastThreshold=0.10, edgeThreshold=15, "
                      "sigma=1.0)"}
    p.add_argument("--preset", choices=sorted(PRESET_NAMES + (("auto",) if auto else ())), default=default_preset,
                   help="SIFT settings: " + "; ".join(f"{k}{' (default)' if k == default_preset else ''} = {v}"
                                                      for k, v in words.items()))
    p.add_argument("--max-features", type=int, default=None if auto_max_features else 0,
                   help="SIFT features per image, 0 = no limit (colmap: COLMAP's 8192)"
                        + (f"; default: {auto_max_features}" if auto_max_features else ""))
    p.add_argument("--skip-bad-images", action="store_true",
                   help="leave out unreadable image files (listed in a warning) instead of refusing the run")


def add_arguments(p) -> None:
    p.add_argument("inputs", nargs="*", metavar="IMAGES",
                   help="image folders, glob patterns or files (or none, with --image-list)")
    p.add_argument("--out", required=True, help="FEATURES.npz to write")
    outputs.add_overwrite_option(p)
    add_image_options(p, default_preset=SFM_PRESET)
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def extract(args, min_images: int) -> io.FeatureSet:
    """SIFT of the images named by ``args.inputs`` and ``args.image_list`` (``args.recursive``: folders with
    their sub-folders), with the shared options of :func:`add_image_options`; reports skipped files."""
    from ..vision.features import extract_images

    LOG.info("SIFT: preset %s%s", args.preset, f", at most {args.max_features} features per image"
             if args.max_features else "")
    bar = ProgressBar("sift", force=False if args.quiet else None, unit="images")
    skipped = []
    fs = extract_images(args.inputs, preset=args.preset, max_features=args.max_features, progress=bar,
                        min_images=min_images, skip_bad=args.skip_bad_images, skipped=skipped,
                        recursive=args.recursive, image_list=args.image_list)
    if skipped:
        print(f"warning: skipped {count(len(skipped), 'unreadable image')}: {', '.join(skipped)}", file=sys.stderr)
    empty = [str(fs.image_names[k]) for k in range(len(fs.image_names)) if not (fs.image_ids == k).any()]
    if empty:
        print(f"note: no SIFT features in {len(empty)} image(s): {', '.join(empty[:5])}")
    return fs


def run(args) -> int:
    t0 = time.perf_counter()
    outputs.check_file(args.out, "--out", (".npz",), overwrite=args.overwrite)
    fs = extract(args, min_images=1)
    io.save_features(args.out, fs)
    print(f"wrote {count(len(fs), 'feature')} of {count(len(fs.image_names), 'image')} to {args.out} "
          f"({time.perf_counter() - t0:.1f} s)")
    return 0
