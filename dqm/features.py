"""SIFT features with OpenCV: detection + description, or description at given points.

Keypoints travel as a float32 (n, 4) array with columns x, y, size, angle
(OpenCV conventions: pixels, 0-based, angle in degrees, -1 = not set).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Tuple

import numpy as np

from .validation import InputError

#: SIFT settings; "paper" is the seed paper's experiment preset
PRESETS: Dict[str, Dict[str, float]] = {
    "opencv": {},
    "paper": {"nOctaveLayers": 6, "contrastThreshold": 0.10, "edgeThreshold": 15, "sigma": 1.0},
}


@dataclass(frozen=True)
class ImageFeatures:
    """Keypoints (n, 4: x, y, size, angle) and uint8 SIFT descriptors (n, 128) of one image."""

    keypoints: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return len(self.descriptors)


def read_gray(path) -> np.ndarray:
    """Read an image file as 8-bit grayscale; clear error if it cannot be read."""
    import cv2

    p = Path(path)
    if not p.exists():
        raise InputError(f"image not found: {p}")
    img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
    if img is None or img.size == 0:
        raise InputError(f"cannot read image (not an image or empty): {p}")
    return img


def _as_gray(image) -> np.ndarray:
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


def create_sift(preset: str = "opencv", max_features: int = 0):
    import cv2

    if preset not in PRESETS:
        raise InputError(f"unknown SIFT preset {preset!r}; choose from {sorted(PRESETS)}")
    if max_features < 0:
        raise InputError(f"max_features must be >= 0 (0 = no limit), got {max_features}")
    return cv2.SIFT_create(nfeatures=int(max_features), **PRESETS[preset])


def _kp_array(kps) -> np.ndarray:
    return np.array([(k.pt[0], k.pt[1], k.size, k.angle) for k in kps], dtype=np.float32).reshape(-1, 4)


def extract(image, preset: str = "opencv", max_features: int = 0) -> ImageFeatures:
    """Detect and describe SIFT features of an image (path or array)."""
    img = _as_gray(image)
    kps, desc = create_sift(preset, max_features).detectAndCompute(img, None)
    if desc is None:
        desc = np.zeros((0, 128), np.float32)
    return ImageFeatures(_kp_array(kps), np.clip(np.round(desc), 0, 255).astype(np.uint8))


def describe_at(image, points, size: float = 24.0, angle: float = 0.0,
                preset: str = "opencv") -> ImageFeatures:
    """SIFT descriptors at given points (x, y; 0-based pixels), all of one size and angle.

    Points whose patch OpenCV drops (too close to the border) raise an error
    naming them, so descriptors always line up with the points given.
    """
    import cv2

    img = _as_gray(image)
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise InputError(f"points must be (n, 2) x, y, got shape {pts.shape}")
    kps = [cv2.KeyPoint(float(x), float(y), float(size), float(angle)) for x, y in pts]
    out_kps, desc = create_sift(preset).compute(img, kps)
    if desc is None or len(out_kps) != len(kps):
        kept = {(round(k.pt[0], 3), round(k.pt[1], 3)) for k in (out_kps or [])}
        lost = [i for i, (x, y) in enumerate(pts) if (round(x, 3), round(y, 3)) not in kept]
        raise InputError(f"OpenCV could not describe points {lost[:10]} (outside the image?)")
    return ImageFeatures(_kp_array(out_kps), np.clip(np.round(desc), 0, 255).astype(np.uint8))


def landmark_descriptors(seq, size: float = 24.0) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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


def extract_many(images, preset: str = "opencv", max_features: int = 0,
                 progress=None) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Extract from a list of images: ``(descriptors, image_ids, keypoints)`` stacked."""
    descs, ids, kps = [], [], []
    images = list(images)
    for k, im in enumerate(images):
        f = extract(im, preset, max_features)
        descs.append(f.descriptors)
        kps.append(f.keypoints)
        ids.append(np.full(len(f), k))
        if progress is not None:
            progress(k + 1, len(images))
    if not descs:
        return np.zeros((0, 128), np.uint8), np.zeros(0, np.int64), np.zeros((0, 4), np.float32)
    return np.vstack(descs), np.concatenate(ids).astype(np.int64), np.vstack(kps)

