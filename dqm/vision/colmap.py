"""COLMAP databases in and out: QuickMatch clusters become tracks that COLMAP reconstructs.

Export (:func:`export_database`) writes what COLMAP's own feature extraction and matching would:

* one camera per image, ``SIMPLE_RADIAL``; the focal length comes from the image's EXIF when
  COLMAP can read it there (then marked as a prior), otherwise COLMAP's own default,
  ``1.2 * max(width, height)``; the principal point is the image centre;
* a trivial rig and frame per image (COLMAP 3.12+ databases hold them);
* keypoints in COLMAP's convention (the centre of the top-left pixel is (0.5, 0.5); dqm and
  OpenCV put it at (0, 0), so 0.5 is added);
* SIFT descriptors when the features are 128-D uint8 (COLMAP's descriptor type); other
  descriptors are left out (the mapper does not read them);
* the matches implied by the clusters for every image pair: every two members of a cluster;
* verified two-view geometries, computed by COLMAP itself (``pycolmap.geometric_verification``
  over the exported matches), so ``pycolmap.incremental_mapping(DB, IMAGE_DIR, OUT)`` runs
  with no further step.

Import (:func:`import_database`) reads keypoints, descriptors and image names back into a
FEATURES set, so ``dqm match`` / ``dqm run`` cluster features that COLMAP extracted.

pycolmap is an optional dependency (``pip install 'dqm[colmap]'``).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..io import FeatureSet
from ..validation import InputError

#: COLMAP's default focal length without EXIF, relative to the larger image side
DEFAULT_FOCAL_FACTOR = 1.2


def require_pycolmap(quiet: bool = True):
    """The pycolmap module, or one line saying how to install it.

    ``quiet``: COLMAP's own log keeps to warnings and errors (its info lines go to stderr).
    """
    try:
        import pycolmap
    except ImportError:
        raise InputError("COLMAP import/export needs pycolmap: pip install 'dqm[colmap]'") from None
    if quiet and hasattr(pycolmap, "logging"):
        pycolmap.logging.minloglevel = int(pycolmap.logging.WARNING)
    return pycolmap


def cluster_pairs(labels, image_ids) -> Dict[Tuple[int, int], np.ndarray]:
    """Every two members of every cluster, grouped by image pair.

    Returns ``{(a, b): (m, 2) int64 array of feature indices}`` with image ``a < b`` and column 0
    in image ``a``. Within a cluster the images differ (constraint C2), so no pair is dropped.
    """
    labels = np.asarray(labels, np.int64)
    ids = np.asarray(image_ids, np.int64)
    order = np.argsort(labels, kind="stable")
    bounds = np.flatnonzero(np.diff(labels[order])) + 1
    first, second = [], []
    for members in np.split(order, bounds):
        if len(members) < 2:
            continue
        i, j = np.triu_indices(len(members), 1)
        first.append(members[i])
        second.append(members[j])
    if not first:
        return {}
    f, g = np.concatenate(first), np.concatenate(second)
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


@dataclass
class ExportSummary:
    database: Path
    image_dir: Path
    n_images: int
    n_keypoints: int
    n_image_pairs: int
    n_matches: int
    n_verified_pairs: int = 0
    names: List[str] = field(default_factory=list)


def _image_folder(paths: Sequence[Path], image_dir: Optional[Path]) -> Tuple[Path, List[str]]:
    """The image folder and each image's name relative to it (COLMAP names images that way)."""
    if image_dir is None:
        image_dir = Path(os.path.commonpath([str(p.parent) for p in paths]))
    names = []
    for p in paths:
        try:
            # absolute, not resolved: a folder of links to the images is a valid COLMAP image folder
            names.append(Path(os.path.abspath(p)).relative_to(os.path.abspath(image_dir)).as_posix())
        except ValueError:
            raise InputError(f"image {p} is not inside the image folder {image_dir}") from None
    return image_dir, names


def resolve_images(image_names, image_dir=None) -> List[Path]:
    """Paths of the images, found as named or under ``image_dir``; one line if one is missing."""
    out = []
    for name in [str(n) for n in image_names]:
        p = Path(name)
        candidates = [p] if image_dir is None else [p, Path(image_dir) / p, Path(image_dir) / p.name]
        found = next((c for c in candidates if c.is_file()), None)
        if found is None:
            where = f" or under {image_dir}" if image_dir is not None else " (pass --image-dir)"
            raise InputError(f"image {name} not found{where}; the export needs every image's size")
        out.append(found)
    return out


def export_database(database, keypoints, image_ids, image_paths: Sequence, labels, *,
                    image_dir=None, descriptors=None, verify: bool = True,
                    num_threads: int = -1) -> ExportSummary:
    """Write a COLMAP database from clusters (see the module docstring); refuses an existing file.

    ``keypoints``: (n, >=2) OpenCV pixel coordinates; ``image_ids``: 0..m-1 indexing
    ``image_paths`` (existing image files); ``labels``: the clusters.
    """
    pycolmap = require_pycolmap()
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
    folder, names = _image_folder(paths, None if image_dir is None else Path(image_dir))
    desc = None if descriptors is None else np.asarray(descriptors)
    if desc is not None and (desc.dtype != np.uint8 or desc.shape[1:] != (128,)):
        desc = None  # COLMAP's descriptor type is 128-D uint8; the mapper does not need others
    pairs = cluster_pairs(labels, ids)
    rows_of = [np.flatnonzero(ids == k) for k in range(len(paths))]
    local = np.zeros(n, np.int64)  # index of each feature within its image
    for rows in rows_of:
        local[rows] = np.arange(len(rows))
    database.parent.mkdir(parents=True, exist_ok=True)
    colmap_id = {}
    db = pycolmap.Database.open(str(database))
    try:
        for k, (path, name) in enumerate(zip(paths, names)):
            bitmap = pycolmap.Bitmap.read(str(path), False)
            if bitmap is None:
                raise InputError(f"image {path} cannot be read")
            w, h = bitmap.width, bitmap.height
            exif = bitmap.exif_focal_length()
            focal = float(exif) if exif else DEFAULT_FOCAL_FACTOR * max(w, h)
            cam = pycolmap.Camera.create_from_model_name(0, "SIMPLE_RADIAL", focal, w, h)
            cam.has_prior_focal_length = bool(exif)
            cam.camera_id = db.write_camera(cam)
            rig = pycolmap.Rig()
            rig.add_ref_sensor(cam.sensor_id)
            rig_id = db.write_rig(rig)
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
        n_matches = 0
        for (a, b), m in pairs.items():
            db.write_matches(colmap_id[a], colmap_id[b], local[m].astype(np.uint32))
            n_matches += len(m)
    finally:
        db.close()
    summary = ExportSummary(database, folder, len(paths), n, len(pairs), n_matches, names=names)
    if verify and pairs:
        opts = pycolmap.GeometricVerifierOptions()
        if hasattr(opts, "num_threads"):
            opts.num_threads = num_threads
        pycolmap.geometric_verification(str(database), verifier_options=opts)
        db = pycolmap.Database.open(str(database))
        try:
            summary.n_verified_pairs = int(db.num_verified_image_pairs())
        finally:
            db.close()
    return summary


def import_database(database, image_dir=None) -> FeatureSet:
    """Keypoints, descriptors and image names of a COLMAP database as a FEATURES set.

    Images in COLMAP's image-id order get dqm image ids 0..m-1; keypoints are converted to
    OpenCV's pixel convention (x, y; 0.5 subtracted) and keep COLMAP's scale and orientation
    when the database stores them (4 columns) or derives them from the affine shape (6).
    ``image_names`` are the database's names, under ``image_dir`` when given.
    """
    pycolmap = require_pycolmap()
    database = Path(database)
    if not database.is_file():
        raise InputError(f"COLMAP database not found: {database}")
    try:
        db = pycolmap.Database.open(str(database))
    except Exception as exc:  # noqa: BLE001 - a file that is not a database
        raise InputError(f"{database}: not a COLMAP database ({type(exc).__name__})") from None
    try:
        images = sorted(db.read_all_images(), key=lambda im: im.image_id)
        if not images:
            raise InputError(f"{database}: the database holds no images")
        D, K, ids, names = [], [], [], []
        for k, im in enumerate(images):
            if not db.exists_keypoints(im.image_id) or not db.exists_descriptors(im.image_id):
                raise InputError(f"{database}: image {im.name} has no keypoints or no descriptors")
            kp = np.asarray(db.read_keypoints(im.image_id), np.float64)
            desc = np.asarray(db.read_descriptors(im.image_id).data)
            if len(kp) != len(desc):
                raise InputError(f"{database}: image {im.name} has {len(kp)} keypoints but {len(desc)} descriptors")
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
            names.append(str(Path(image_dir) / im.name) if image_dir is not None else im.name)
    finally:
        db.close()
    if len({d.shape[1] for d in D if d.size}) > 1:
        raise InputError(f"{database}: descriptor dimensions differ between images")
    return FeatureSet(descriptors=np.concatenate(D), image_ids=np.concatenate(ids), keypoints=np.concatenate(K),
                      image_names=np.array(names)).validate(str(database))
