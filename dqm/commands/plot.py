"""Draw matches and evaluation results as PNG (or PDF / SVG, from --out's suffix).

    dqm plot pair CLUSTERS.npz --images 0 1 --out pair.png [--truth SEQ_FOLDER]
    dqm plot clusters CLUSTERS.npz --out clusters.png [--count 6] [--min-size 3]
    dqm plot sizes CLUSTERS.npz --out sizes.png
    dqm plot pr EVALUATION.json --out-dir plots/

pair: two images side by side with a line per match implied by the clusters
(with --truth, an Oxford-layout folder, lines are green when the homography
maps one keypoint within --tol pixels of the other, red otherwise).
clusters: the largest clusters, one row each, a patch around every feature.
sizes: histogram of cluster sizes. pr: the PR curves of every dataset of a
``dqm evaluate`` run.

pair and clusters need the images: a CLUSTERS file made by ``dqm match`` from
images records their paths (image_names); --image-dir resolves relative ones.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from .. import io, outputs, plots
from ..evaluation import PRCurve, cluster_pairs, reprojection_error
from ..validation import InputError
from . import HelpFormatter

NAME = "plot"
HELP = "draw matches (pair, clusters), cluster sizes or PR curves"

LOG = logging.getLogger("dqm.commands")


def add_arguments(p) -> None:
    sub = p.add_subparsers(dest="what", metavar="WHAT", required=True)
    a = sub.add_parser("pair", formatter_class=HelpFormatter, help="two images with lines between matched features")
    a.add_argument("clusters", metavar="CLUSTERS.npz")
    a.add_argument("--images", type=int, nargs=2, default=(0, 1), metavar=("I", "J"), help="image ids (default 0 1)")
    a.add_argument("--out", required=True, help="figure file (.png, .pdf, .svg, ...)")
    outputs.add_overwrite_option(a)
    a.add_argument("--truth", default=None, help="Oxford-layout folder with H1toNp: colour lines by correctness")
    a.add_argument("--tol", type=float, default=5.0, help="pixels, with --truth")
    a.add_argument("--max-lines", type=int, default=300,
                   help="draw at most this many matches (a random subset)")
    a.add_argument("--image-dir", default=None, help=IMAGE_DIR_HELP)
    c = sub.add_parser("clusters", formatter_class=HelpFormatter,
                       help="patches of the features of the largest clusters")
    c.add_argument("clusters", metavar="CLUSTERS.npz")
    c.add_argument("--out", required=True, help="figure file (.png, .pdf, .svg, ...)")
    outputs.add_overwrite_option(c)
    c.add_argument("--count", type=int, default=6, help="clusters to draw (largest first)")
    c.add_argument("--min-size", type=int, default=2, help="smallest cluster size drawn")
    c.add_argument("--radius", type=int, default=32, help="patch half-size in pixels")
    c.add_argument("--image-dir", default=None, help=IMAGE_DIR_HELP)
    s = sub.add_parser("sizes", formatter_class=HelpFormatter, help="histogram of cluster sizes")
    s.add_argument("clusters", metavar="CLUSTERS.npz")
    s.add_argument("--out", required=True, help="figure file (.png, .pdf, .svg, ...)")
    outputs.add_overwrite_option(s)
    r = sub.add_parser("pr", formatter_class=HelpFormatter, help="PR curves from a dqm evaluate JSON")
    r.add_argument("evaluation", metavar="EVALUATION.json")
    r.add_argument("--out-dir", required=True, help="folder for one pr_<data set>.png per data set (the name made "
                                                         "safe for file names: scene:3 -> pr_scene-3.png)")
    outputs.add_overwrite_option(r)


#: --image-dir of the plots that draw images
IMAGE_DIR_HELP = ("where the images are now: a name the file holds is looked up as it is, then under this folder "
                  "(relative names), then by its file name alone (absolute names of images that moved)")


def _images(cl: dict, image_dir, needed) -> list:
    """Paths of the images (row k: image id k); only the ``needed`` image ids must exist (a CLUSTERS
    file may name images it holds no feature of, e.g. a distributed job's)."""
    if "image_names" not in cl:
        raise InputError("this clusters file records no image names (made from a FEATURES file without them); "
                         "pair and clusters plots need the images")
    from ..io import find_image

    names = [str(n) for n in cl["image_names"].tolist()]
    out = [find_image(name, image_dir) or Path(name) for name in names]
    for k in sorted(set(int(k) for k in needed)):
        if not 0 <= k < len(out) or not names[k]:
            raise InputError(f"this clusters file names no image for image id {k}")
        if not out[k].is_file():
            where = (f"nor under --image-dir {image_dir} (by that name or by its file name)" if image_dir is not None
                     else "(use --image-dir to say where the images are)")
            raise InputError(f"image {names[k]} not found {where}")
    return out


def _keypoints(cl: dict) -> np.ndarray:
    if "keypoints" not in cl:
        raise InputError("this clusters file has no keypoints; pair and clusters plots need them")
    return np.asarray(cl["keypoints"], float)


def _pair(args) -> int:
    cl = io.load_clusters(args.clusters)
    ids = np.asarray(cl["image_ids"])
    i, j = args.images
    top = max(len(cl.get("image_names", ())), int(ids.max()) + 1 if len(ids) else 0)
    for k in (i, j):
        if not 0 <= k < top:
            raise InputError(f"image id {k} out of range 0..{top - 1}")
    if i == j:
        raise InputError("--images needs two different image ids")
    images = _images(cl, args.image_dir, (i, j))
    kp = _keypoints(cl)
    a, b = cluster_pairs(cl["labels"], ids)
    sel = ((ids[a] == i) & (ids[b] == j)) | ((ids[a] == j) & (ids[b] == i))
    pa = np.where(ids[a[sel]] == i, a[sel], b[sel])
    pb = np.where(ids[a[sel]] == i, b[sel], a[sel])
    correct = None
    if args.truth:
        from ..vision.datasets import load_homography_sequence

        seq = load_homography_sequence(args.truth)
        if len(seq.image_paths) != len(images):
            raise InputError(f"--truth has {len(seq.image_paths)} images, the clusters {len(images)}")
        from ..vision.features import read_gray

        for k in (i, j):  # the homographies are only meaningful for images of the same size
            truth_shape, shape = read_gray(seq.image_paths[k]).shape, read_gray(images[k]).shape
            if truth_shape != shape:
                raise InputError(f"--truth {args.truth} does not fit these images: its image {k} "
                                 f"({Path(seq.image_paths[k]).name}) is {truth_shape[1]}x{truth_shape[0]}, "
                                 f"the clusters' ({Path(images[k]).name}) {shape[1]}x{shape[0]}")
        correct = reprojection_error(seq.homography(i, j), kp[pa, :2], kp[pb, :2]) <= args.tol
    fig = plots.pair_figure(images[i], images[j], kp[pa, :2], kp[pb, :2], correct, max_lines=args.max_lines,
                            title=f"{Path(images[i]).name} - {Path(images[j]).name}")
    print(f"wrote {plots.save(fig, args.out)} ({len(pa)} matches)")
    return 0


def _clusters(args) -> int:
    cl = io.load_clusters(args.clusters)
    if args.count < 1 or args.min_size < 2 or args.radius < 4:
        raise InputError("--count must be >= 1, --min-size >= 2 and --radius >= 4")
    labels = np.asarray(cl["labels"])
    sizes = np.bincount(labels)
    big = [k for k in np.argsort(-sizes, kind="stable") if sizes[k] >= args.min_size][:args.count]
    if not big:
        raise InputError(f"no cluster has {args.min_size} or more features")
    members = [np.flatnonzero(labels == k) for k in big]
    used = np.unique(np.asarray(cl["image_ids"])[np.concatenate(members)])
    fig = plots.clusters_figure(_images(cl, args.image_dir, used), _keypoints(cl), cl["image_ids"], members,
                                radius=args.radius, point_ids=cl.get("point_ids"),
                                title=f"{len(members)} largest clusters")
    print(f"wrote {plots.save(fig, args.out)}")
    return 0


def _sizes(args) -> int:
    cl = io.load_clusters(args.clusters)
    fig = plots.cluster_sizes_figure(cl["labels"], cl["image_ids"])
    print(f"wrote {plots.save(fig, args.out)}")
    return 0


def _pr(args) -> int:
    p = Path(args.evaluation)
    if not p.exists():
        raise InputError(f"evaluation file not found: {p}")
    try:
        data = json.loads(p.read_text())
        sets = data["datasets"]
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{p}: not a dqm evaluate JSON ({exc})") from None
    from ..benchmark import METHODS, file_stem

    stems: list = []  # data-set names as file names: one rule everywhere (benchmark.file_stem), unique here
    for name, d in sets.items():
        stems.append(file_stem(name, stems))
        rows = d["methods"]
        curves = [PRCurve.from_dict(r["curve"]) for r in rows]
        points = {r["method"]: (r["scores"]["recall"], r["scores"]["precision"]) for r in rows}
        fig = plots.pr_figure(curves, points, labels=METHODS,
                              title=f"{name}: {d['n_features']} features, {d['n_images']} images")
        print(f"wrote {plots.save(fig, Path(args.out_dir) / f'pr_{stems[-1]}.png')}")
    return 0


def run(args) -> int:
    LOG.info("plot %s: reading %s", args.what, getattr(args, "evaluation", None) or args.clusters)
    if args.what == "pr":
        outputs.check_dir(args.out_dir, "--out-dir", ("pr_*",), overwrite=args.overwrite)
    else:
        outputs.check_file(args.out, "--out", outputs.IMAGE_SUFFIXES, overwrite=args.overwrite)
    return {"pair": _pair, "clusters": _clusters, "sizes": _sizes, "pr": _pr}[args.what](args)
