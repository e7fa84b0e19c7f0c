"""A generated 3-D multi-view scene with exact ground truth, for structure-from-motion tests
(a test helper: tests import it as ``from generators.scenes3d import generate_scene3d``).

World (metres; x right, y down, z forward, as OpenCV cameras): ``n_planes``
textured rectangles. The farthest is a large background plane about 10 m away,
sized so that it fills every view; the others are smaller foreground planes
stratified in depth between 4 and 8 m, spread across the view so that they
overlap each other and the background, each tilted by up to ~30 degrees and
carrying its own :func:`dqm.vision.scenes.texture`. Depths differ by metres,
so neighbouring views show tens of pixels of parallax: the scene is not one
plane, and two-view geometry and triangulation are well posed.

Cameras: pinhole, ``K = [[f, 0, (w-1)/2], [0, f, (h-1)/2], [0, 0, 1]]``
(``f = 0.9 * width`` unless given; no distortion), on a horizontal arc of
radius ~6.5 m around the scene centre, ~0.35-0.5 m apart (the whole arc is
capped at ~70 degrees), each looking at the centre with a little seeded jitter
in height and aim. ``R[k]``, ``t[k]`` map world to camera: ``x_cam = R x + t``.

Rendering: for each view the planes are drawn far to near (painter's order),
each through ``cv2.warpPerspective`` with its exact plane-to-image homography
``K [R du | R dv | R o + t]`` (``o`` the world point of texture pixel (0, 0),
``du``/``dv`` the world steps of one texture column / row). The mask of a
plane is the set of pixels whose ray hits it in front of the camera, inside
its rectangle, before any other plane (exact ray casting), so occlusion is
exact and planes crossing the camera plane are clipped correctly. Mild seeded
sensor noise is added; output is uint8 grayscale. Pixel coordinates are
0-based with pixel centres at integers, as OpenCV keypoints.

Truth: :meth:`Scene3D.backproject` casts the same rays the renderer uses,
:meth:`Scene3D.project` projects world points with a visibility (occlusion)
test, and :meth:`Scene3D.correspondence` maps pixels of one view to another.
Deterministic for a seed.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np

from dqm.validation import InputError
from dqm.vision.scenes import texture

#: sensor noise (grey levels) and texture oversampling (texture pixels per image pixel at the plane's depth)
_NOISE, _OVERSAMPLE, _MAX_TEXTURE = 1.0, 1.3, 2048


@dataclass(frozen=True)
class Plane:
    """A textured rectangle: texture pixel (s, r) sits at world point ``origin + s du + r dv``."""

    origin: np.ndarray
    du: np.ndarray
    dv: np.ndarray
    texture: np.ndarray  # uint8 (rows, cols)

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.du, self.dv)
        return n / np.linalg.norm(n)

    @property
    def centre(self) -> np.ndarray:
        h, w = self.texture.shape
        return self.origin + (w - 1) / 2 * self.du + (h - 1) / 2 * self.dv


@dataclass(frozen=True)
class Scene3D:
    """Views of textured planes; ``x_cam = R[k] @ x_world + t[k]``, pixels ``~ K x_cam``."""

    images: List[np.ndarray]
    K: np.ndarray  # (3, 3)
    R: np.ndarray  # (n, 3, 3) world-to-camera rotations
    t: np.ndarray  # (n, 3)
    planes: List[Plane]

    def __len__(self) -> int:
        return len(self.images)

    @property
    def size(self) -> Tuple[int, int]:
        """(height, width) of every view."""
        return self.images[0].shape

    @property
    def centres(self) -> np.ndarray:
        """(n, 3) camera centres in world coordinates."""
        return -np.einsum("kji,kj->ki", self.R, self.t)

    def homography(self, k: int, p: int) -> np.ndarray:
        """Texture pixels of plane ``p`` -> pixels of view ``k``."""
        pl, R, t = self.planes[p], self.R[k], self.t[k]
        return self.K @ np.column_stack([R @ pl.du, R @ pl.dv, R @ pl.origin + t])

    def _cast(self, k: int, xy: np.ndarray, points: bool = True
              ) -> Tuple[Optional[np.ndarray], np.ndarray, np.ndarray]:
        """Nearest plane hit by the ray of each pixel: (world points, camera depth, plane index or -1)."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        x, y = xy[:, 0], xy[:, 1]
        best_z = np.full(len(xy), np.inf)
        best_p = np.full(len(xy), -1)
        pts = np.full((len(xy), 3), np.nan) if points else None
        for p, pl in enumerate(self.planes):
            G = np.linalg.inv(self.homography(k, p))  # pixel -> (s, r, 1) / depth
            w = G[2, 0] * x + G[2, 1] * y + G[2, 2]
            front = w > 1e-12
            z = np.divide(1.0, w, out=np.full_like(w, np.inf), where=front)
            with np.errstate(invalid="ignore"):
                s = (G[0, 0] * x + G[0, 1] * y + G[0, 2]) * z
                r = (G[1, 0] * x + G[1, 1] * y + G[1, 2]) * z
            rows, cols = pl.texture.shape
            hit = front & (z < best_z) & (s >= 0) & (s <= cols - 1) & (r >= 0) & (r <= rows - 1)
            best_z[hit], best_p[hit] = z[hit], p
            if points:
                pts[hit] = pl.origin + s[hit, None] * pl.du + r[hit, None] * pl.dv
        return pts, best_z, best_p

    def _check(self, k: int, xy) -> np.ndarray:
        if int(k) != k or not 0 <= k < len(self):
            raise InputError(f"image index must be in 0..{len(self) - 1}, got {k!r}")
        arr = np.asarray(xy, np.float64)
        if arr.ndim != 2 or arr.shape[1] != 2 or not np.isfinite(arr).all():
            raise InputError(f"pixels must be a finite (m, 2) array of x, y; got shape {arr.shape}")
        return arr

    def backproject(self, k: int, xy) -> Tuple[np.ndarray, np.ndarray]:
        """World points (m, 3) seen at pixels ``xy`` (m, 2) of view ``k`` (the visible plane), and a valid mask."""
        pts, _, idx = self._cast(int(k), self._check(k, xy))
        return pts, idx >= 0

    def _project_one(self, k: int, X: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        Xc = X @ self.R[k].T + self.t[k]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (Xc @ self.K.T)[:, :2] / Xc[:, 2:3]
        h, w = self.size
        inside = (Xc[:, 2] > 1e-9) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] >= -0.5) \
            & (uv[:, 1] <= h - 0.5)
        return uv, Xc[:, 2], inside

    def project(self, points) -> Tuple[np.ndarray, np.ndarray]:
        """Pixels (n_images, m, 2) of world points (m, 3) and visibility (n_images, m): in view, not occluded."""
        X = np.asarray(points, np.float64)
        if X.ndim != 2 or X.shape[1] != 3 or not np.isfinite(X).all():
            raise InputError(f"points must be a finite (m, 3) array; got shape {X.shape}")
        uv = np.full((len(self), len(X), 2), np.nan)
        vis = np.zeros((len(self), len(X)), bool)
        for k in range(len(self)):
            uv[k], z, inside = self._project_one(k, X)
            _, z_hit, idx = self._cast(k, np.where(inside[:, None], uv[k], 0.0))
            vis[k] = inside & ~((idx >= 0) & (z_hit < z * (1 - 1e-6)))
        return uv, vis

    def correspondence(self, i: int, j: int, xy_i, tol: float = 1.0) -> Tuple[np.ndarray, np.ndarray]:
        """Where pixels ``xy_i`` of view ``i`` appear in view ``j``: (m, 2) pixels and a mask.

        The mask is true where the surface point is inside view ``j`` and not
        occluded there: the point view ``j`` sees at that pixel, projected back
        into view ``i``, lands within ``tol`` pixels of ``xy_i``.
        """
        xy = self._check(i, xy_i)
        self._check(j, np.zeros((0, 2)))
        if not (np.isfinite(tol) and tol > 0):
            raise InputError(f"tol must be a positive number of pixels, got {tol!r}")
        X, hit = self.backproject(i, xy)
        uv, _, inside = self._project_one(int(j), np.where(hit[:, None], X, 0.0))
        uv[~hit] = np.nan
        ok = hit & inside
        seen, _, idx = self._cast(int(j), np.where(ok[:, None], uv, 0.0))
        back, _, _ = self._project_one(int(i), np.where((idx >= 0)[:, None], seen, 0.0))
        ok &= (idx >= 0) & (np.linalg.norm(back - xy, axis=1) <= tol)
        return uv, ok

    def save(self, folder) -> Path:
        """Write ``img1.png``.. and ``cameras.json`` (K, R, t, width, height) into a new or empty folder."""
        import cv2

        root = Path(folder)
        if root.exists() and (not root.is_dir() or any(root.iterdir())):
            raise InputError(f"refusing to write the scene into {root}: it exists and is not an empty folder")
        root.mkdir(parents=True, exist_ok=True)
        for k, img in enumerate(self.images):
            if not cv2.imwrite(str(root / f"img{k + 1}.png"), img):
                raise InputError(f"cannot write {root / f'img{k + 1}.png'}")
        h, w = self.size
        meta = {"width": w, "height": h, "K": self.K.tolist(), "R": self.R.tolist(), "t": self.t.tolist(),
                "images": [f"img{k + 1}.png" for k in range(len(self))], "convention": "x_cam = R x_world + t"}
        (root / "cameras.json").write_text(json.dumps(meta, indent=1))
        return root


def _rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    Rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    return Ry @ Rx @ Rz


def _plane(centre, rot, half_w: float, half_h: float, px_per_m: float, seed: int) -> Plane:
    """A plane centred at ``centre`` with axes rot[:, 0] (texture columns) and rot[:, 1] (rows)."""
    cols = int(np.clip(round(2 * half_w * px_per_m), 16, _MAX_TEXTURE))
    rows = int(np.clip(round(2 * half_h * px_per_m), 16, _MAX_TEXTURE))
    du, dv = rot[:, 0] * (2 * half_w / (cols - 1)), rot[:, 1] * (2 * half_h / (rows - 1))
    origin = np.asarray(centre, np.float64) - half_w * rot[:, 0] - half_h * rot[:, 1]
    return Plane(origin, du, dv, texture(rows, cols, seed=seed))


def generate_scene3d(seed: int = 0, n_images: int = 8, width: int = 640, height: int = 480,
                     n_planes: int = 4, focal: Optional[float] = None) -> Scene3D:
    """Generate textured planes seen by ``n_images`` pinhole cameras on an arc, with exact truth.

    ``n_planes`` (>= 2) counts the background plane; ``focal`` in pixels
    (default ``0.9 * width``). See the module docstring for the layout.
    """
    import cv2

    for label, v, lo in (("n_images", n_images, 2), ("n_planes", n_planes, 2), ("width", width, 32),
                         ("height", height, 32)):
        if isinstance(v, bool) or int(v) != v or v < lo:
            raise InputError(f"{label} must be an integer >= {lo}, got {v!r}")
    n_images, n_planes, width, height = int(n_images), int(n_planes), int(width), int(height)
    f = 0.9 * width if focal is None else focal
    if not (np.isfinite(f) and f > 0):
        raise InputError(f"focal must be a positive number of pixels, got {focal!r}")
    rng = np.random.default_rng(seed)
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    tx, ty = (width / 2) / f, (height / 2) / f  # half-view tangents

    # cameras on an arc around the scene centre, looking at it
    radius = 6.5
    target = np.array([0.0, 0.0, radius])
    step = min(rng.uniform(0.35, 0.5) / radius, 1.2 / (n_images - 1))
    Rs, ts = [], []
    for k in range(n_images):
        a = (k - (n_images - 1) / 2) * step
        C = target + radius * np.array([np.sin(a), 0.0, -np.cos(a)]) + [0, rng.uniform(-0.1, 0.1), 0]
        z = target + rng.uniform(-0.15, 0.15, 3) - C
        z /= np.linalg.norm(z)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        Rs.append(R)
        ts.append(-R @ C)
    R_all, t_all = np.stack(Rs), np.stack(ts)

    # foreground planes: stratified depths in 4..8 m, spread around the view centre, tilted
    m = n_planes - 1
    planes: List[Plane] = []
    phase = rng.uniform(0, 2 * np.pi)
    spread = 0.0 if m == 1 else 0.45
    for k in range(m):
        d = 4.0 + 4.0 * (k + rng.uniform(0.15, 0.85)) / m
        th = phase + 2 * np.pi * k / m
        ax, ay = spread * np.cos(th) + rng.uniform(-0.1, 0.1), spread * np.sin(th) + rng.uniform(-0.1, 0.1)
        rot = _rotation(rng.uniform(-0.52, 0.52), rng.uniform(-0.35, 0.35), rng.uniform(-0.17, 0.17))
        half_w, half_h = d * tx * rng.uniform(0.35, 0.55), d * ty * rng.uniform(0.4, 0.6)
        planes.append(_plane([d * ax * tx, d * ay * ty, d], rot, half_w, half_h, _OVERSAMPLE * f / d,
                             int(rng.integers(0, 2**31))))

    # background: ~10 m away, slightly tilted, as large as every view's corners need (plus a margin)
    d_bg = rng.uniform(9.5, 10.5)
    rot = _rotation(rng.uniform(-0.17, 0.17), rng.uniform(-0.17, 0.17), 0.0)
    centre = np.array([0.0, 0.0, d_bg])
    corners = np.array([[0, 0, 1], [width, 0, 1], [width, height, 1], [0, height, 1]], np.float64)
    uv = []
    for R, t in zip(R_all, t_all):
        rays = (corners - [0.5, 0.5, 0]) @ np.linalg.inv(K).T @ R  # world directions
        C = -R.T @ t
        lam = ((centre - C) @ rot[:, 2]) / (rays @ rot[:, 2])
        hits = C + lam[:, None] * rays - centre
        uv.append(np.c_[hits @ rot[:, 0], hits @ rot[:, 1]])
    uv = np.vstack(uv)
    lo, hi = uv.min(0), uv.max(0)
    mid, half = (lo + hi) / 2, (hi - lo) / 2 * 1.05 + 0.2
    planes.append(_plane(centre + mid[0] * rot[:, 0] + mid[1] * rot[:, 1], rot, half[0], half[1],
                         _OVERSAMPLE * f / d_bg, int(rng.integers(0, 2**31))))

    scene = Scene3D([], K, R_all, t_all, planes)
    gx, gy = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    grid = np.c_[gx.ravel(), gy.ravel()]
    for k in range(n_images):
        _, _, idx = scene._cast(k, grid, points=False)
        idx = idx.reshape(height, width)
        img = np.zeros((height, width), np.float32)
        depth = [(scene.R[k] @ pl.centre + scene.t[k])[2] for pl in planes]
        for p in np.argsort(depth)[::-1]:  # far to near
            Hinv = np.linalg.inv(scene.homography(k, int(p)))
            warped = cv2.warpPerspective(planes[p].texture, Hinv, (width, height),
                                         flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                         borderMode=cv2.BORDER_REPLICATE)
            mask = idx == p
            img[mask] = warped[mask]
        img += rng.normal(0.0, _NOISE, img.shape).astype(np.float32)
        scene.images.append(np.clip(np.round(img), 0, 255).astype(np.uint8))
    return scene
