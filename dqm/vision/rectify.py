"""Rectified descriptors: a planar pair's features described again in one frame, for guided growth.

SIFT describes each feature in its own image, normalised for scale and rotation but not for the
perspective that tilts a plane between two views: at a wide baseline (graf's 40-60 degrees) the
descriptors of one point drift apart, and guided growth's ratio test and sigma bound
(:mod:`dqm.vision.guided`) turn true links away. Where a verified pair is planar or panoramic its
homography H maps one image onto the other, so both features of a candidate link can be described
in **one frame**: the image in which the plane appears smaller is warped up by H into the other's
frame (so no image is ever down-sampled), its keypoints move there with their scale taken through
H's local Jacobian, and every feature of the pair is described **upright** (angle 0) at its own
position and scale: the frame already aligns the two views, so the orientation that SIFT
estimates, which the tilt perturbs by 5-22 degrees on graf, is not needed. A true match then
compares like with like (the median distance of graf's verified matches of image 1 with images 2, 3
and 4: 89, 165, 219 -> 59, 90, 126, of a length of 512), while a chance candidate, whose patch shows
other content, stays far.

Descriptors are OpenCV's SIFT computed at the stored keypoints (``size``; the pyramid level is
recovered from it, :func:`sift_octave`, so a keypoint described again in its own image at its own
angle gives its original descriptor), stored as RootSIFT (:func:`dqm.vision.features.root_sift`),
whatever descriptors were clustered: both sides of a comparison are made here. Keypoints at one
location with several orientations have one upright descriptor; :mod:`dqm.vision.guided` keeps
one of them for the comparison and pairs the others afterwards.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Optional, Sequence, Tuple

import numpy as np

#: OpenCV's SIFT: layers per octave and the base sigma (its first octave is -1: the image up-sampled)
SIFT_LAYERS = 3
SIFT_SIGMA = 1.6
#: the length of the descriptors made here (RootSIFT: unit length, x 512 as uint8)
DESCRIPTOR_NORM = 512.0


def sift_octave(size) -> np.ndarray:
    """OpenCV's packed ``KeyPoint.octave`` (octave, layer, sub-layer offset) of SIFT keypoints of diameter
    ``size``: OpenCV makes ``size = 1.6 * 2 ** (octave + 1 + (layer + xi) / 3)`` (first octave -1, layers 1-3,
    xi in [-0.5, 0.5]) and its ``compute`` describes a keypoint at the pyramid level the word names (xi does
    not change the descriptor). Sizes below the first level's are described there."""
    t = np.maximum(SIFT_LAYERS * np.log2(np.maximum(np.asarray(size, np.float64), 1e-6) / SIFT_SIGMA), 0.5)
    k = np.floor(t + 0.5).astype(np.int64)
    octave = (k - 1) // SIFT_LAYERS - 1
    layer = k - SIFT_LAYERS * (octave + 1)
    xi = np.clip(t - k, -0.5, 0.5)
    return (octave & 255) | (layer << 8) | (np.round((xi + 0.5) * 255).astype(np.int64) << 16)


def upright_descriptors(gray: np.ndarray, xy: np.ndarray, size: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """RootSIFT descriptors (uint8) at points ``xy`` (n, 2) of diameters ``size``, angle 0, in ``gray``; and
    which of them OpenCV described (the others are zero rows)."""
    import cv2

    from .features import _finish

    n = len(xy)
    out = np.zeros((n, 128), np.uint8)
    done = np.zeros(n, bool)
    if n == 0:
        return out, done
    words = sift_octave(size)
    kps = [cv2.KeyPoint(float(x), float(y), float(s), 0.0, 0.0, int(w))
           for (x, y), s, w in zip(np.asarray(xy, np.float64), np.asarray(size, np.float64), words)]
    got, desc = cv2.SIFT_create().compute(gray, kps)
    if desc is None:
        return out, done
    if len(got) == n and all(a.pt == b.pt and a.size == b.size for a, b in zip(got, kps)):
        rows = np.arange(n)
    else:  # OpenCV dropped keypoints: find each one it kept
        where: dict = {}
        for k, kp in enumerate(kps):
            where.setdefault((kp.pt, kp.size), []).append(k)
        found = []
        for kp in got:
            left = where.get((kp.pt, kp.size))
            found.append(left.pop(0) if left else -1)
        rows = np.array(found, np.int64)
    ok = rows >= 0
    out[rows[ok]] = _finish(desc[ok], "rootsift")  # as the image presets store them
    done[rows[ok]] = True
    return out, done


def _transfer(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    p = np.c_[xy, np.ones(len(xy))] @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[:, :2] / p[:, 2:3]


def area_scale(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """|det| of the Jacobian of the homography H at points ``xy``: how much H scales areas there."""
    x = np.c_[xy, np.ones(len(xy))]
    w = x @ H[2]
    # d(Hx / w) / dx has determinant det(H) / w^3 for a homography
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.abs(np.linalg.det(H) / w ** 3)


class Rectifier:
    """Upright descriptors of a planar pair's features in one frame (module docstring).

    ``images``: per image id, a path or an array (what :func:`dqm.vision.features.as_gray` reads); ``cached``:
    decoded images, and images' upright descriptors, kept at once (the last used); ``sigma_scale``: what takes
    a distance between the clustered descriptors to one between these (guided growth's sigma bound).
    Thread-safe: guided growth calls :meth:`pair` from several threads."""

    def __init__(self, images: Sequence, cached: int = 8, sigma_scale: float = 1.0):
        self.images = list(images)
        self.sigma_scale = float(sigma_scale)
        self.cached = max(2, int(cached))
        self._grays: "OrderedDict[int, np.ndarray]" = OrderedDict()
        self._own: "OrderedDict[int, tuple]" = OrderedDict()
        self._lock = threading.Lock()
        self._image_locks: dict = {}
        self.rectified = 0  # pairs compared rectified
        self.skipped = ""  # why a pair was not (the first reason met)

    def _kept(self, store: "OrderedDict", k: int, make):
        """``store[k]``, made by ``make()`` once while it stays among the last ``cached`` used (one maker per key
        at a time)."""
        with self._lock:
            if k in store:
                store.move_to_end(k)
                return store[k]
            lock = self._image_locks.setdefault((id(store), k), threading.Lock())
        with lock:
            with self._lock:
                if k in store:
                    return store[k]
            value = make()
            with self._lock:
                store[k] = value
                while len(store) > self.cached:
                    store.popitem(last=False)
        return value

    def gray(self, k: int) -> np.ndarray:
        """Image ``k`` in grey."""
        from .features import as_gray

        return self._kept(self._grays, k, lambda: as_gray(self.images[k]))

    def own(self, k: int, features: np.ndarray, kp: np.ndarray, image_ids: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Upright descriptors of image ``k``'s ``features`` in their own image: every feature of image k
        (``image_ids == k``) is described at once, and kept as the images are."""
        def describe():
            every = np.flatnonzero(image_ids == k)
            return (every, *upright_descriptors(self.gray(k), kp[every, :2], kp[every, 2]))

        have = self._kept(self._own, k, describe)
        pos = np.minimum(np.searchsorted(have[0], features), max(len(have[0]) - 1, 0))
        if len(features) and not (have[0][pos] == features).all():
            raise ValueError(f"features of another image than {k} asked for")
        return have[1][pos], have[2][pos]

    def warped(self, src: int, dst: int, H: np.ndarray, features: np.ndarray,
               kp: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Upright descriptors of image ``src``'s ``features`` once ``src`` is warped into image ``dst``'s frame by
        H (src pixels to dst pixels); features that land outside the frame are not described."""
        import cv2

        target = self.gray(dst)
        h, w = target.shape[:2]
        # dst(x) = src(H^-1 x)
        image = cv2.warpPerspective(self.gray(src), H, (w, h), flags=cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        xy = kp[features, :2].astype(np.float64)
        moved = _transfer(H, xy)
        size = kp[features, 2] * np.sqrt(area_scale(H, xy))
        inside = np.isfinite(moved).all(axis=1) & np.isfinite(size)
        inside &= (moved[:, 0] >= 0) & (moved[:, 1] >= 0) & (moved[:, 0] <= w - 1) & (moved[:, 1] <= h - 1)
        D = np.zeros((len(features), 128), np.uint8)
        ok = np.zeros(len(features), bool)
        if inside.any():
            D[inside], ok[inside] = upright_descriptors(image, moved[inside], size[inside])
        return D, ok

    def pair(self, a: int, b: int, H: np.ndarray, rows: np.ndarray, cols: np.ndarray, kp: np.ndarray,
             image_ids: np.ndarray) -> Optional[Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """Upright descriptors of image a's ``rows`` and image b's ``cols`` in one frame (H maps a's pixels to
        b's): a warped up into b's frame where H enlarges areas around a's centre, else b into a's. Returns
        (descriptors of rows, described, descriptors of cols, described), or None where an image cannot serve
        (it does not decode, or the features' keypoints lie outside it: not the image they came from); then
        :attr:`skipped` says why and the pair is compared with the clustered descriptors."""
        from ..validation import InputError

        try:
            ga, gb = self.gray(a), self.gray(b)
        except (InputError, OSError, ValueError) as exc:
            return self._skip(str(exc))
        for k, g, f in ((a, ga, rows), (b, gb, cols)):
            xy = kp[f, :2]  # within a pixel of the image (COLMAP's keypoints put pixel centres at +0.5)
            if len(xy) and ((xy < -1).any() or (xy[:, 0] > g.shape[1] + 1).any() or (xy[:, 1] > g.shape[0] + 1).any()):
                return self._skip(f"keypoints of image {k} lie outside its {g.shape[1]} x {g.shape[0]} pixels")
        h, w = ga.shape[:2]
        if area_scale(H, np.array([[w / 2.0, h / 2.0]]))[0] > 1.0:  # b shows a's middle larger: warp a up
            Da, oka = self.warped(a, b, H, rows, kp)
            Db, okb = self.own(b, cols, kp, image_ids)
        else:
            Da, oka = self.own(a, rows, kp, image_ids)
            Db, okb = self.warped(b, a, np.linalg.inv(H), cols, kp)
        with self._lock:
            self.rectified += 1
        return Da, oka, Db, okb

    def _skip(self, why: str) -> None:
        with self._lock:
            self.skipped = self.skipped or why
        return None


def rectifier_for(images: Optional[Sequence], keypoints, descriptors,
                  image_ids: Optional[np.ndarray] = None) -> Tuple[Optional[Rectifier], str]:
    """A :class:`Rectifier` over ``images`` where they can serve (keypoints with a size column, every image a
    file or an array), else None and why not. Its ``sigma_scale`` is :data:`DESCRIPTOR_NORM` over the
    clustered ``descriptors``' median length (1 for SIFT and RootSIFT as dqm and COLMAP store them), so that
    guided growth's sigma bound means the same for both."""
    from pathlib import Path

    from ..validation import InputError

    if images is None:
        return None, "no images given"
    if image_ids is not None and len(image_ids) and len(images) <= int(np.max(image_ids)):
        raise InputError(f"guided growth: images must give one image per image id (0..{int(np.max(image_ids))}); "
                         f"got {len(images)}")
    kp = np.asarray(keypoints)
    if kp.ndim != 2 or kp.shape[1] < 3:
        return None, "the keypoints have no size"
    missing = [str(p) for p in images if not isinstance(p, np.ndarray) and not Path(str(p)).is_file()]
    if missing:
        return None, f"image {missing[0]} not found"
    X = np.asarray(descriptors)
    sample = X[:: max(1, len(X) // 4096)].astype(np.float64)
    norm = float(np.median(np.linalg.norm(sample, axis=1))) if len(sample) else 0.0
    if not norm > 0:
        return None, "the descriptors are zero"
    return Rectifier(images, sigma_scale=DESCRIPTOR_NORM / norm), ""


__all__ = ["DESCRIPTOR_NORM", "Rectifier", "area_scale", "rectifier_for", "sift_octave", "upright_descriptors"]
