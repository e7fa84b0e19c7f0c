"""COLMAP databases in and out: QuickMatch clusters become tracks that COLMAP reconstructs.

Export (:func:`export_database`) writes what COLMAP's own feature extraction and matching would:

* cameras as COLMAP's image reader makes them (:class:`CameraOptions`): one per image by
  default, or one for all images (``single``, COLMAP's ``ImageReader.single_camera``) or per
  folder (``per-folder``, ``single_camera_per_folder``), whose images must then have one size;
  model ``SIMPLE_RADIAL`` unless told (any COLMAP model name); the focal length comes from the
  (first) image's EXIF when COLMAP can read it there (then marked as a prior), otherwise
  COLMAP's own default, ``1.2 * max(width, height)``; the principal point is the image centre;
  given parameters (``ImageReader.camera_params``) replace all that and are marked as a prior;
* a trivial rig per camera and a frame per image (COLMAP 3.12+ databases hold them);
* keypoints in COLMAP's convention (the centre of the top-left pixel is (0.5, 0.5); dqm and
  OpenCV put it at (0, 0), so 0.5 is added);
* SIFT descriptors when the features are 128-D uint8 (COLMAP's descriptor type); other
  descriptors are left out (the mapper does not read them);
* the matches implied by the clusters for every image pair: every two members of a cluster (when
  verifying, only the pairs with at least as many matches as COLMAP's verification can accept:
  :func:`verifiable`);
* verified two-view geometries, computed by COLMAP's two-view estimator over the exported matches
  (:func:`_verify`: its RANSAC seeded so that the same clusters give the same database, each pair's
  trials bounded by what a pass needs), less those too weak for both images (:func:`drop_weak_pairs`), so
  ``pycolmap.incremental_mapping(DB, IMAGE_DIR, OUT)`` runs with no further step.

Import (:func:`import_database`) reads keypoints, descriptors and image names back into a
FEATURES set, so ``dqm match`` / ``dqm run`` cluster features that COLMAP extracted.

pycolmap is an optional dependency (``pip install 'dqm[colmap]'``).
"""
from __future__ import annotations

import contextlib
import logging
import os
import posixpath
import re
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import signals
from ..io import FeatureSet
from ..outputs import atomic_output
from ..progress import ProgressArg, resolve_progress
from ..validation import InputError
from ..wording import count

LOG = logging.getLogger("dqm.vision")

#: COLMAP's default focal length without EXIF, relative to the larger image side
DEFAULT_FOCAL_FACTOR = 1.2
#: COLMAP's default camera model (``ImageReader.camera_model``)
DEFAULT_CAMERA_MODEL = "SIMPLE_RADIAL"
#: how images share cameras: one each, one for all (``single_camera``), one per folder
CAMERA_MODES = ("per-image", "single", "per-folder")


def require_pycolmap(quiet: bool = True, what: str = "this command"):
    """The pycolmap module, or one line saying how to install it (``what`` names what needs it).

    Loading it installs glog's failure handler for SIGTERM (a stack dump, death by the signal, no cleanup):
    Python's handlers are given the signal back (:func:`dqm.signals.reassert`). COLMAP's log goes to
    stderr, never to glog's files in the temporary folder; ``quiet``: only with ``-v`` (its warnings; its
    errors are reported by the calls that fail).
    """
    import sys

    fresh = "pycolmap" not in sys.modules
    try:
        with signals.held():
            import pycolmap

            if fresh:
                signals.reassert()
    except ImportError:
        raise InputError(f"{what} needs pycolmap: pip install 'dqm[colmap]'") from None
    if hasattr(pycolmap, "logging"):
        log = pycolmap.logging
        log.logtostderr = True
        verbose = not quiet or logging.getLogger("dqm").isEnabledFor(logging.INFO)
        log.minloglevel = int(log.WARNING if verbose else log.FATAL)
        for level in (log.INFO, log.WARNING, log.ERROR, log.FATAL) if hasattr(log, "set_log_destination") else ():
            log.set_log_destination(level, "")  # glog's "no file": a call that turns logtostderr off writes none
    return pycolmap


#: the glog flags that :func:`require_pycolmap` sets and :func:`colmap_log_kept` keeps
_LOG_FLAGS = ("logtostderr", "alsologtostderr", "minloglevel")


@contextlib.contextmanager
def colmap_log_kept(pycolmap, at_least: int | None = None):
    """COLMAP's log settings (glog's flags, as :func:`require_pycolmap` set them) the same after the block as before
    it; ``at_least``: the level raised to that within the block (COLMAP warns that its extraction uses every core; it
    is asked to). ``pycolmap.bundle_adjustment`` (pycolmap 4.2: COLMAP's OptionManager) sets them to its defaults,
    INFO and log files, and leaves them so: every COLMAP call after it would log, quiet or not (its own two
    INFO lines, a heading and its time, are written while it runs: :func:`glog_info_dropped` keeps them off stderr)."""
    log = getattr(pycolmap, "logging", None)
    kept = {name: getattr(log, name) for name in _LOG_FLAGS if hasattr(log, name)}  # those this pycolmap has
    if at_least is not None and "minloglevel" in kept:
        log.minloglevel = max(kept["minloglevel"], int(at_least))
    try:
        yield
    finally:
        for name, value in kept.items():
            setattr(log, name, value)


#: a glog INFO line as COLMAP writes it to stderr (after any colour reset): ``I<yyyymmdd> <time> <thread> <file>] ``
_GLOG_INFO = re.compile(rb"^(?:\x1b\[[0-9;]*m)*I\d{8} \d\d:\d\d:\d\d\.\d+ +\d+ [^\]\n]*\] ")
#: what may still become such a line: held back until its line ends, everything else passes at once
_GLOG_INFO_START = re.compile(rb"^(?:\x1b(?:\[[0-9;]*m?)?)*(?:I[0-9 :.]*)?$")


@contextlib.contextmanager
def glog_info_dropped():
    """stderr (file descriptor 2) through a pipe for the block: COLMAP's glog INFO lines are dropped, everything
    else (its warnings and errors, progress bars, Python's own output) passes as it comes. ``pycolmap.
    bundle_adjustment`` (pycolmap 4.2) logs a heading and its time at INFO whatever glog's flags
    (:func:`colmap_log_kept`). Where stderr cannot be duplicated, the block runs as it is."""
    import sys
    import threading

    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):
        yield
        return
    read, write = os.pipe()
    os.dup2(write, 2)
    os.close(write)

    def forward() -> None:
        held, out = b"", saved
        while True:
            chunk = os.read(read, 65536)
            if not chunk:
                break
            *lines, held = (held + chunk).split(b"\n")
            text = b"".join(line + b"\n" for line in lines if not _GLOG_INFO.match(line))
            if held and not _GLOG_INFO_START.match(held):
                text, held = text + held, b""
            while text and out is not None:
                try:
                    text = text[os.write(out, text):]
                except OSError:  # stderr went away: drain the pipe, write nothing
                    out = None
        if held and out is not None and not _GLOG_INFO.match(held):
            with contextlib.suppress(OSError):
                os.write(out, held)
        os.close(read)

    thread = threading.Thread(target=forward, name="dqm-glog-filter", daemon=True)
    thread.start()
    try:
        yield
    finally:
        with contextlib.suppress(OSError, ValueError):
            sys.stderr.flush()
        os.dup2(saved, 2)  # the pipe's last write end closes: the forwarder reads its end
        thread.join(timeout=10)
        os.close(saved)


#: which members of a cluster are handed to COLMAP as matches (:func:`cluster_pairs`): ``all`` every two;
#: ``auto`` every two, but in a track through a run of frames (:func:`sequence_clusters`) log-spaced ones;
#: ``log`` each member with those 1, 2, 4, ... places after it in image order
CLUSTER_MATCHES = ("all", "auto", "log")
#: the export's choice (dqm export colmap, dqm sfm, :func:`export_database`, :func:`write_matches`): a video's
#: tracks cut, every other cluster as ``all`` (docs/sfm.md: cmu_hotel 0.97x COLMAP's points in 0.60x its time,
#: every pair 1.01x in 0.91x; the photo sets with cameras and the 270-photo collection as with every pair)
DEFAULT_CLUSTER_MATCHES = "auto"

#: ``cluster_matches="auto"``: a cluster of more than this many members whose members are in at least
#: :data:`SEQUENCE_FILL` of the images from its first to its last (image order) gets log-spaced matches. Every
#: two members of a cluster of up to 16 are at most 7.5 matches an observation. Measured (docs/sfm.md): a video's
#: tracks run through tens of frames (cmu_hotel 1,072 of 4,165 clusters: 17.5 matches an observation become 5.6);
#: in nerf_lego's renders, in no order, a cluster's members are scattered (none; log-spaced matches in that order
#: cost its cameras: AUC@1 0.730 -> 0.662 over 3 seeds with every cluster of more than 16 log-spaced), in
#: dtu/scan24's, in path order, 11 of 66,275 qualify; entry-P10's and sacre_coeur's clusters are all smaller
SEQUENCE_FROM = 16

#: the share of the images from a cluster's first to its last that must hold a member (:data:`SEQUENCE_FROM`)
SEQUENCE_FILL = 2 / 3


def sequence_clusters(labels, image_ids) -> np.ndarray:
    """Per row, whether its cluster is a track through a run of frames: more than :data:`SEQUENCE_FROM` members,
    in at least :data:`SEQUENCE_FILL` of the images from its first member's to its last's (image ids in image
    order; at most one member an image, constraint C2). There each member's neighbours in image order are its
    strongest matches, and :func:`log_spaced_pairs` keeps them."""
    lab = np.asarray(labels, np.int64)
    ids = np.asarray(image_ids, np.int64)
    if not len(lab):
        return np.zeros(0, bool)
    _, inverse, counts = np.unique(lab, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    first = np.full(len(counts), ids.max(), np.int64)
    last = np.full(len(counts), ids.min(), np.int64)
    np.minimum.at(first, inverse, ids)
    np.maximum.at(last, inverse, ids)
    run = (counts > SEQUENCE_FROM) & (counts >= SEQUENCE_FILL * (last - first + 1))
    return run[inverse]


def log_spaced_pairs(labels, image_ids) -> tuple[np.ndarray, np.ndarray]:
    """Each member ``i`` of every cluster with the members 1, 2, 4, 8, ... places after it, the members in image
    order: pairs ``(f, g)`` of row indices. A cluster of s members gives sum over d = 1, 2, 4, ... < s of (s - d)
    pairs, at most s log2 s (every two: s (s - 1) / 2), and any two members are joined by a path of at most
    log2 s of them, so the cluster stays one track in COLMAP's correspondence graph; the pairs of 2 or 3 members
    are every pair."""
    lab = np.asarray(labels, np.int64)
    order = np.lexsort((np.asarray(image_ids, np.int64), lab))
    sorted_labels = lab[order]
    first, second = [], []
    d = 1
    while d < len(order):
        same = sorted_labels[:-d] == sorted_labels[d:]
        if not same.any():
            break
        first.append(order[:-d][same])
        second.append(order[d:][same])
        d *= 2
    if not first:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(first), np.concatenate(second)


def spaced_clusters(labels, image_ids, matches: str) -> int:
    """How many clusters :func:`cluster_pairs` hands over as log-spaced members under ``matches`` (``log``: every
    cluster of 4 or more; below, log-spaced members are every two)."""
    lab = np.asarray(labels, np.int64)
    if matches == "auto":
        lab = lab[sequence_clusters(lab, image_ids)]
    elif matches != "log":
        return 0
    return int((np.unique(lab, return_counts=True)[1] >= 4).sum())


def cluster_pairs(labels, image_ids, matches: str = "all") -> dict[tuple[int, int], np.ndarray]:
    """Every two members of every cluster (``matches="all"``; ``"log"``: :func:`log_spaced_pairs`; ``"auto"``:
    log-spaced in the clusters :func:`sequence_clusters` marks, every two in the others), grouped by image pair.

    Returns ``{(a, b): (m, 2) int64 array of feature indices}`` with image ``a < b`` and column 0
    in image ``a``. Within a cluster the images differ (constraint C2), so no pair is dropped.
    """
    from ..core.tree import member_pairs

    if matches not in CLUSTER_MATCHES:
        raise InputError(f"cluster matches {matches!r}: use one of {', '.join(CLUSTER_MATCHES)}")
    ids = np.asarray(image_ids, np.int64)
    labels = np.asarray(labels, np.int64)
    if matches == "auto":
        spaced = sequence_clusters(labels, ids)
        every, spaced = np.flatnonzero(~spaced), np.flatnonzero(spaced)
        f1, g1 = member_pairs(labels[every])
        f2, g2 = log_spaced_pairs(labels[spaced], ids[spaced])
        f, g = np.concatenate([every[f1], spaced[f2]]), np.concatenate([every[g1], spaced[g2]])
    else:
        f, g = member_pairs(labels) if matches == "all" else log_spaced_pairs(labels, ids)
    if not len(f):
        return {}
    swap = ids[f] > ids[g]
    f, g = np.where(swap, g, f), np.where(swap, f, g)
    key = ids[f] * (int(ids.max()) + 1) + ids[g]
    o = np.lexsort((g, f, key))
    f, g, key = f[o], g[o], key[o]
    cuts = np.flatnonzero(np.diff(key)) + 1
    out = {}
    for fs, gs in zip(np.split(f, cuts), np.split(g, cuts)):
        out[(int(ids[fs[0]]), int(ids[gs[0]]))] = np.stack([fs, gs], axis=1)
    return out


def verifiable(pairs: dict, min_matches: int) -> tuple[dict, int]:
    """The image pairs of :func:`cluster_pairs` with at least ``min_matches`` matches, and how many were left out.
    COLMAP's two-view verification verifies no pair with fewer matches than its ``min_num_inliers`` (15 by
    default): writing them only costs time in the export, the verification and the mapper's database
    reading. On a collection of several scenes the clusters join nearly every image pair with a few
    matches (169 images of 4 scenes: 14,151 of 14,196 pairs)."""
    kept = {pair: m for pair, m in pairs.items() if len(m) >= min_matches}
    return kept, len(pairs) - len(kept)


#: ``dqm sfm --partners``' default: how many of each image's image pairs are verified and mapped, its strongest by
#: shared clusters; COLMAP's vocabulary-tree matcher matches each image with its 100 most similar (``num_images``)
SFM_PARTNERS = 100


def strongest_partners(pairs: dict, partners: int) -> tuple[dict, int]:
    """The image pairs of :func:`cluster_pairs` that are among the ``partners`` with the most matches of one of
    their two images (ties: the lower image), and how many were left out; all of them where ``partners`` is 0 or
    no image has more. At most ``partners`` pairs an image are chosen (``partners`` times the images in all, twice
    that many partners an image on average), so the pairs verified and handed to the mapper grow with the
    images, not with their pairs, and so do the matches of a point seen in hundreds of images. What is left out
    are each image's weakest pairs: on nerf_lego (100 renders, 3,815 pairs with 15 matches or more) 50 keep 2,902
    pairs and 1,597 of the 1,599 COLMAP verifies, 30 keep 1,805 and 1,422; nothing is left out of a collection of
    ``partners + 1`` images or fewer."""
    if partners <= 0:
        return pairs, 0
    ranked: dict[int, list[tuple[int, int]]] = {}
    for (a, b), m in pairs.items():
        ranked.setdefault(a, []).append((-len(m), b))
        ranked.setdefault(b, []).append((-len(m), a))
    strongest = {i: {j for _, j in sorted(v)[:partners]} for i, v in ranked.items()}
    kept = {(a, b): m for (a, b), m in pairs.items() if b in strongest[a] or a in strongest[b]}
    return kept, len(pairs) - len(kept)


def min_verified_matches() -> int:
    """The fewest matches COLMAP's two-view verification accepts in an image pair (its ``min_num_inliers``)."""
    return int(require_pycolmap().TwoViewGeometryOptions().min_num_inliers)


#: a verified pair is dropped when its inliers are fewer than this share of both images' strong pairs' (each
#: image's STRONG_PAIR_RANK-th most inliers): :func:`drop_weak_pairs`
WEAK_PAIR_SHARE = 0.05
STRONG_PAIR_RANK = 3


def verified_pairs(db) -> list[tuple[int, int, int]]:
    """The verified image pairs of an open pycolmap Database: (image id, image id, inliers) for each pair with at
    least :func:`min_verified_matches` inliers (COLMAP's verification writes a geometry for every pair it tried)."""
    pycolmap = require_pycolmap()
    pair_ids, inliers = db.read_two_view_geometry_num_inliers()
    least = min_verified_matches()
    return [(*map(int, pycolmap.pair_id_to_image_pair(p)), int(k)) for p, k in zip(pair_ids, inliers) if k >= least]


def drop_weak_pairs(database, share: float = WEAK_PAIR_SHARE, rank: int = STRONG_PAIR_RANK) -> int:
    """Take back COLMAP's verification of the image pairs whose inliers are fewer than ``share`` of what both
    images share with their strong partners (each image's ``rank``-th most inliers among its verified pairs; its
    fewest where it has fewer), in the database file ``database``: their two-view geometries are deleted, their
    matches kept. Returns how many.

    QuickMatch's clusters join features of unrelated images too (generic texture, repeated glyphs); on a pair of
    images of two scenes a few dozen such matches can hold 15-20 inliers of a fundamental matrix by chance, which
    COLMAP's verification accepts. Its global mapper then joins the scenes into one model (two generated scenes:
    one model with both, 5 points seen from both; with these pairs dropped, a model each), and its incremental
    mapper spends its registration trials on them. Such a pair has about 2% of the inliers either image shares
    with its strong partners; on nerf_lego's 100 renders the rule drops 3-4 of 1,650 verified pairs."""
    pycolmap = require_pycolmap()
    db = pycolmap.Database.open(str(database))
    try:
        verified = verified_pairs(db)
        partners: dict[int, list[int]] = {}
        for a, b, k in verified:
            partners.setdefault(a, []).append(k)
            partners.setdefault(b, []).append(k)
        strong = {i: sorted(v, reverse=True)[min(rank, len(v)) - 1] for i, v in partners.items()}
        weak = [(a, b) for a, b, k in verified if k < share * min(strong[a], strong[b])]
        for a, b in weak:
            db.delete_two_view_geometry(a, b)
    finally:
        db.close()
    return len(weak)


def local_indices(image_ids) -> np.ndarray:
    """Every feature's index among its own image's features, in row order (COLMAP's and hloc's keypoint index)."""
    ids = np.asarray(image_ids, np.int64)
    order = np.argsort(ids, kind="stable")
    local = np.empty(len(ids), np.int64)
    local[order] = np.arange(len(ids)) - np.searchsorted(ids[order], ids[order])
    return local


@dataclass
class ExportSummary:
    """What :func:`export_database` or :func:`write_matches` wrote."""

    database: Path
    image_dir: Path | None
    n_images: int
    n_keypoints: int
    n_image_pairs: int
    n_matches: int
    n_verified_pairs: int = 0
    names: list[str] = field(default_factory=list)
    n_cameras: int = 0
    #: image pairs with matches too few for COLMAP's verification, not written (:func:`verifiable`)
    n_pairs_left_out: int = 0
    #: the fewest matches a written pair has (COLMAP's ``min_num_inliers`` when verifying, else 1)
    min_matches: int = 1
    #: verified pairs whose verification was taken back as too weak for both images (:func:`drop_weak_pairs`)
    n_pairs_dropped: int = 0
    #: image pairs not among either image's ``partners`` strongest, not written (:func:`strongest_partners`)
    n_pairs_beyond: int = 0
    partners: int = 0
    #: clusters whose matches were log-spaced (``cluster_matches``: ``auto``'s tracks through a run of frames,
    #: :func:`sequence_clusters`, or every cluster of 4+ members with ``log``)
    n_spaced_clusters: int = 0

    def pairs_line(self) -> str:
        """``N matches in M image pairs`` and, where some were left out, how many and why."""
        line = f"{count(self.n_matches, 'match', 'matches')} in {count(self.n_image_pairs, 'image pair')}"
        why = []
        if self.n_pairs_left_out:
            why.append(f"{count(self.n_pairs_left_out, 'pair')} with fewer than {self.min_matches} matches left out: "
                       "COLMAP's verification takes none")
        if self.n_pairs_beyond:
            why.append(f"{count(self.n_pairs_beyond, 'pair')} outside both images' {self.partners} strongest left "
                       "out")
        if self.n_spaced_clusters:
            why.append(f"log-spaced members of {count(self.n_spaced_clusters, 'cluster')}")
        return line + (f" ({'; '.join(why)})" if why else "")

    def verified_line(self) -> str:
        """``N verified pairs`` and, where some were dropped as too weak for both images, how many."""
        line = f"{count(self.n_verified_pairs, 'verified pair')}"
        if self.n_pairs_dropped:
            line += (f" ({count(self.n_pairs_dropped, 'pair')} with under {WEAK_PAIR_SHARE:.0%} of both images' "
                     "strong pairs' inliers dropped)")
        return line


@dataclass(frozen=True)
class CameraOptions:
    """The cameras of an export, checked by :func:`camera_options`.

    ``model``: a COLMAP camera model name; ``mode``: one of :data:`CAMERA_MODES`;
    ``params``: the model's parameters in COLMAP's order for every camera, or None
    (focal length from EXIF or the default, principal point at the image centre, no distortion).
    """

    model: str = DEFAULT_CAMERA_MODEL
    mode: str = "per-image"
    params: tuple[float, ...] | None = None


def camera_model_names() -> list[str]:
    """The camera model names this pycolmap knows (``SIMPLE_PINHOLE``, ``PINHOLE``, ``SIMPLE_RADIAL``, ...)."""
    pycolmap = require_pycolmap()
    return [name for name in pycolmap.CameraModelId.__members__ if name != "INVALID"]


def camera_options(model: str = DEFAULT_CAMERA_MODEL, mode: str = "per-image",
                   params: None | str | Sequence[float] = None) -> CameraOptions:
    """Check camera settings before any work: one InputError line naming a bad model, mode or parameter list.

    ``model`` is a COLMAP model name (any case); ``params``: a comma-separated string
    (COLMAP's ``ImageReader.camera_params``, e.g. ``"1200,640,480,0.01"``) or numbers, exactly
    as many as the model has, finite, focal lengths positive.
    """
    pycolmap = require_pycolmap()
    known = camera_model_names()
    name = str(model).strip().upper()
    if name not in known:
        raise InputError(f"--camera-model {model}: not a COLMAP camera model; use one of {', '.join(known)}")
    if mode not in CAMERA_MODES:
        raise InputError(f"camera mode {mode!r}: use one of {', '.join(CAMERA_MODES)}")
    if params is None:
        return CameraOptions(name, mode, None)
    text = params if isinstance(params, str) else ",".join(str(v) for v in params)
    template = pycolmap.Camera.create_from_model_name(0, name, 1.0, 1, 1)
    want = len(template.params)
    info = template.params_info
    try:
        values = tuple(float(v) for v in text.replace(" ", "").split(","))
    except ValueError:
        raise InputError(f"--camera-params {text!r}: give {want} comma-separated numbers for {name} ({info})") \
            from None
    if len(values) != want:
        raise InputError(f"--camera-params {text!r}: {name} has {want} parameters ({info}), got {len(values)}")
    if not all(np.isfinite(values)):
        raise InputError(f"--camera-params {text!r}: the parameters must be finite numbers")
    names = [n.strip() for n in info.split(",")]
    for k in template.focal_length_idxs():
        if values[k] <= 0:
            raise InputError(f"--camera-params {text!r}: the focal length {names[k]} must be positive, "
                             f"got {values[k]:g}")
    return CameraOptions(name, mode, values)


def image_folder(paths: Sequence, image_dir: Path | None = None) -> tuple[Path, list[str]]:
    """The image folder and each image's name relative to it, '/'-separated (COLMAP and hloc name images so).

    ``image_dir`` None: the images' common folder. Raises InputError for an image outside it.
    """
    paths = [Path(p) for p in paths]
    if image_dir is None:
        try:
            image_dir = Path(os.path.commonpath([os.path.abspath(p.parent) for p in paths]))
        except ValueError:
            raise InputError("the images have no common folder (other drives?); pass --image-dir") from None
    names = []
    for p in paths:
        try:
            # absolute, not resolved: a folder of links to the images is a valid COLMAP image folder
            names.append(Path(os.path.abspath(p)).relative_to(os.path.abspath(image_dir)).as_posix())
        except ValueError:
            raise InputError(f"image {p} is not inside the image folder {image_dir}") from None
    return Path(image_dir), names


def resolve_images(image_names, image_dir=None) -> list[Path]:
    """Paths of the images, found as named or under ``image_dir``; one line if one is missing."""
    from ..io import find_image

    out = []
    for name in [str(n) for n in image_names]:
        found = find_image(name, image_dir)
        if found is None:
            where = f" or under {image_dir}" if image_dir is not None else " (pass --image-dir)"
            raise InputError(f"image {name} not found{where}; the export needs every image's size")
        out.append(found)
    return out


def _image_facts(paths: Sequence[Path]) -> list[tuple[int, int, float]]:
    """(width, height, EXIF focal length in pixels or 0) of every image, as COLMAP reads them."""
    pycolmap = require_pycolmap()
    out = []
    for path in paths:
        bitmap = pycolmap.Bitmap.read(str(path), False)
        if bitmap is None:
            raise InputError(f"image {path} cannot be read")
        exif = bitmap.exif_focal_length()
        out.append((int(bitmap.width), int(bitmap.height), float(exif) if exif else 0.0))
    return out


def check_camera_sharing(image_paths: Sequence, camera: CameraOptions, image_dir=None) -> None:
    """InputError, before any work, where ``camera`` shares a camera among images of different sizes (as
    :func:`export_database` would refuse them, after the extraction and matching); names relative to
    ``image_dir`` (default the images' common folder), as the export names them. Reads every image (its size)
    unless every image has a camera of its own."""
    if camera.mode == "per-image":
        return
    paths = [Path(p) for p in image_paths]
    _, names = image_folder(paths, None if image_dir is None else Path(image_dir))
    _camera_groups(names, _image_facts(paths), camera.mode)


def shared_camera_unfit(image_paths: Sequence, image_dir=None) -> str | None:
    """Why one camera per folder does not fit these images, or None where it does: each folder's images have
    one size and none has an EXIF focal length (a prior of its own; photos of several cameras often have one).
    Names relative to ``image_dir`` (default the images' common folder), as the export names them."""
    paths = [Path(p) for p in image_paths]
    _, names = image_folder(paths, None if image_dir is None else Path(image_dir))
    facts = _image_facts(paths)
    with_exif = [name for name, fact in zip(names, facts) if fact[2]]
    if with_exif:
        return f"{count(len(with_exif), 'image')} ({with_exif[0]}, ...) with an EXIF focal length"
    try:
        _camera_groups(names, facts, "per-folder")
    except InputError as e:
        return str(e)
    return None


def _camera_groups(names: Sequence[str], facts: Sequence[tuple[int, int, float]], mode: str) -> list[int]:
    """The camera of every image, named by its first image: one each, one for all, or one per folder of its name.

    A shared camera needs one image size: InputError naming two images that differ.
    """
    keys = {"per-image": list(range(len(names))), "single": [0] * len(names),
            "per-folder": [posixpath.dirname(n) for n in names]}[mode]
    first: dict[object, int] = {}
    groups = []
    for k, key in enumerate(keys):
        j = first.setdefault(key, k)
        if facts[j][:2] != facts[k][:2]:
            where = "all images" if mode == "single" else f"the images of folder '{key or '.'}'"
            raise InputError(f"one camera for {where} needs one image size: {names[j]} is {facts[j][0]}x{facts[j][1]}, "
                             f"{names[k]} is {facts[k][0]}x{facts[k][1]}")
        groups.append(j)
    return groups


def export_database(database, keypoints, image_ids, image_paths: Sequence, labels, *,
                    image_dir=None, descriptors=None, verify: bool = True,
                    num_threads: int = -1, camera: CameraOptions | None = None, seed: int = 0,
                    partners: int = 0, cluster_matches: str = DEFAULT_CLUSTER_MATCHES,
                    progress: ProgressArg = None) -> ExportSummary:
    """Write a COLMAP database from clusters (see the module docstring); refuses an existing file.

    ``keypoints``: (n, >=2) OpenCV pixel coordinates; ``image_ids``: 0..m-1 indexing
    ``image_paths`` (existing image files); ``labels``: the clusters; ``camera``: the camera
    model, sharing and parameters (:func:`camera_options`; default one ``SIMPLE_RADIAL`` per image);
    ``partners``: only each image's strongest pairs are written (:func:`strongest_partners`; 0: every pair);
    ``cluster_matches``: which members of a cluster are matches (:data:`CLUSTER_MATCHES`, :func:`cluster_pairs`);
    ``progress(done, total)`` (:data:`dqm.progress.ProgressArg`): image pairs done, twice (their matches
    written, then verified; ``done`` restarts at 0).
    Every image is read (its size) before the database is created.
    """
    pycolmap = require_pycolmap()
    camera = camera or CameraOptions()
    database = Path(database)
    if database.exists():
        raise InputError(f"{database} exists; the export writes a new database (remove it or pick another name)")
    kp = np.asarray(keypoints, np.float64)
    ids = np.asarray(image_ids, np.int64)
    labels = np.asarray(labels, np.int64)
    n = len(ids)
    if kp.ndim != 2 or kp.shape[0] != n or kp.shape[1] < 2 or labels.shape != (n,):
        raise InputError(f"keypoints (n, 2..) and labels (n,) must match the {n} image ids")
    paths = [Path(p) for p in image_paths]
    if n and (ids.min() < 0 or ids.max() >= len(paths)):
        raise InputError(f"image ids must index the {len(paths)} images (0..{len(paths) - 1})")
    folder, names = image_folder(paths, None if image_dir is None else Path(image_dir))
    facts = _image_facts(paths)
    groups = _camera_groups(names, facts, camera.mode)
    desc = None if descriptors is None else np.asarray(descriptors)
    if desc is not None and (desc.dtype != np.uint8 or desc.shape[1:] != (128,)):
        desc = None  # COLMAP's descriptor type is 128-D uint8; the mapper does not need others
    pairs = cluster_pairs(labels, ids, cluster_matches)
    least = min_verified_matches() if verify else 1
    pairs, left_out = verifiable(pairs, least)
    pairs, beyond = strongest_partners(pairs, partners)
    rows_of = [np.flatnonzero(ids == k) for k in range(len(paths))]
    local = local_indices(ids)
    bar = resolve_progress(progress, "export (write, then verify)", unit="pairs")
    with atomic_output(database) as tmp:  # a stop or an error leaves no half-written database
        colmap_id = {}
        cameras: dict[int, tuple[object, int]] = {}  # camera group -> (pycolmap camera, rig id)
        db = pycolmap.Database.open(tmp)
        try:
            for k, name in enumerate(names):
                if groups[k] not in cameras:
                    w, h, exif = facts[k]
                    focal = exif if exif else DEFAULT_FOCAL_FACTOR * max(w, h)
                    cam = pycolmap.Camera.create_from_model_name(0, camera.model, focal, w, h)
                    cam.has_prior_focal_length = bool(exif)
                    if camera.params is not None:
                        cam.params = np.asarray(camera.params, np.float64)
                        cam.has_prior_focal_length = True  # as COLMAP's ImageReader.camera_params
                    cam.camera_id = db.write_camera(cam)
                    rig = pycolmap.Rig()
                    rig.add_ref_sensor(cam.sensor_id)
                    cameras[groups[k]] = (cam, db.write_rig(rig))
                cam, rig_id = cameras[groups[k]]
                image_id = db.write_image(pycolmap.Image(name=name, camera_id=cam.camera_id))
                frame = pycolmap.Frame()
                frame.rig_id = rig_id
                frame.add_data_id(pycolmap.data_t(sensor_id=cam.sensor_id, id=image_id))
                db.write_frame(frame)
                colmap_id[k] = image_id
                rows = rows_of[k]
                db.write_keypoints(image_id, (kp[rows, :2] + 0.5).astype(np.float32))
                if desc is not None:
                    db.write_descriptors(image_id, pycolmap.FeatureDescriptors(
                        pycolmap.FeatureExtractorType.SIFT, np.ascontiguousarray(desc[rows])))
            n_matches = _write_cluster_matches(db, pairs, colmap_id, local, bar)
        finally:
            db.close()
        summary = ExportSummary(database, folder, len(paths), n, len(pairs), n_matches, names=names,
                                n_cameras=len(cameras), n_pairs_left_out=left_out, min_matches=least,
                                n_pairs_beyond=beyond, partners=partners,
                                n_spaced_clusters=spaced_clusters(labels, ids, cluster_matches))
        if verify and pairs:
            summary.n_verified_pairs = _verify(tmp, num_threads, seed, bar)
            summary.n_pairs_dropped = drop_weak_pairs(tmp)
            summary.n_verified_pairs -= summary.n_pairs_dropped
    return summary


def _write_cluster_matches(db, pairs: dict, colmap_id, local: np.ndarray,
                           progress: Callable[[int, int], None] | None = None) -> int:
    """Write every image pair's matches (:func:`cluster_pairs`; ``colmap_id[k]``: COLMAP's id of dqm image k,
    ``local``: every feature's keypoint index in its image) into the open pycolmap database; the match count.
    ``progress(done, total)``: image pairs written."""
    LOG.info("writing the matches of %s", count(len(pairs), "image pair"))
    n_matches = 0
    for done, ((a, b), m) in enumerate(pairs.items(), start=1):
        db.write_matches(colmap_id[a], colmap_id[b], local[m].astype(np.uint32))
        n_matches += len(m)
        if progress is not None:
            progress(done, len(pairs))
    return n_matches


#: COLMAP's RANSAC ``min_inlier_ratio`` (the inlier ratio its trial count assumes at least)
COLMAP_MIN_INLIER_RATIO = 0.25


def trial_ratio(n_matches: int, min_inliers: int) -> float:
    """The ``ransac.min_inlier_ratio`` of a pair of ``n_matches`` matches in :func:`_verify`: COLMAP's 0.25, or
    ``min_inliers / n_matches`` where that is larger. A pair passes COLMAP's verification only with
    ``min_inliers`` inliers, so only at that ratio or above; RANSAC's trial count at that ratio (with COLMAP's
    confidence 0.999 and its multiplier 3) finds such a model all the same, and a pair that cannot hold one
    stops there instead of running COLMAP's 10,000 trials."""
    return max(COLMAP_MIN_INLIER_RATIO, min_inliers / max(1, n_matches))


def _verify(path, num_threads: int, seed: int, progress: Callable[[int, int], None] | None = None) -> int:
    """COLMAP's geometric verification of every matched image pair of the database file ``path``: its
    two-view estimator (``pycolmap.estimate_two_view_geometry``, what COLMAP's verifier calls per pair, with
    its options) on ``num_threads`` threads (-1: every core), its RANSAC seeded (so the same matches give the
    same geometries) and each pair's trials bounded by :func:`trial_ratio`; every pair's geometry is written,
    as COLMAP's verifier writes them. Returns the number of verified image pairs. ``progress(done, total)``: image
    pairs verified.

    The bound is the only departure from ``pycolmap.geometric_verification`` with COLMAP's defaults (which
    gives the same geometries as this function without it, pair for pair): it makes the verification of
    nerf_lego's clusters (3,815 pairs, 2,180 of which fail) 2.6x faster, and loses the pairs that reach 15
    inliers only late in 10,000 trials (32 of 1,635 on nerf_lego, 2 of the 902 dtu/scan24 keeps, each with 15
    or 16 inliers among 19-35 matches: chance consensus more than geometry; docs/sfm.md, "At scale")."""
    from ..core.pairs import tile_pool

    pycolmap = require_pycolmap()
    db = pycolmap.Database.open(str(path))
    try:
        images = {im.image_id: im for im in db.read_all_images()}
        cameras = {c.camera_id: c for c in db.read_all_cameras()}
        pair_ids, _ = db.read_num_matches()
        pairs = [tuple(int(v) for v in pycolmap.pair_id_to_image_pair(p)) for p in pair_ids]
        points = {i: np.asarray(db.read_keypoints(i)[:, :2], np.float64)
                  for i in sorted({i for pair in pairs for i in pair})}
        matches = [db.read_matches(a, b) for a, b in pairs]
    finally:
        db.close()
    least = min_verified_matches()
    LOG.info("COLMAP's geometric verification of %s (RANSAC seed %d)", count(len(pairs), "image pair"), seed)

    def estimate(k: int):
        a, b = pairs[k]
        options = pycolmap.TwoViewGeometryOptions()
        options.ransac.random_seed = int(seed)  # COLMAP's default (-1) draws a new seed every run
        options.ransac.min_inlier_ratio = trial_ratio(len(matches[k]), least)
        return pycolmap.estimate_two_view_geometry(cameras[images[a].camera_id], points[a],
                                                   cameras[images[b].camera_id], points[b], matches[k], options)

    geometries = []
    with tile_pool(None if num_threads < 1 else num_threads) as run:  # None: tile_pool's default threads
        for g in run(estimate, range(len(pairs))):  # in pair order
            geometries.append(g)
            if progress is not None:
                progress(len(geometries), len(pairs))
    db = pycolmap.Database.open(str(path))
    try:
        for (a, b), g in zip(pairs, geometries):
            db.write_two_view_geometry(a, b, g)
    finally:
        db.close()
    return sum(1 for g in geometries if len(g.inlier_matches) >= least)


def _read_only(database: Path, read: Callable):
    """``read(connection)`` on the database's SQLite file opened read-only, or None where SQLite fails (not an
    SQLite file, a table or column missing).

    COLMAP's databases are in WAL mode, where a read-only reader makes ``-shm`` and ``-wal`` files beside the
    database and leaves them (it may not check the log back in), and cannot read at all in a read-only folder.
    Without a log of pending writes beside it the file is read as immutable: nothing is made beside it."""
    import sqlite3

    wal = Path(f"{database}-wal")
    pending = wal.exists() and wal.stat().st_size > 0
    try:
        con = sqlite3.connect(f"{Path(database).absolute().as_uri()}?{'mode=ro' if pending else 'immutable=1'}",
                              uri=True)
    except sqlite3.Error:
        return None
    try:
        return read(con)
    except sqlite3.Error:
        return None
    finally:
        con.close()


def _table_rows(database: Path, tables: Sequence[str]) -> dict[str, int] | None:
    """The number of rows of each table (read-only), or None when the file is not an SQLite database holding them."""
    return _read_only(database, lambda con: {t: int(con.execute(f"SELECT COUNT(*) FROM {t}").fetchone()[0])
                                             for t in tables})


def check_matches_target(database, *, overwrite: bool = False, option: str = "--into-database") -> Path:
    """Check, before any work, that matches can be written into the existing COLMAP database ``database``
    (:func:`write_matches`): a COLMAP database (matches and two-view geometry tables), writable, in a writable
    folder, and without matches or two-view geometries unless ``overwrite`` (they are then replaced). One
    InputError line otherwise; ``option`` names the command's option in it."""
    from ..outputs import check_file

    database = Path(database)
    if not database.is_file():
        raise InputError(f"{option}: COLMAP database not found: {database}")
    rows = _table_rows(database, ("images", "keypoints", "matches", "two_view_geometries"))
    if rows is None:
        raise InputError(f"{option}: {database} is not a COLMAP database (no matches or two_view_geometries table)")
    if not overwrite and (rows["matches"] or rows["two_view_geometries"]):
        raise InputError(f"{option}: {database} already holds {rows['matches']} image pairs' matches and "
                         f"{rows['two_view_geometries']} two-view geometries; pass --overwrite to replace them")
    require_pycolmap(what=f"{option}")
    return check_file(database, option, overwrite=True)


def _images_keypoints(database: Path) -> list | None:
    """``(image_id, name, keypoints)`` of every image in image-id order, read-only from the database's SQLite tables
    (0 keypoints where an image has none), or None where they are not laid out as COLMAP's."""
    return _read_only(database, lambda con: [(int(i), str(name), int(rows or 0)) for i, name, rows in con.execute(
        "SELECT images.image_id, images.name, keypoints.rows FROM images LEFT JOIN keypoints "
        "ON keypoints.image_id = images.image_id ORDER BY images.image_id")])


def _check_images(database: Path, images: list, ids: np.ndarray, names: Sequence[str] | None) -> None:
    """Refuse (InputError) a database whose images (``(image_id, name, keypoints)`` in image-id order) are not those
    the features ``ids`` (dqm image ids, in that order) were read from: other keypoint counts or, with ``names``,
    other image names."""
    found = [k for _, _, k in images]
    if (len(ids) and not 0 <= ids.min() <= ids.max() < len(images)) or \
            found != np.bincount(ids, minlength=len(images)).tolist():
        raise InputError(f"{database}: its images' keypoints ({len(images)} images, {sum(found)} keypoints) "
                         f"are not the matched features' ({len(np.unique(ids))} images, {len(ids)} features); "
                         "was it changed since it was read?")
    for k, (_, name, _) in enumerate(images if names is not None else ()):
        given = str(names[k]).replace(os.sep, "/") if k < len(names) else "(none)"
        if given != name and not given.endswith("/" + name):
            raise InputError(f"{database}: its image {k + 1} is {name}, the clusters' image {k + 1} is "
                             f"{given}: the clusters were not matched from this database")


def write_matches(database, labels, image_ids, *, overwrite: bool = False, verify: bool = True,
                  num_threads: int = -1, seed: int = 0, names: Sequence[str] | None = None,
                  partners: int = 0, cluster_matches: str = DEFAULT_CLUSTER_MATCHES,
                  progress: ProgressArg = None) -> ExportSummary:
    """Write the matches the clusters imply, and COLMAP's verified two-view geometries of them, into the COLMAP
    database the features were read from (:func:`import_database`), as COLMAP's own matchers do: its cameras,
    images, keypoints and descriptors stay as they are, so its mapper runs next.

    ``labels`` and ``image_ids`` are in :func:`import_database`'s order (images by COLMAP image id, keypoints
    in their rows' order); ``names`` (optional): the images' names in that order (one per image), each the
    database's name of its image or a path ending in it, checked with the keypoint counts (clusters matched from
    another database are refused). The database is checked first (:func:`check_matches_target`); existing
    matches and geometries are replaced only with ``overwrite``. The new database is written beside the old one and
    renamed over it when complete, so a stop or an error leaves the old one untouched. ``partners``,
    ``cluster_matches`` and ``progress``: as :func:`export_database`'s.
    """
    pycolmap = require_pycolmap()
    database = check_matches_target(database, overwrite=overwrite)
    ids = np.asarray(image_ids, np.int64)
    labels = np.asarray(labels, np.int64)
    if labels.shape != ids.shape:
        raise InputError(f"labels ({len(labels)}) and image ids ({len(ids)}) must have one entry per feature")
    listed = _images_keypoints(database)
    if listed is not None:  # checked before the database is copied (else on the copy, as pycolmap reads it)
        _check_images(database, listed, ids, names)
    pairs = cluster_pairs(labels, ids, cluster_matches)
    least = min_verified_matches() if verify else 1
    pairs, left_out = verifiable(pairs, least)
    pairs, beyond = strongest_partners(pairs, partners)
    local = local_indices(ids)
    bar = resolve_progress(progress, "export (write, then verify)", unit="pairs")
    mode = os.stat(database).st_mode & 0o7777
    with atomic_output(database, mode=mode) as tmp:
        shutil.copyfile(database, tmp)
        db = pycolmap.Database.open(tmp)
        try:
            images = sorted(db.read_all_images(), key=lambda im: im.image_id)
            if listed is None:
                _check_images(database, [(im.image_id, im.name, int(db.num_keypoints_for_image(im.image_id)))
                                         for im in images], ids, names)
            if overwrite:
                db.clear_two_view_geometries()
                db.clear_matches()
            n_matches = _write_cluster_matches(db, pairs, [im.image_id for im in images], local, bar)
        finally:
            db.close()
        summary = ExportSummary(database, None, len(images), len(ids), len(pairs), n_matches,
                                names=[im.name for im in images], n_pairs_left_out=left_out, min_matches=least,
                                n_pairs_beyond=beyond, partners=partners,
                                n_spaced_clusters=spaced_clusters(labels, ids, cluster_matches))
        if verify and pairs:
            summary.n_verified_pairs = _verify(tmp, num_threads, seed, bar)
            summary.n_pairs_dropped = drop_weak_pairs(tmp)
            summary.n_verified_pairs -= summary.n_pairs_dropped
    return summary


SQLITE_MAGIC = b"SQLite format 3\x00"


def is_database(path) -> bool:
    """A COLMAP database is known by its content (an SQLite file) or its .db suffix, in any case."""
    path = Path(path)
    if path.suffix.lower() == ".db":
        return True
    try:
        with open(path, "rb") as fh:
            return fh.read(16) == SQLITE_MAGIC
    except OSError:
        return False


#: ``descriptors.type`` of COLMAP's SIFT (FeatureExtractorType.SIFT): uint8 rows; the only type read without pycolmap
_SIFT_TYPE = 0


def _blob(row, dtype) -> np.ndarray | None:
    """A (rows, cols) array from a keypoints / descriptors row ``(rows, cols, data)``; None when the row is
    missing, empty or its bytes do not make rows x cols of ``dtype`` (pycolmap then reads the database)."""
    if row is None:
        return None
    rows, cols, data = row
    if not rows or data is None or len(data) != rows * cols * np.dtype(dtype).itemsize:
        return None
    return np.frombuffer(data, dtype).reshape(rows, cols)


def _read_tables(database: Path) -> list | None:
    """``(name, keypoints, descriptors)`` of every image in image-id order, read from the database's SQLite
    tables (read-only: COLMAP's layout of 3.x and 4.x, float32 keypoints, uint8 SIFT descriptors; an image
    without keypoints or descriptors has None). None where anything else is found: then pycolmap reads it.
    Without pycolmap's import (0.06 s and 60 MB at start-up)."""
    def read(con):
        cols = {t: {r[1] for r in con.execute(f"PRAGMA table_info({t})")}
                for t in ("images", "keypoints", "descriptors")}
        blob_cols = {"image_id", "rows", "cols", "data"}
        if not ({"image_id", "name"} <= cols["images"] and blob_cols <= cols["keypoints"]
                and blob_cols <= cols["descriptors"]):
            return None
        typed = "type" in cols["descriptors"]
        images = con.execute("SELECT image_id, name FROM images ORDER BY image_id").fetchall()
        keypoints = {r[0]: r[1:] for r in con.execute("SELECT image_id, rows, cols, data FROM keypoints")}
        descriptors = {}
        for r in con.execute("SELECT image_id, rows, cols, data" + (", type" if typed else "") + " FROM descriptors"):
            if typed and r[4] != _SIFT_TYPE:
                return None
            descriptors[r[0]] = r[1:4]
        return images, keypoints, descriptors

    tables = _read_only(database, read)
    if tables is None:
        return None
    images, keypoints, descriptors = tables
    out = []
    for image_id, name in images:
        kp, desc = _blob(keypoints.get(image_id), np.float32), _blob(descriptors.get(image_id), np.uint8)
        if (kp is None and image_id in keypoints) or (desc is None and image_id in descriptors):
            return None  # present but not as expected (empty, other sizes): pycolmap's reading decides
        out.append((str(name), kp, desc))
    return out


def unreadable_because(database: Path, exc: BaseException) -> str:
    """Why SQLite (through pycolmap) could not open ``database``, in words: not an SQLite file, a truncated one, a
    read-only folder (SQLite must make its ``-shm`` file beside a WAL database), or the error itself."""
    try:
        with open(database, "rb") as fh:
            head = fh.read(100)
    except OSError as err:
        return err.strerror or str(err)
    if not head.startswith(SQLITE_MAGIC):
        return "it is not an SQLite file"
    page = int.from_bytes(head[16:18], "big")
    page = 65536 if page == 1 else page
    pages = int.from_bytes(head[28:32], "big")
    size = database.stat().st_size
    if len(head) < 100 or size < page * pages:
        return f"it is truncated ({size:,} bytes of the {page * pages:,} its header gives)"
    folder = database.absolute().parent
    if not os.access(folder, os.W_OK):
        return (f"its folder {folder} is read-only, and SQLite must make its -shm file beside a COLMAP database "
                "(copy the database somewhere writable)")
    return f"{type(exc).__name__}: {str(exc).strip() or 'SQLite refused it'}"


def _read_with_pycolmap(database: Path) -> list:
    """As :func:`_read_tables`, through pycolmap (any layout it reads)."""
    pycolmap = require_pycolmap(what="reading this COLMAP database")
    try:
        db = pycolmap.Database.open(str(database))
    except Exception as exc:  # noqa: BLE001 - a file that is not a database
        raise InputError(f"{database}: cannot be read as a COLMAP database: {unreadable_because(database, exc)}") \
            from None
    try:
        out = []
        for im in sorted(db.read_all_images(), key=lambda im: im.image_id):
            kp = np.asarray(db.read_keypoints(im.image_id)) if db.exists_keypoints(im.image_id) else None
            desc = np.asarray(db.read_descriptors(im.image_id).data) if db.exists_descriptors(im.image_id) else None
            out.append((im.name, kp, desc))
        return out
    finally:
        db.close()


def import_database(database, image_dir=None) -> FeatureSet:
    """Keypoints, descriptors and image names of a COLMAP database as a FEATURES set.

    Images in COLMAP's image-id order get dqm image ids 0..m-1; keypoints are converted to
    OpenCV's pixel convention (x, y; 0.5 subtracted) and keep COLMAP's scale and orientation
    when the database stores them (4 columns) or derives them from the affine shape (6).
    ``image_names`` are the database's names, under ``image_dir`` when given. SIFT databases are read
    straight from their tables; others (descriptor types besides SIFT, layouts not known here) by pycolmap.
    """
    database = Path(database)
    if not database.is_file():
        raise InputError(f"COLMAP database not found: {database}")
    with open(database, "rb") as fh:  # checked here: pycolmap would log its own error line first
        if fh.read(16) != SQLITE_MAGIC:
            raise InputError(f"{database}: not a COLMAP database (not an SQLite file)")
    images = _read_tables(database)
    if images is None:
        images = _read_with_pycolmap(database)
    if not images:
        raise InputError(f"{database}: the database holds no images")
    D, K, ids, names = [], [], [], []
    for k, (name, kp, desc) in enumerate(images):
        if kp is None or desc is None:
            raise InputError(f"{database}: image {name} has no keypoints or no descriptors")
        kp = np.asarray(kp, np.float64)
        if len(kp) != len(desc):
            raise InputError(f"{database}: image {name} has {len(kp)} keypoints but {len(desc)} descriptors")
        out = np.zeros((len(kp), 4), np.float32)
        out[:, :2] = kp[:, :2] - 0.5
        if kp.shape[1] == 4:
            out[:, 2], out[:, 3] = kp[:, 2], np.degrees(kp[:, 3])
        elif kp.shape[1] == 6:  # affine shape a11 a12 a21 a22: scale and orientation of its first column
            out[:, 2] = np.hypot(kp[:, 2], kp[:, 4])
            out[:, 3] = np.degrees(np.arctan2(kp[:, 4], kp[:, 2]))
        D.append(desc)
        K.append(out)
        ids.append(np.full(len(kp), k, np.int64))
        names.append(str(Path(image_dir) / name) if image_dir is not None else name)
    if len({d.shape[1] for d in D if d.size}) > 1:
        raise InputError(f"{database}: descriptor dimensions differ between images")
    return FeatureSet(descriptors=np.concatenate(D), image_ids=np.concatenate(ids), keypoints=np.concatenate(K),
                      image_names=np.array(names)).validate(str(database))
