"""Loaders for image sequences with ground truth (plain folders, any copy of the same layout).

* Homography sequences (Oxford affine layout): ``img1..imgN`` (.png/.ppm/.pgm/.jpg)
  and ``H1to2p .. H1toNp`` (3x3 text, image-1 pixels -> image-k pixels).
* Landmark sequences (CMU hotel layout): frames ``<name>.seq<K>.png`` and
  ``<name><K+1>.txt`` with one "x y" row per landmark (1-based pixels), the same
  row being the same physical point in every frame.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional

import numpy as np

from ..validation import InputError

IMAGE_SUFFIXES = (".png", ".ppm", ".pgm", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@dataclass(frozen=True)
class HomographySequence:
    """Images of a planar scene; ``homographies[k]`` maps image-0 pixels to image-k pixels."""

    name: str
    image_paths: List[Path]
    homographies: np.ndarray  # (N, 3, 3), homographies[0] = identity

    def homography(self, i: int, j: int) -> np.ndarray:
        """Homography mapping pixels of image ``i`` to image ``j`` (normalised, H[2,2] = 1)."""
        H = self.homographies[j] @ np.linalg.inv(self.homographies[i])
        return H / H[2, 2]


@dataclass(frozen=True)
class LandmarkSequence:
    """Frames with labelled landmarks: ``landmarks[k, r]`` = (x, y) of landmark r in frame k (0-based)."""

    name: str
    image_paths: List[Path]
    landmarks: np.ndarray  # (N, L, 2) float64, 0-based pixel coordinates


def _read_matrix(path: Path) -> np.ndarray:
    try:
        H = np.loadtxt(path, dtype=np.float64)
    except ValueError as exc:
        raise InputError(f"{path}: not a 3x3 text matrix ({exc})") from None
    if H.shape != (3, 3) or not np.isfinite(H).all():
        raise InputError(f"{path}: expected a finite 3x3 matrix, got shape {H.shape}")
    return H / H[2, 2]


def load_homography_sequence(root) -> HomographySequence:
    """Load an Oxford-layout sequence folder; errors name the missing file."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"homography sequence folder not found: {root}")
    images = {}
    for p in root.iterdir():
        m = re.fullmatch(r"img(\d+)", p.stem)
        if m and p.suffix.lower() in IMAGE_SUFFIXES:
            images[int(m.group(1))] = p
    if 1 not in images:
        raise InputError(f"{root}: no img1.<ext> image (expected img1..imgN and H1to2p..H1toNp)")
    n = max(images)
    missing = [k for k in range(1, n + 1) if k not in images]
    if missing:
        raise InputError(f"{root}: images missing for indices {missing}")
    Hs = [np.eye(3)]
    for k in range(2, n + 1):
        hp = root / f"H1to{k}p"
        if not hp.exists():
            raise InputError(f"{root}: homography file {hp.name} is missing")
        Hs.append(_read_matrix(hp))
    return HomographySequence(root.name, [images[k] for k in range(1, n + 1)], np.stack(Hs))


def load_landmark_sequence(root, name: Optional[str] = None) -> LandmarkSequence:
    """Load a CMU-hotel-layout folder (``<name>.seq<K>.png`` + ``<name><K+1>.txt``)."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"landmark sequence folder not found: {root}")
    frames = {}
    for p in root.iterdir():
        m = re.fullmatch(r"(.+)\.seq(\d+)", p.stem)
        if m and p.suffix.lower() in IMAGE_SUFFIXES and (name is None or m.group(1) == name):
            frames[int(m.group(2))] = (m.group(1), p)
    if not frames:
        raise InputError(f"{root}: no frames named <name>.seq<K>.<ext>")
    names = {v[0] for v in frames.values()}
    if len(names) > 1:
        raise InputError(f"{root}: several sequences {sorted(names)}; pass name=")
    seq = names.pop()
    keys = sorted(frames)
    marks = []
    for k in keys:
        tp = root / f"{seq}{k + 1}.txt"
        if not tp.exists():
            raise InputError(f"{root}: landmark file {tp.name} for frame {frames[k][1].name} is missing")
        xy = np.loadtxt(tp, dtype=np.float64, ndmin=2)
        if xy.shape[1] != 2:
            raise InputError(f"{tp}: expected rows 'x y', got {xy.shape[1]} columns")
        marks.append(xy - 1.0)
    counts = {m.shape[0] for m in marks}
    if len(counts) != 1:
        raise InputError(f"{root}: frames have different landmark counts {sorted(counts)}")
    return LandmarkSequence(seq, [frames[k][1] for k in keys], np.stack(marks))
