"""SIFT features with OpenCV: detection + description, or description at given points.

Keypoints travel as a float32 (n, 4) array with columns x, y, size, angle
(OpenCV conventions: pixels, 0-based, angle in degrees, -1 = not set).

Images come as paths or arrays; :func:`collect_images` turns folders (optionally
recursive), glob patterns, files and image-list files (:func:`read_image_list`)
into a list of image paths, each folder's in natural order (``img2`` before ``img10``).
"""
from __future__ import annotations

import glob
import logging
import os
import re
import warnings
from collections import deque
from collections.abc import Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from itertools import islice
from pathlib import Path

import numpy as np

from .. import signals
from ..progress import ticking
from ..validation import InputError

#: SIFT settings; "paper" is the seed paper's experiment preset
PRESETS: dict[str, dict[str, float]] = {
    "opencv": {},
    "paper": {"nOctaveLayers": 6, "contrastThreshold": 0.10, "edgeThreshold": 15, "sigma": 1.0},
    "rootsift": {},
    # RootSIFT with a lower contrast threshold: about 1.3x the features; the best cameras in
    # scripts/bench_sfm.py (docs/sfm.md), so dqm sfm's default
    "sfm": {"contrastThreshold": 0.03},
    # COLMAP's feature budget with OpenCV's SIFT: contrast threshold 0.02, then each image's
    # LOCATION_BUDGET strongest locations with all their orientations (docs/sfm.md, "Where COLMAP's
    # points go")
    "budget": {"contrastThreshold": 0.02},
}
#: presets that keep each image's N strongest keypoint locations (every orientation of each), as COLMAP's
#: SiftExtractionOptions.max_num_features counts them
LOCATION_BUDGET = {"budget": 8192}
#: presets made by another library: pycolmap's SIFT with COLMAP's default options (L1-root
#: normalised, i.e. RootSIFT, stored x512 as uint8; peak threshold 0.02/3, up-sampled first
#: octave, 8192 features per image unless --max-features says otherwise)
EXTERNAL_PRESETS = {"colmap": "pycolmap's SIFT, COLMAP's default extraction options"}
#: every preset name
PRESET_NAMES = tuple(PRESETS) + tuple(EXTERNAL_PRESETS)
#: COLMAP's SiftExtractionOptions.max_num_features, used by the colmap preset when no limit is given
COLMAP_MAX_FEATURES = 8192
#: the default: RootSIFT won against plain SIFT on every dataset in dqm evaluate (docs/sfm.md)
DEFAULT_PRESET = "rootsift"
#: the default of ``dqm sfm``: RootSIFT at contrast threshold 0.03 (docs/sfm.md, "Which default")
SFM_PRESET = "sfm"
#: presets whose descriptors are RootSIFT (:func:`root_sift`) rather than plain SIFT
ROOT_PRESETS = frozenset({"rootsift", "sfm", "budget"})


def root_sift(descriptors) -> np.ndarray:
    """RootSIFT (Arandjelovic & Zisserman 2012): L1-normalise, take square roots, store as uint8.

    Euclidean distance between RootSIFT vectors is the Hellinger distance between the SIFT
    histograms. The unit-L2 result is scaled by 512 and clipped to 255, as COLMAP stores its
    (L1-root normalised, by default) SIFT, so the descriptors stay 128-D uint8.
    """
    d = np.asarray(descriptors, np.float64)
    d = d / np.maximum(d.sum(axis=1, keepdims=True), 1e-12)
    return np.minimum(np.round(np.sqrt(d) * 512.0), 255).astype(np.uint8)


def _finish(desc, preset: str) -> np.ndarray:
    out = np.clip(np.round(desc), 0, 255).astype(np.uint8)
    return root_sift(out) if preset in ROOT_PRESETS else out


@dataclass(frozen=True)
class ImageFeatures:
    """Keypoints (n, 4: x, y, size, angle) and uint8 SIFT descriptors (n, 128) of one image."""

    keypoints: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return len(self.descriptors)


#: file suffixes treated as images (case-insensitive)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".ppm", ".pgm", ".bmp", ".tif", ".tiff")


def natural_key(path: str | Path) -> tuple:
    """Sort key that orders embedded numbers by value: img2 < img10, seq9 < seq10."""
    parts = re.split(r"(\d+)", str(path))
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in parts)


def _folder_images(folder: Path, recursive: bool) -> list[Path]:
    """The image files in ``folder`` (and its sub-folders when ``recursive``), in natural order.

    Natural order part by part of the path below ``folder`` (``a/img2`` < ``a/img10`` < ``b/img1``).
    Links to folders are not followed (as COLMAP's image reader).
    """
    if recursive:
        found = [Path(root) / name for root, _, files in os.walk(folder) for name in files]
    else:
        found = list(folder.iterdir())
    found = [q for q in found if q.suffix.lower() in IMAGE_SUFFIXES and q.is_file()]
    return sorted(found, key=lambda q: tuple(natural_key(part) for part in q.relative_to(folder).parts))


def read_image_list(path: str | Path) -> list[Path]:
    """The image files named in a list file, one path a line, in the list's order.

    Relative paths are taken from the list file's folder; blank lines and lines
    starting with ``#`` are ignored; leading and trailing white space is dropped.
    The paths come back absolute (not resolved: links stay links). Raises
    InputError naming the list and the line of the first missing or non-file entry
    (and how many are missing), or a list that names no image.
    """
    lst = Path(path)
    if not lst.is_file():
        raise InputError(f"image list not found: {lst}" if not lst.exists() else f"image list {lst} is not a file")
    try:
        lines = lst.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"image list {lst}: not a readable UTF-8 text file ({exc})") from None
    root = Path(os.path.abspath(lst.parent))
    out: list[Path] = []
    missing: list[tuple[int, str]] = []
    for number, line in enumerate(lines, 1):
        entry = line.strip()
        if not entry or entry.startswith("#"):
            continue
        q = Path(os.path.normpath(root / entry))
        if q.is_dir():
            raise InputError(f"{lst}:{number}: {entry} is a folder; an image list names image files")
        if not q.is_file():
            missing.append((number, entry))
        out.append(q)
    if missing:
        number, entry = missing[0]
        more = f" ({len(missing)} of the {len(out)} listed images are missing)" if len(missing) > 1 else ""
        raise InputError(f"{lst}:{number}: image not found: {entry} (looked for {root / entry}){more}")
    if not out:
        raise InputError(f"image list {lst} names no image (blank lines and # comments only)")
    return out


def collect_images(inputs: str | Path | Iterable[str | Path] = (), recursive: bool = False,
                   image_list: str | Path | None = None) -> list[Path]:
    """Expand folders, glob patterns, files and an image list into a list of image paths.

    Each item: a folder (its image files; with ``recursive`` those of its
    sub-folders too), a glob pattern (``'photos/*.jpg'``; ``**`` matches any
    depth of folders) or an image file. ``image_list``: a text file naming
    images, one a line (:func:`read_image_list`), read after the items. Order:
    items in the order given, each folder's or pattern's images in natural order
    (``img2`` before ``img10``), then the list's images in its order; an image
    named twice is kept at its first place. Raises InputError naming a missing
    item, a folder or pattern without images, or when nothing is given.
    """
    items = [inputs] if isinstance(inputs, (str, Path)) else list(inputs)
    if not items and image_list is None:
        raise InputError("no image inputs given: name image folders, glob patterns or files, or an image list")
    out: list[Path] = []
    for item in items:
        text = str(item)
        p = Path(text)
        if p.is_dir():
            found = _folder_images(p, recursive)
            if not found:
                hint = ""
                if not recursive:
                    below = len(_folder_images(p, True))
                    hint = f"; its sub-folders hold {below} image(s) (--recursive reads them)" if below else ""
                raise InputError(f"no image files ({', '.join(IMAGE_SUFFIXES)}) in folder {p}{hint}")
            out += found
        elif p.exists():
            out.append(p)
        elif any(ch in text for ch in "*?["):
            found = sorted((Path(q) for q in glob.glob(text, recursive=True)
                            if Path(q).suffix.lower() in IMAGE_SUFFIXES and Path(q).is_file()), key=natural_key)
            if not found:
                raise InputError(f"no image files match {text!r}")
            out += found
        else:
            raise InputError(f"input not found: {text}")
    if image_list is not None:
        out += read_image_list(image_list)
    seen, unique = set(), []
    for q in out:
        r = q.resolve()
        if r not in seen:
            seen.add(r)
            unique.append(q)
    return unique


def read_gray(path) -> np.ndarray:
    """Read an image file as 8-bit grayscale; clear error if it cannot be read."""
    import cv2

    p = Path(path)
    if not p.exists():
        raise InputError(f"image not found: {p}")
    img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
    if img is None or img.size == 0:
        raise InputError(f"cannot read image (not an image or empty): {p}")
    if truncated_jpeg(p):
        warnings.warn(f"{p} is a truncated JPEG file (it has no end marker): its missing part is read as grey, "
                      "where no features are found", stacklevel=2)
    return img


#: the end marker (EOI) of a JPEG file, and how far from the end it may sit (some writers pad after it)
JPEG_END, JPEG_END_WITHIN = b"\xff\xd9", 4096


def truncated_jpeg(path) -> bool:
    """Whether ``path`` is a JPEG file (by its first bytes) without its end marker near the end: libjpeg decodes
    such a file with a warning that names no file ('Premature end of JPEG file')."""
    with open(path, "rb") as fh:
        if fh.read(3) != b"\xff\xd8\xff":
            return False
        fh.seek(0, os.SEEK_END)
        size = fh.tell()
        fh.seek(max(0, size - JPEG_END_WITHIN))
        return JPEG_END not in fh.read()


def as_gray(image) -> np.ndarray:
    """An image (path, grayscale or BGR(A) array, any numeric dtype) as a 2-D uint8 array."""
    if isinstance(image, (str, Path)):
        return read_gray(image)
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        import cv2

        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if img.ndim != 2 or img.size == 0:
        raise InputError(f"image must be a non-empty 2-D grayscale or BGR array, got shape {img.shape}")
    if img.dtype != np.uint8:
        if np.issubdtype(img.dtype, np.floating) and img.max() <= 1.0:
            img = img * 255.0
        img = np.clip(img, 0, 255).astype(np.uint8)
    return img


def check_preset(preset: str, max_features: int = 0) -> None:
    """One line naming a bad preset or feature limit (a missing pycolmap for the colmap preset)."""
    if preset not in PRESET_NAMES:
        raise InputError(f"unknown SIFT preset {preset!r}; choose from {sorted(PRESET_NAMES)}")
    if int(max_features) != max_features or max_features < 0:
        raise InputError(f"max_features must be >= 0 (0 = no limit), got {max_features}")
    if preset == "colmap":
        from .colmap import require_pycolmap

        require_pycolmap(what="--preset colmap (COLMAP's SIFT)")


def create_sift(preset: str = "opencv", max_features: int = 0):
    import cv2

    check_preset(preset, max_features)
    if preset not in PRESETS:
        raise InputError(f"preset {preset!r} is not OpenCV's SIFT; it detects its own points (use an OpenCV preset: "
                         f"{', '.join(sorted(PRESETS))})")
    return cv2.SIFT_create(nfeatures=int(max_features), **PRESETS[preset])


def extract_colmap(images: Sequence, max_features: int = 0, progress=None,
                   failed: list[int] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """pycolmap's SIFT (COLMAP's default options, its threads) of images: as :func:`extract_many`.

    COLMAP's extractor reads files: paths are read where they are (one temporary database,
    deleted after), arrays are written as PNG files first. Keypoints come back in OpenCV's pixel
    convention with COLMAP's scale and orientation (:func:`dqm.vision.colmap.import_database`).
    ``max_features`` 0 means COLMAP's default, 8192 per image.
    """
    import tempfile

    from .colmap import colmap_log_kept, import_database, require_pycolmap

    pycolmap = require_pycolmap()
    images = list(images)
    with tempfile.TemporaryDirectory(prefix="dqm-colmap-sift-") as tmp:
        files = []
        for k, im in enumerate(images):
            if isinstance(im, (str, Path)):
                files.append(Path(os.path.abspath(im)))
            else:
                import cv2

                files.append(Path(tmp) / f"image{k}.png")
                cv2.imwrite(str(files[-1]), as_gray(im))
        root = Path(os.path.commonpath([str(f.parent) for f in files]))
        names = [f.relative_to(root).as_posix() for f in files]
        options = pycolmap.FeatureExtractionOptions()
        options.sift.max_num_features = int(max_features) or COLMAP_MAX_FEATURES
        db = Path(tmp) / "features.db"
        logging.getLogger("dqm.vision").info("COLMAP's SIFT (pycolmap's extractor): %d images", len(names))
        with colmap_log_kept(pycolmap, pycolmap.logging.ERROR), ticking(progress, "sift (COLMAP's extractor)"):
            # it reports no images: its time, then them
            signals.interruptible(pycolmap.extract_features, str(db), str(root), image_names=names,
                                  camera_mode=pycolmap.CameraMode.PER_IMAGE, extraction_options=options,
                                  device=pycolmap.Device.cpu)
        fs = import_database(db)
    where = {str(nm): k for k, nm in enumerate(fs.image_names)}
    descs, ids, kps = [], [], []
    for k, nm in enumerate(names):
        if nm not in where:  # COLMAP could not read it
            if failed is None:
                raise InputError(f"COLMAP's extractor could not read image {files[k]}")
            failed.append(k)
            continue
        rows = fs.image_ids == where[nm]
        descs.append(fs.descriptors[rows])
        kps.append(fs.keypoints[rows])
        ids.append(np.full(int(rows.sum()), k - (0 if failed is None else len(failed)), np.int64))
        if progress is not None:
            progress(k + 1, len(images))
    if not descs:
        return np.zeros((0, 128), np.uint8), np.zeros(0, np.int64), np.zeros((0, 4), np.float32)
    return np.vstack(descs).astype(np.uint8), np.concatenate(ids), np.vstack(kps).astype(np.float32)


def _kp_array(kps) -> np.ndarray:
    return np.array([(k.pt[0], k.pt[1], k.size, k.angle) for k in kps], dtype=np.float32).reshape(-1, 4)


def strongest_locations(keypoints, n: int) -> list:
    """The keypoints at the ``n`` locations of highest response (a location's response: its strongest
    keypoint's; OpenCV gives a location one keypoint per orientation), every orientation kept, in the input's
    order; ties between locations go to the earlier."""
    kps = list(keypoints)
    if not kps:
        return kps
    pts = np.array([k.pt for k in kps], np.float64)
    _, loc = np.unique(pts, axis=0, return_inverse=True)
    loc = loc.ravel()
    best = np.full(int(loc.max()) + 1, -np.inf)
    np.maximum.at(best, loc, np.array([k.response for k in kps], np.float64))
    first = np.full(len(best), len(kps))
    np.minimum.at(first, loc, np.arange(len(kps)))
    rank = np.empty(len(best), np.int64)
    rank[np.lexsort((first, -best))] = np.arange(len(best))
    return [k for k, r in zip(kps, rank[loc]) if r < n]


def extract(image, preset: str = DEFAULT_PRESET, max_features: int = 0) -> ImageFeatures:
    """Detect and describe SIFT features of an image (path or array)."""
    if preset in EXTERNAL_PRESETS:
        check_preset(preset, max_features)
        D, _, kp = extract_colmap([image], max_features)
        return ImageFeatures(kp, D)
    img = as_gray(image)
    sift = create_sift(preset, max_features)
    if preset in LOCATION_BUDGET:
        kps = strongest_locations(sift.detect(img, None), LOCATION_BUDGET[preset])
        kps, desc = sift.compute(img, kps) if kps else ((), None)
    else:
        kps, desc = sift.detectAndCompute(img, None)
    if desc is None:
        desc = np.zeros((0, 128), np.float32)
    if max_features and len(kps) > max_features:
        # OpenCV's nfeatures keeps the N strongest keypoints, then adds a copy per extra orientation: keep the
        # N strongest of those (ties: the earlier), in OpenCV's order, so that the limit holds
        keep = np.sort(np.argsort(-np.array([k.response for k in kps]), kind="stable")[:max_features])
        kps, desc = [kps[i] for i in keep], desc[keep]
    return ImageFeatures(_kp_array(kps), _finish(desc, preset))


def describe_at(image, points, size: float = 24.0, angle: float = 0.0,
                preset: str = "opencv") -> ImageFeatures:
    """SIFT descriptors at given points: (n, 2) x, y (0-based pixels) or (n, 4) x, y, size, angle.

    With (n, 2) points every patch has ``size`` pixels and orientation ``angle``
    (degrees); (n, 4) keypoints (e.g. from :func:`extract`) carry their own.
    Points whose patch OpenCV drops (too close to the border) raise an error
    naming them, so descriptors always line up with the points given.
    """
    import cv2

    img = as_gray(image)
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] not in (2, 4):
        raise InputError(f"points must be (n, 2) x, y or (n, 4) x, y, size, angle; got shape {pts.shape}")
    if not np.isfinite(pts).all():
        raise InputError("points contain NaN or inf")
    if pts.shape[1] == 2:
        pts = np.c_[pts, np.full(len(pts), float(size)), np.full(len(pts), float(angle))]
    if (pts[:, 2] <= 0).any():
        raise InputError("keypoint sizes must be positive")
    if len(pts) == 0:
        return ImageFeatures(np.zeros((0, 4), np.float32), np.zeros((0, 128), np.uint8))
    kps = [cv2.KeyPoint(float(x), float(y), float(sz), float(a)) for x, y, sz, a in pts]
    out_kps, desc = create_sift(preset).compute(img, kps)
    if desc is None or len(out_kps) != len(kps):
        kept = {(round(k.pt[0], 3), round(k.pt[1], 3)) for k in (out_kps or [])}
        lost = [i for i, (x, y) in enumerate(pts[:, :2]) if (round(x, 3), round(y, 3)) not in kept]
        raise InputError(f"OpenCV could not describe points {lost[:10]} (outside the image?)")
    return ImageFeatures(_kp_array(out_kps), _finish(desc, preset))


def landmark_descriptors(seq, size: float = 24.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Describe every labelled landmark of every frame of a :class:`LandmarkSequence`.

    Returns ``(descriptors, image_ids, landmark_ids, keypoints)``. Upright
    patches of ``size`` pixels (24 px: measured best on CMU hotel among 8-32 px,
    see docs/quickmatch.md).
    """
    descs, ids, lms, kps = [], [], [], []
    for k, path in enumerate(seq.image_paths):
        f = describe_at(path, seq.landmarks[k], size=size)
        descs.append(f.descriptors)
        kps.append(f.keypoints)
        ids.append(np.full(len(f), k))
        lms.append(np.arange(len(f)))
    return np.vstack(descs), np.concatenate(ids), np.concatenate(lms), np.vstack(kps)


@contextmanager
def _extractor(preset: str, max_features: int, n_images: int):
    """``each(images)``: :func:`extract` of each image in order (an image that cannot be read: its InputError),
    one image per core at a time with OpenCV's own threads at 1 while they run: 1.45x faster than one image at a
    time with OpenCV's threads on 2 cores (dtu/scan24's 49 photos: 31.1 -> 21.5 s), and the same features,
    since each image's are computed alone. At most two images a worker are in flight; on leaving, those not
    started are cancelled (an interrupted extraction waits for the images being read, not for the rest)."""
    import cv2

    from ..core.pairs import default_threads

    def one(im):
        try:
            return extract(im, preset, max_features)
        except InputError as e:
            return e

    workers = min(default_threads(), n_images)
    if workers <= 1:
        yield lambda images: map(one, images)
        return
    pool = ThreadPoolExecutor(workers)
    before = cv2.getNumThreads()
    cv2.setNumThreads(1)

    def each(images):
        it = iter(images)
        pending = deque(pool.submit(one, im) for im in islice(it, 2 * workers))
        while pending:
            done = pending.popleft().result()
            for im in islice(it, 1):
                pending.append(pool.submit(one, im))
            yield done

    try:
        yield each
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        cv2.setNumThreads(before)


def extract_many(images: Sequence, preset: str = DEFAULT_PRESET, max_features: int = 0,
                 progress=None, failed: list[int] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Extract from a list of images (paths or arrays): ``(descriptors, image_ids, keypoints)`` stacked.

    Image ids are positions in ``images`` (0, 1, ...); an image without
    features simply has no rows. ``progress``: callable ``(done, total)``
    called after each image (e.g. a :class:`dqm.progress.ProgressBar`).
    ``failed``: when a list is given, an image that cannot be read is left
    out (its position is appended) instead of raising, and the ids count the
    images kept.
    """
    descs, ids, kps = [], [], []
    images = list(images)
    check_preset(preset, max_features)  # validate the settings before any work
    if preset in EXTERNAL_PRESETS:
        return extract_colmap(images, max_features, progress, failed)
    with _extractor(preset, max_features, len(images)) as each:
        for k, f in enumerate(each(images)):
            if isinstance(f, InputError):
                if failed is None:
                    raise f
                failed.append(k)
                continue
            descs.append(f.descriptors)
            kps.append(f.keypoints)
            ids.append(np.full(len(f), k - (0 if failed is None else len(failed)), np.int64))
            if progress is not None:
                progress(k + 1, len(images))
    if not descs:
        return np.zeros((0, 128), np.uint8), np.zeros(0, np.int64), np.zeros((0, 4), np.float32)
    return np.vstack(descs), np.concatenate(ids).astype(np.int64), np.vstack(kps)


def unreadable_images(paths: Sequence[Path]) -> list[Path]:
    """The files OpenCV has no decoder for (by their header; cheap, nothing is decoded)."""
    import cv2

    return [p for p in paths if not cv2.haveImageReader(str(p))]


def extract_images(inputs, preset: str = DEFAULT_PRESET, max_features: int = 0, progress=None, min_images: int = 2,
                   skip_bad: bool = False, skipped: list[str] | None = None, recursive: bool = False,
                   image_list: str | Path | None = None):
    """SIFT of every image in folders / globs / files: a :class:`dqm.io.FeatureSet` with keypoints and names.

    ``inputs``, ``recursive`` and ``image_list`` name the images as in :func:`collect_images`.

    Unreadable files are found before any SIFT runs: by default they are
    refused in one line naming them; with ``skip_bad`` they are left out (and
    appended to ``skipped``), as is an image that fails to decode later.
    Raises InputError when fewer than ``min_images`` images are found or fewer
    than ``min_images`` of them have any feature (nothing to match).
    """
    from ..io import FeatureSet

    paths = collect_images(inputs, recursive=recursive, image_list=image_list)
    bad = unreadable_images(paths)
    if bad and not skip_bad:
        raise InputError(f"cannot read image(s) (not an image or empty): {len(bad)} file(s): "
                         + ", ".join(str(p) for p in bad[:5]) + (" ..." if len(bad) > 5 else "")
                         + "; --skip-bad-images leaves them out")
    paths = [p for p in paths if p not in bad]
    lost = [str(p) for p in bad]
    if len(paths) < min_images:
        raise InputError(f"need at least {min_images} images to match, got {len(paths)}: "
                         + ", ".join(str(p) for p in paths))
    # with skip_bad, a file whose header looks fine but fails to decode is left out too
    failed: list[int] | None = [] if skip_bad else None
    D, ids, kp = extract_many(paths, preset=preset, max_features=max_features, progress=progress, failed=failed)
    if failed:
        gone = set(failed)
        lost += [str(paths[k]) for k in failed]
        paths = [p for k, p in enumerate(paths) if k not in gone]
    if skipped is not None:
        skipped.extend(lost)
    if len(paths) < min_images:
        raise InputError(f"need at least {min_images} readable images, got {len(paths)}")
    with_features = len(np.unique(ids))
    if with_features < min_images:
        raise InputError(f"SIFT found features in only {with_features} of {len(paths)} images "
                         f"(blank or tiny images?); matching needs at least {min_images}")
    return FeatureSet(D, ids, kp, np.array([str(p) for p in paths]))
