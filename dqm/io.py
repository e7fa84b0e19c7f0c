"""The plain file formats between dqm's stages (numpy ``.npz``, no pickles).

FEATURES file (input of ``dqm match``)::

    descriptors   (n, d)  uint8 or float     one row per feature
    image_ids     (n,)    int                image of every feature
    keypoints     (n, 4)  float32, optional  x, y, size, angle (OpenCV, 0-based px)
    image_names   (m,)    str, optional      name of image id k at row k (ids 0..m-1)
    point_ids     (n,)    int, optional      ground-truth physical point (-1 unknown)

CLUSTERS file (output of ``dqm match``): every FEATURES field that was present,
plus::

    labels           (n,) int64    cluster of every feature (0..k-1)
    sigma            (n,) float64  distinctiveness
    density          (n,) float64
    parent           (n,) int64    tree parent within reach, -1 if none
    parent_distance  (n,) float64  inf if no parent
    params           ()   str      JSON: rho, ratio_density, kernel, parent mode, dqm version

TRACKS CSV (``dqm match --tracks-csv``): one row per feature of every cluster
with at least two features, sorted by track then image; columns ``track``
(0, 1, ... in order of cluster label), ``label`` (the CLUSTERS label),
``image_id``, ``image`` (name, if known), ``feature`` (row in the FEATURES
arrays), ``x``, ``y``, ``size``, ``angle`` (empty if no keypoints).
"""
from __future__ import annotations

import csv
import json
import os
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from .validation import InputError, check_descriptors, check_image_ids


@dataclass
class FeatureSet:
    descriptors: np.ndarray
    image_ids: np.ndarray
    keypoints: Optional[np.ndarray] = None
    image_names: Optional[np.ndarray] = None
    point_ids: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return len(self.descriptors)

    def validate(self, source: str = "features") -> "FeatureSet":
        check_descriptors(self.descriptors, f"{source}: descriptors")
        n = len(self.descriptors)
        check_image_ids(self.image_ids, n, f"{source}: image_ids")
        if self.keypoints is not None:
            kp = np.asarray(self.keypoints)
            if kp.ndim != 2 or kp.shape[0] != n or kp.shape[1] < 2:
                raise InputError(f"{source}: keypoints must be (n, 2..4) with n = {n}, got {kp.shape}")
        if self.point_ids is not None and np.asarray(self.point_ids).shape != (n,):
            raise InputError(f"{source}: point_ids must have one entry per feature ({n})")
        return self


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _atomic_savez(path: Path, arrays: dict) -> None:
    """Write an npz next to ``path`` and rename it in place: no half-written file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp.npz", dir=path.parent)
    os.close(fd)
    try:
        np.savez_compressed(tmp, **arrays)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; a result file follows the umask like any other
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _feature_arrays(fs: FeatureSet) -> dict:
    """The FEATURES arrays of a feature set (optional ones only when present)."""
    arrays = {"descriptors": fs.descriptors, "image_ids": np.asarray(fs.image_ids, np.int64)}
    for name in ("keypoints", "image_names", "point_ids"):
        v = getattr(fs, name)
        if v is not None:
            arrays[name] = np.asarray(v)
    return arrays


def save_features(path, fs: FeatureSet) -> None:
    _atomic_savez(Path(path), _feature_arrays(fs))


def load_features(path) -> FeatureSet:
    p = Path(path)
    if not p.exists():
        raise InputError(f"features file not found: {p}")
    if not zipfile.is_zipfile(p):
        raise InputError(f"{p}: not an .npz features file (an .npz is a zip archive of numpy arrays; "
                         "see docs/formats.md)")
    try:
        z = np.load(p, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable file
        raise InputError(f"{p}: not a readable .npz features file ({type(exc).__name__})") from None
    with z:
        for key in ("descriptors", "image_ids"):
            if key not in z.files:
                raise InputError(f"{p}: missing array {key!r} (has {sorted(z.files)})")
        fs = FeatureSet(
            descriptors=z["descriptors"], image_ids=z["image_ids"],
            keypoints=z["keypoints"] if "keypoints" in z.files else None,
            image_names=z["image_names"] if "image_names" in z.files else None,
            point_ids=z["point_ids"] if "point_ids" in z.files else None,
        )
    return fs.validate(str(p))


def absolute_if_exists(name: str) -> str:
    """The absolute path of an existing file, else the name as given."""
    p = Path(str(name))
    return str(p.resolve()) if p.is_file() else str(name)


def save_clusters(path, fs: FeatureSet, result, extra_params: Optional[dict] = None) -> None:
    from . import __version__

    params = {"rho": result.rho, "ratio_density": result.ratio_density, "kernel": result.kernel,
              "parent": result.parent_mode, "dqm_version": __version__}
    if "n_neighbors" in result.stats:  # the approximate mode
        params.update(approximate=True, n_neighbors=int(result.stats["n_neighbors"]))
    params.update(extra_params or {})
    arrays = _feature_arrays(fs)
    if "image_names" in arrays:  # absolute, so the file can be used from any folder
        arrays["image_names"] = np.array([absolute_if_exists(n) for n in arrays["image_names"].tolist()])
    arrays.update(
        labels=result.labels, sigma=result.sigma, density=result.density, parent=result.parent,
        parent_distance=result.parent_distance, params=np.array(json.dumps(params)),
    )
    _atomic_savez(Path(path), arrays)


def load_clusters(path) -> dict:
    p = Path(path)
    if not p.exists():
        raise InputError(f"clusters file not found: {p}")
    with np.load(p, allow_pickle=False) as z:
        if "labels" not in z.files:
            raise InputError(f"{p}: not a clusters file (no 'labels' array)")
        out = {k: z[k] for k in z.files}
    out["params"] = json.loads(str(out["params"])) if "params" in out else {}
    return out


def save_tracks_csv(path, labels, image_ids, keypoints=None, image_names=None, min_size: int = 2) -> int:
    """Write the clusters with ``min_size`` or more features as a TRACKS CSV; returns the track count."""
    labels = np.asarray(labels)
    image_ids = np.asarray(image_ids)
    if labels.shape != image_ids.shape or labels.ndim != 1:
        raise InputError("labels and image_ids must be 1-D arrays of equal length")
    if min_size < 1:
        raise InputError(f"min_size must be >= 1, got {min_size}")
    kp = None if keypoints is None else np.asarray(keypoints, dtype=np.float64)
    sizes = np.bincount(labels) if len(labels) else np.zeros(0, np.int64)
    keep = np.flatnonzero(sizes[labels] >= min_size) if len(labels) else np.zeros(0, np.int64)
    order = keep[np.lexsort((keep, image_ids[keep], labels[keep]))]
    track_of = {lab: k for k, lab in enumerate(np.unique(labels[order]).tolist())}
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".tmp")
    with open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["track", "label", "image_id", "image", "feature", "x", "y", "size", "angle"])
        for f in order.tolist():
            img = int(image_ids[f])
            name = str(image_names[img]) if image_names is not None and 0 <= img < len(image_names) else ""
            geo = [""] * 4
            if kp is not None:
                geo = [f"{v:.3f}" for v in kp[f, :4]] + [""] * (4 - min(4, kp.shape[1]))
            w.writerow([track_of[int(labels[f])], int(labels[f]), img, name, f, *geo[:4]])
    os.replace(tmp, p)
    return len(track_of)
