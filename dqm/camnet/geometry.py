"""Pinhole cameras on a ground plane, planar textures, and target localization from a box.

Conventions
-----------
* World frame: metres, ``x`` east, ``y`` north, ``z`` up; the ground is ``z = 0``.
* Camera frame (OpenCV): ``x`` right, ``y`` down, ``z`` forward (optical axis).
* A camera's pose is its centre ``position`` (3,), its ``yaw`` (heading in the
  ground plane, radians, 0 = looking along +x, counter-clockwise positive) and
  its ``pitch`` (radians, positive = looking up). Ground robots with forward
  cameras have pitch 0, which the box-height range model assumes.
* Pixels: 0-based, ``(u, v)`` = (column, row); the principal point of a
  ``width x height`` image is ``((width - 1) / 2, (height - 1) / 2)``.
* Bearing: angle of a point to the right of the optical axis, radians,
  ``atan((u - cx) / fx)``; positive = to the right (clockwise seen from above).

Localization (the seed paper's rule, :func:`localize_from_box`): a detected
object's bounding box of height ``h`` pixels lies at depth ``k / h`` where
``k`` (pixel metres) is calibrated once from an object of known size at a
known distance (:func:`calibrate_range`; ideally ``k = fy * object height``);
the box centre gives the bearing; with the camera's known pose the two give
a position in the world.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np

from ..validation import InputError


def _finite(value, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise InputError(f"{name} must be finite, got {value!r}")
    return v


def _vec(value, n: int, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (n,) or not np.isfinite(arr).all():
        raise InputError(f"{name} must be {n} finite numbers, got {value!r}")
    return arr


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics: focal lengths and principal point in pixels, image size."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def from_fov(cls, hfov_deg: float = 62.0, vfov_deg: float = 48.0, width: int = 640,
                 height: int = 480) -> "Intrinsics":
        """Intrinsics of a ``width x height`` camera with the given full fields of view (degrees)."""
        for name, fov in (("hfov_deg", hfov_deg), ("vfov_deg", vfov_deg)):
            f = _finite(fov, name)
            if not 0 < f < 179:
                raise InputError(f"{name} must lie in (0, 179) degrees, got {fov!r}")
        if int(width) != width or int(height) != height or width < 8 or height < 8:
            raise InputError(f"image size must be integers >= 8, got {width} x {height}")
        fx = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        fy = (height / 2.0) / math.tan(math.radians(vfov_deg) / 2.0)
        return cls(fx, fy, (width - 1) / 2.0, (height - 1) / 2.0, int(width), int(height))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def hfov(self) -> float:
        """Horizontal full field of view, radians."""
        return 2.0 * math.atan((self.width / 2.0) / self.fx)


def rotation_world_to_camera(yaw: float, pitch: float = 0.0) -> np.ndarray:
    """3x3 rotation R with rows (right, down, forward) in world coordinates: ``X_cam = R (X - C)``."""
    yaw = _finite(yaw, "yaw")
    pitch = _finite(pitch, "pitch")
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    forward = np.array([cp * cy, cp * sy, sp])
    right = np.array([sy, -cy, 0.0])
    down = np.cross(forward, right)
    return np.stack([right, down, forward])


@dataclass(frozen=True)
class Camera:
    """A calibrated camera at a known pose (see module doc for the conventions)."""

    name: str
    position: np.ndarray  # (3,) world metres
    yaw: float
    pitch: float
    intrinsics: Intrinsics

    def __post_init__(self):
        object.__setattr__(self, "position", _vec(self.position, 3, "camera position"))
        object.__setattr__(self, "yaw", _finite(self.yaw, "camera yaw"))
        object.__setattr__(self, "pitch", _finite(self.pitch, "camera pitch"))
        if abs(self.pitch) >= math.pi / 2:
            raise InputError(f"camera pitch must lie in (-90, 90) degrees, got {math.degrees(self.pitch):.1f}")

    @property
    def R(self) -> np.ndarray:
        return rotation_world_to_camera(self.yaw, self.pitch)

    def to_camera(self, points_world) -> np.ndarray:
        """World points (n, 3) in the camera frame (n, 3)."""
        P = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        return (P - self.position) @ self.R.T

    def project(self, points_world) -> Tuple[np.ndarray, np.ndarray]:
        """Pixels (n, 2) of world points and their depth (n,); points with depth <= 0 get NaN pixels."""
        Xc = self.to_camera(points_world)
        z = Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.intrinsics.fx * Xc[:, 0] / z + self.intrinsics.cx
            v = self.intrinsics.fy * Xc[:, 1] / z + self.intrinsics.cy
        uv = np.stack([u, v], 1)
        uv[z <= 0] = np.nan
        return uv, z

    def range_bearing(self, point_world) -> Tuple[float, float, float]:
        """(depth along the optical axis, ground-plane distance, bearing) of a world point."""
        Xc = self.to_camera(point_world)[0]
        p = _vec(point_world, 3, "point")
        dist = float(np.hypot(*(p[:2] - self.position[:2])))
        return float(Xc[2]), dist, float(math.atan2(Xc[0], Xc[2]))


def plane_homography(camera: Camera, origin, axis_u, axis_v) -> np.ndarray:
    """Homography from texture pixels (s, t) of a plane to image pixels.

    The plane point of texture pixel (s, t) is ``origin + s * axis_u + t * axis_v``
    (3-vectors, metres per texture pixel along each axis). Valid for the part of
    the plane in front of the camera.
    """
    o = _vec(origin, 3, "origin")
    U = _vec(axis_u, 3, "axis_u")
    V = _vec(axis_v, 3, "axis_v")
    if np.linalg.norm(np.cross(U, V)) == 0:
        raise InputError("plane axes must not be parallel")
    M = np.stack([U, V, o - camera.position], 1)
    H = camera.intrinsics.K @ camera.R @ M
    return H / H[2, 2] if abs(H[2, 2]) > 1e-12 else H


def clip_near(points_cam: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a convex polygon (camera frame, (n, 3)) to depth >= near."""
    P = np.asarray(points_cam, dtype=np.float64)
    out = []
    n = len(P)
    for k in range(n):
        a, b = P[k], P[(k + 1) % n]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            t = (near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out).reshape(-1, 3)


def apply_homography(H, points) -> np.ndarray:
    """Map (n, 2) points by a 3x3 homography (points at infinity become inf)."""
    H = np.asarray(H, dtype=np.float64)
    if H.shape != (3, 3) or not np.isfinite(H).all():
        raise InputError(f"homography must be a finite 3x3 matrix, got shape {H.shape}")
    P = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    q = np.c_[P, np.ones(len(P))] @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return q[:, :2] / q[:, 2:3]


def projected_quad(H, width: float, height: float) -> Optional[np.ndarray]:
    """Corners (4, 2) of a ``width x height`` reference image mapped by H, or None if degenerate.

    Degenerate: a corner maps to infinity or behind the camera (its homogeneous
    coordinate changes sign), or the quad is not convex (a homography estimated
    from wrong matches folds the rectangle).
    """
    H = np.asarray(H, dtype=np.float64)
    if H.shape != (3, 3) or not np.isfinite(H).all():
        return None
    c = np.array([[0, 0], [width, 0], [width, height], [0, height]], np.float64)
    w = np.c_[c, np.ones(4)] @ H.T
    if not (np.all(w[:, 2] > 0) or np.all(w[:, 2] < 0)) or np.any(np.abs(w[:, 2]) < 1e-12):
        return None
    q = w[:, :2] / w[:, 2:3]
    e = np.roll(q, -1, 0) - q
    cross = e[:, 0] * np.roll(e, -1, 0)[:, 1] - e[:, 1] * np.roll(e, -1, 0)[:, 0]
    if not (np.all(cross > 0) or np.all(cross < 0)):
        return None
    return q


def bounding_box(points) -> Tuple[float, float, float, float]:
    """Axis-aligned box (x0, y0, x1, y1) of (n, 2) points."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(P) == 0 or not np.isfinite(P).all():
        raise InputError("bounding box needs finite points")
    return float(P[:, 0].min()), float(P[:, 1].min()), float(P[:, 0].max()), float(P[:, 1].max())


def calibrate_range(box_height_px: float, distance_m: float) -> float:
    """Range constant ``k`` (pixel metres) from one observation of the object at a known depth.

    A box ``h`` pixels high then lies at depth ``k / h`` (pinhole: ``h = fy * H / depth``,
    so ``k = fy * H`` for an object ``H`` metres high).
    """
    h = _finite(box_height_px, "box_height_px")
    d = _finite(distance_m, "distance_m")
    if h <= 0 or d <= 0:
        raise InputError(f"calibration needs a positive box height and distance, got {h} px at {d} m")
    return h * d


def range_bearing_from_box(box, intrinsics: Intrinsics, range_constant: float) -> Tuple[float, float]:
    """(depth along the optical axis in metres, bearing in radians) of a box (x0, y0, x1, y1)."""
    x0, y0, x1, y1 = (_finite(v, "box coordinate") for v in box)
    k = _finite(range_constant, "range_constant")
    if k <= 0:
        raise InputError(f"range_constant must be positive, got {k}")
    h = y1 - y0
    if h <= 0:
        raise InputError(f"box height must be positive, got {h}")
    depth = k / h
    bearing = math.atan(((x0 + x1) / 2.0 - intrinsics.cx) / intrinsics.fx)
    return depth, bearing


def camera_to_world_ground(camera: Camera, depth: float, bearing: float) -> np.ndarray:
    """Ground-plane world position (2,) of a point at ``depth`` and ``bearing`` from a level camera."""
    lateral = depth * math.tan(bearing)
    f = np.array([math.cos(camera.yaw), math.sin(camera.yaw)])
    r = np.array([math.sin(camera.yaw), -math.cos(camera.yaw)])
    return camera.position[:2] + depth * f + lateral * r


def localize_from_box(box, camera: Camera, range_constant: float, behind: float = 0.0) -> np.ndarray:
    """World ground position (2,) of an object from its box in ``camera``'s image.

    ``behind``: distance (metres) from the seen face to the point sought
    (e.g. half the depth of a box-shaped target for its centre), added along
    the line of sight.
    """
    depth, bearing = range_bearing_from_box(box, camera.intrinsics, range_constant)
    p = camera_to_world_ground(camera, depth, bearing)
    b = _finite(behind, "behind")
    if b:
        ray = p - camera.position[:2]
        n = np.linalg.norm(ray)
        if n > 0:
            p = p + b * ray / n
    return p


def estimate_homography(src, dst, threshold: float = 10.0, min_inliers: int = 4,
                        seed: int = 0) -> Tuple[Optional[np.ndarray], np.ndarray]:
    """RANSAC homography mapping ``src`` (n, 2) to ``dst`` (n, 2) points.

    Returns ``(H or None, inlier mask)``; None when there are fewer than 4
    correspondences, OpenCV finds no model, or fewer than ``min_inliers`` agree
    within ``threshold`` pixels. OpenCV's RNG is seeded for repeatable results.
    """
    import cv2

    s = np.asarray(src, dtype=np.float64).reshape(-1, 2)
    d = np.asarray(dst, dtype=np.float64).reshape(-1, 2)
    if len(s) != len(d):
        raise InputError(f"src and dst differ in length ({len(s)} vs {len(d)})")
    if not (np.isfinite(s).all() and np.isfinite(d).all()):
        raise InputError("homography points must be finite")
    thr = _finite(threshold, "threshold")
    if thr <= 0:
        raise InputError(f"RANSAC threshold must be positive, got {thr}")
    mask = np.zeros(len(s), bool)
    if len(s) < 4:
        return None, mask
    cv2.setRNGSeed(int(seed))
    H, m = cv2.findHomography(s.astype(np.float32), d.astype(np.float32), cv2.RANSAC, thr)
    if H is None or m is None:
        return None, mask
    mask = m.ravel().astype(bool)
    if mask.sum() < max(4, int(min_inliers)) or not np.isfinite(H).all():
        return None, mask
    return H / H[2, 2], mask


def fov_wedge(camera: Camera, length: float) -> np.ndarray:
    """Ground-plane polygon (3, 2) of a camera's horizontal field of view, for plots."""
    h = camera.intrinsics.hfov / 2.0
    p = camera.position[:2]
    a1, a2 = camera.yaw + h, camera.yaw - h
    return np.array([p, p + length * np.array([math.cos(a1), math.sin(a1)]),
                     p + length * np.array([math.cos(a2), math.sin(a2)])])


def look_at_yaw(position: Sequence[float], target: Sequence[float]) -> float:
    """Yaw (radians) of a camera at ``position`` looking at ``target`` (ground plane)."""
    p = _vec(position, len(position), "position")[:2]
    t = _vec(target, len(target), "target")[:2]
    d = t - p
    if not np.any(d):
        raise InputError("look_at_yaw: position and target coincide")
    return float(math.atan2(d[1], d[0]))
