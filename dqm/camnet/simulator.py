"""A seeded simulator of the seed paper's camera-network experiment, with exact ground truth.

The world (metres, ``z`` up; see :mod:`dqm.camnet.geometry`):

* an arena: a textured floor and four walls covered with a repeated tile
  (repeated structure) plus unique marks;
* static clutter: box-shaped objects whose faces are textured from a small
  pool, so the same texture appears on several objects (repeated structure);
* a **decoy** poster on a wall that shows a crop of one target side (a
  realistic confuser: a camera that sees it sees part of the target's texture
  although the target is elsewhere);
* the **target**: a box (default 0.5 x 0.5 m, 0.4 m high, 0.12 m off the
  ground, like a box on a small robot) whose four sides carry different
  textures; the side textures, photographed fronto-parallel and clean, are the
  **reference images**. It drives along a smooth closed trajectory (default
  30 s, sampled at 2 Hz) and faces its direction of travel, so different sides
  face the cameras over time;
* ``n_cameras`` level cameras (default 5: 62 x 48 degree field of view,
  640 x 480 px, 0.35 m high, like forward cameras of ground robots) at known
  poses around the arena, each aimed at a point of the trajectory so the
  target enters and leaves its view.

Rendering is a proper pinhole projection: every planar surface is clipped to
the near plane, projected, and filled by warping its texture with the exact
plane-to-image homography (``cv2.warpPerspective``, from a mip-map level close
to the on-screen scale to limit aliasing); surfaces are painted far to near
(floor, walls, then objects by distance; back faces culled), so objects
occlude each other and the image border cuts the target when it enters or
leaves a view. An id buffer records which surface every pixel shows, so the
target's visible area is exact. Image degradations: per-face shading from a
light direction, a slowly varying global illumination (gain, bias, gamma) per
camera, vignetting, Gaussian blur, sensor noise and JPEG compression.

Everything is drawn from ``numpy.random.default_rng`` seeded by the config's
seed (per camera and time step by ``[seed, camera, step]``), so a world and
every frame are identical for a seed, in any order of rendering.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..validation import InputError
from ..vision.scenes import texture
from .geometry import Camera, Intrinsics, clip_near, look_at_yaw, plane_homography

#: near clipping plane, metres
NEAR = 0.05
#: surface kinds, in painting order before objects
KINDS = ("floor", "wall", "decoy", "clutter", "target")


@dataclass(frozen=True)
class SimConfig:
    """Settings of a simulated experiment (all lengths in metres, angles in degrees).

    ``blur``, ``noise``, ``illumination`` scale the image degradations (0 = none);
    ``min_visible_px``: the target counts as visible in a frame (ground truth of
    detection) when at least this many pixels of its sides are seen.
    """

    seed: int = 0
    duration: float = 30.0
    rate: float = 2.0
    n_cameras: int = 5
    arena: Tuple[float, float] = (8.0, 6.0)
    hfov: float = 62.0
    vfov: float = 48.0
    image_size: Tuple[int, int] = (640, 480)  # width, height
    camera_height: float = 0.35
    target_size: Tuple[float, float, float] = (0.5, 0.5, 0.4)  # width, depth, height
    target_elevation: float = 0.12
    target_px_per_m: float = 800.0
    n_clutter: int = 8
    decoy: bool = True
    blur: float = 1.0
    noise: float = 3.0
    illumination: float = 1.0
    jpeg_quality: int = 75
    min_visible_px: int = 400

    def __post_init__(self):
        def pos(name):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InputError(f"{name} must be a positive number, got {v!r}")

        def nonneg(name):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise InputError(f"{name} must be a number >= 0, got {v!r}")

        for name in ("duration", "rate", "camera_height", "target_elevation", "target_px_per_m"):
            (nonneg if name == "target_elevation" else pos)(name)
        for name in ("blur", "noise", "illumination"):
            nonneg(name)
        if int(self.seed) != self.seed:
            raise InputError(f"seed must be an integer, got {self.seed!r}")
        if int(self.n_cameras) != self.n_cameras or self.n_cameras < 1:
            raise InputError(f"n_cameras must be an integer >= 1, got {self.n_cameras!r}")
        if int(self.n_clutter) != self.n_clutter or self.n_clutter < 0:
            raise InputError(f"n_clutter must be an integer >= 0, got {self.n_clutter!r}")
        if self.n_steps < 1:
            raise InputError(f"duration x rate gives no time step ({self.duration} s at {self.rate} Hz)")
        if len(self.arena) != 2 or min(self.arena) < 3.0:
            raise InputError(f"arena must be (x, y) sizes of at least 3 m, got {self.arena!r}")
        if len(self.target_size) != 3 or min(self.target_size) <= 0:
            raise InputError(f"target_size must be 3 positive lengths, got {self.target_size!r}")
        if max(self.target_size[:2]) > min(self.arena) / 4:
            raise InputError(f"target {self.target_size} too large for the arena {self.arena}")
        if not 1 <= int(self.jpeg_quality) <= 100:
            raise InputError(f"jpeg_quality must lie in 1..100, got {self.jpeg_quality!r}")
        if self.min_visible_px < 1:
            raise InputError(f"min_visible_px must be >= 1, got {self.min_visible_px!r}")
        w, h = self.image_size
        if int(w) != w or int(h) != h or w < 64 or h < 48:
            raise InputError(f"image_size must be integers of at least 64 x 48, got {self.image_size!r}")
        Intrinsics.from_fov(self.hfov, self.vfov, w, h)  # validates the fields of view

    @property
    def n_steps(self) -> int:
        return int(math.floor(self.duration * self.rate + 1e-9))

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.n_steps) / self.rate


@dataclass(frozen=True)
class Surface:
    """A textured planar rectangle: texture pixel (s, t) lies at ``origin + s axis_u + t axis_v``."""

    name: str
    kind: str
    texture: str
    origin: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    size_px: Tuple[int, int]  # texture width, height
    group: int  # painter's order: objects sorted by distance of their group centre
    face: int = -1  # target side index (= reference image), -1 otherwise

    @property
    def corners(self) -> np.ndarray:
        w, h = self.size_px
        o, U, V = self.origin, self.axis_u, self.axis_v
        return np.array([o, o + w * U, o + w * U + h * V, o + h * V])

    @property
    def normal(self) -> np.ndarray:
        """Unit normal on the side the texture is seen from (not mirrored)."""
        n = np.cross(self.axis_v, self.axis_u)
        return n / np.linalg.norm(n)

    @property
    def centre(self) -> np.ndarray:
        return self.corners.mean(axis=0)


@dataclass(frozen=True)
class BoxObject:
    """A box on the ground plane: centre (x, y), heading (radians), size (width, depth, height), elevation."""

    name: str
    centre: Tuple[float, float]
    heading: float
    size: Tuple[float, float, float]
    elevation: float
    textures: Tuple[str, ...]  # front, left, back, right[, top]
    px_per_m: float

    def surfaces(self, group: int, kind: str, faces: bool = False) -> List[Surface]:
        w, d, h = self.size
        c = np.array([self.centre[0], self.centre[1]], float)
        f = np.array([math.cos(self.heading), math.sin(self.heading)])
        left = np.array([-f[1], f[0]])
        out = []
        z_top = self.elevation + h
        s = 1.0 / self.px_per_m
        sides = ((f, d / 2.0, w), (left, w / 2.0, d), (-f, d / 2.0, w), (-left, w / 2.0, d))
        for k, (n, off, width) in enumerate(sides):
            right = np.array([-n[1], n[0]])
            corner = c + n * off - right * width / 2.0
            out.append(Surface(
                f"{self.name}/side{k}", kind, self.textures[k],
                np.array([corner[0], corner[1], z_top]), np.r_[right * s, 0.0], np.array([0.0, 0.0, -s]),
                (int(round(width * self.px_per_m)), int(round(h * self.px_per_m))), group,
                face=k if faces else -1))
        if len(self.textures) > 4:
            corner = c - f * w / 2.0 + left * d / 2.0
            out.append(Surface(f"{self.name}/top", kind, self.textures[4], np.array([corner[0], corner[1], z_top]),
                               np.r_[f * s, 0.0], np.r_[-left * s, 0.0],
                               (int(round(w * self.px_per_m)), int(round(d * self.px_per_m))), group))
        return out


@dataclass(frozen=True)
class FrameTruth:
    """Ground truth of one camera at one time step.

    ``visible_px[k]``: pixels showing target side k (after occlusion and the
    image border); ``box``: bounding box (x0, y0, x1, y1) of those pixels in
    continuous coordinates (pixel centres at integers; None when none);
    ``position``: the target centre (x, y); ``depth`` and
    ``bearing``: of the target centre in this camera; ``decoy_px``: pixels
    showing the decoy poster.
    """

    camera: int
    step: int
    visible_px: np.ndarray
    visible: bool
    box: Optional[Tuple[float, float, float, float]]
    position: np.ndarray
    depth: float
    bearing: float
    decoy_px: int

    @property
    def target_px(self) -> int:
        return int(self.visible_px.sum())


def _trajectory(rng: np.random.Generator, times: np.ndarray, period: float,
                arena: Tuple[float, float]) -> np.ndarray:
    """(T, 3) x, y, heading of a smooth closed loop (one lap per ``period``) inside the arena."""
    ax, ay = arena[0] / 2.0 - 1.3, arena[1] / 2.0 - 1.3
    w = 2 * np.pi / period
    ph = rng.uniform(0, 2 * np.pi, 4)
    a2 = rng.uniform(0.1, 0.25, 2)

    def pos(t):
        x = ax * (0.8 * np.cos(w * t + ph[0]) + a2[0] * np.cos(2 * w * t + ph[2]))
        y = ay * (0.8 * np.sin(w * t + ph[0]) + a2[1] * np.sin(3 * w * t + ph[3]))
        return x, y

    x, y = pos(times)
    dx, dy = pos(times + 1e-3)
    heading = np.arctan2(dy - y, dx - x)
    return np.stack([x, y, heading], 1)


def _pyramid(img: np.ndarray) -> List[np.ndarray]:
    import cv2

    levels = [img.astype(np.float32)]
    while min(levels[-1].shape) >= 16 and len(levels) < 8:
        levels.append(cv2.pyrDown(levels[-1]))
    return levels


class World:
    """A built simulation: cameras, trajectory, textures, references; renders frames with truth."""

    def __init__(self, config: SimConfig):
        self.config = config
        rng = np.random.default_rng([int(config.seed), 7919])
        w, h = config.image_size
        self.intrinsics = Intrinsics.from_fov(config.hfov, config.vfov, w, h)
        self.times = config.times
        self.trajectory = _trajectory(rng, self.times, max(config.duration, 1.0), config.arena)
        self._textures: Dict[str, List[np.ndarray]] = {}
        tw, td, th = config.target_size
        ppm = config.target_px_per_m
        # target sides: distinct textures with a common logo (repeated structure across sides)
        logo = texture(int(0.12 * ppm), int(0.12 * ppm), seed=int(rng.integers(2**31)), density=2.0)
        self.references: List[np.ndarray] = []
        for k, width in enumerate((tw, td, tw, td)):
            tex = texture(int(round(th * ppm)), int(round(width * ppm)), seed=int(rng.integers(2**31)),
                          density=1.6)
            tex[:6, :] = 20
            tex[-6:, :] = 20
            tex[:, :6] = 20
            tex[:, -6:] = 20
            lh, lw = logo.shape
            tex[12:12 + lh, -12 - lw:-12] = logo
            self.references.append(tex)
            self._textures[f"target{k}"] = _pyramid(tex)
        # arena
        axl, ayl = config.arena
        floor_ppm = 120.0
        self._textures["floor"] = _pyramid(
            (texture(int(ayl * floor_ppm), int(axl * floor_ppm), seed=int(rng.integers(2**31)), density=0.5)
             .astype(np.float32) * 0.5 + 60).astype(np.uint8))
        wall_ppm, wall_h = 160.0, 2.5
        tile = texture(int(wall_ppm), int(wall_ppm * 1.25), seed=int(rng.integers(2**31)), density=1.0)
        self.surfaces_static: List[Surface] = [Surface(
            "floor", "floor", "floor", np.array([-axl / 2, ayl / 2, 0.0]), np.array([1 / floor_ppm, 0, 0]),
            np.array([0, -1 / floor_ppm, 0]), (int(axl * floor_ppm), int(ayl * floor_ppm)), 0)]
        corners = [(-axl / 2, ayl / 2), (axl / 2, ayl / 2), (axl / 2, -ayl / 2), (-axl / 2, -ayl / 2)]
        walls = []
        for k in range(4):
            # seen from inside, the wall runs left (A) to right (B); corners go clockwise
            A = np.array(corners[k], float)
            B = np.array(corners[(k + 1) % 4], float)
            length = float(np.linalg.norm(B - A))
            reps = int(math.ceil(length * wall_ppm / tile.shape[1]))
            wall = np.tile(tile, (int(math.ceil(wall_h * wall_ppm / tile.shape[0])), reps))
            wall = wall[:int(wall_h * wall_ppm), :int(length * wall_ppm)].copy()
            marks = texture(wall.shape[0], wall.shape[1], seed=int(rng.integers(2**31)), density=0.08)
            wall = np.where(np.abs(marks.astype(int) - 128) > 70, marks, wall).astype(np.uint8)
            self._textures[f"wall{k}"] = _pyramid(wall)
            u = (B - A) / length / wall_ppm
            s = Surface(f"wall{k}", "wall", f"wall{k}", np.array([A[0], A[1], wall_h]), np.r_[u, 0.0],
                        np.array([0, 0, -1 / wall_ppm]), (wall.shape[1], wall.shape[0]), 1)
            walls.append(s)
        self.surfaces_static += walls
        # cameras on the arena's border, each aimed at a point of the trajectory
        self.cameras: List[Camera] = []
        inset = 0.35
        ang0 = rng.uniform(0, 2 * np.pi)
        for c in range(config.n_cameras):
            a = ang0 + 2 * np.pi * c / config.n_cameras + rng.uniform(-0.2, 0.2)
            d = np.array([math.cos(a), math.sin(a)])
            sx = (axl / 2 - inset) / max(abs(d[0]), 1e-9)
            sy = (ayl / 2 - inset) / max(abs(d[1]), 1e-9)
            p = d * min(sx, sy)
            yaw = look_at_yaw(p, (0.0, 0.0)) + math.radians(rng.uniform(-45, 45))
            self.cameras.append(Camera(f"cam{c}", np.array([p[0], p[1], config.camera_height]), yaw, 0.0,
                                       self.intrinsics))
        # clutter: boxes away from the trajectory and the cameras, textures from a small pool
        pool = max(1, (config.n_clutter + 1) // 2)
        for k in range(pool):
            self._textures[f"clutter{k}"] = _pyramid(
                texture(300, 300, seed=int(rng.integers(2**31)), density=1.0))
        self.clutter: List[BoxObject] = []
        tries = 0
        while len(self.clutter) < config.n_clutter and tries < 2000:
            tries += 1
            size = (rng.uniform(0.3, 0.8), rng.uniform(0.3, 0.8), rng.uniform(0.3, 1.1))
            xy = rng.uniform([-axl / 2 + 0.6, -ayl / 2 + 0.6], [axl / 2 - 0.6, ayl / 2 - 0.6])
            r = math.hypot(size[0], size[1]) / 2
            if np.min(np.hypot(*(self.trajectory[:, :2] - xy).T)) < r + 0.55:
                continue
            if min(np.hypot(*(cam.position[:2] - xy)) for cam in self.cameras) < r + 0.8:
                continue
            if any(math.hypot(b.centre[0] - xy[0], b.centre[1] - xy[1]) < r + math.hypot(*b.size[:2]) / 2 + 0.1
                   for b in self.clutter):
                continue
            tex = tuple(f"clutter{int(rng.integers(pool))}" for _ in range(5))
            self.clutter.append(BoxObject(f"clutter{len(self.clutter)}", (float(xy[0]), float(xy[1])),
                                          float(rng.uniform(0, np.pi)), size, 0.0, tex, 300.0))
        # the decoy: a crop of target side 0 on a wall, at the target's scale
        self.decoy: Optional[Surface] = None
        if config.decoy:
            ref = self.references[0]
            crop = ref[:, : int(0.3 * ref.shape[1])].copy()
            self._textures["decoy"] = _pyramid(crop)
            wall = walls[int(rng.integers(4))]
            along = rng.uniform(0.25, 0.75) * wall.size_px[0]
            n = wall.normal
            z = config.target_elevation + th
            origin = wall.origin + along * wall.axis_u + n * 0.01
            origin[2] = z
            self.decoy = Surface("decoy", "decoy", "decoy", origin, wall.axis_u / np.linalg.norm(wall.axis_u) / ppm,
                                 np.array([0, 0, -1 / ppm]), (crop.shape[1], crop.shape[0]), 1)
        self.light = np.array([math.cos(rng.uniform(0, 2 * np.pi)), math.sin(rng.uniform(0, 2 * np.pi)), 0.0])
        self.light[:2] /= np.linalg.norm(self.light[:2])

    # --- state at a time step ------------------------------------------------------------------
    @property
    def n_steps(self) -> int:
        return len(self.times)

    def target(self, step: int) -> BoxObject:
        self._check_step(step)
        x, y, hd = self.trajectory[step]
        return BoxObject("target", (float(x), float(y)), float(hd), self.config.target_size,
                         self.config.target_elevation, ("target0", "target1", "target2", "target3"),
                         self.config.target_px_per_m)

    def target_centre(self, step: int) -> np.ndarray:
        """Target centre (x, y, z) at a time step."""
        self._check_step(step)
        tw, td, th = self.config.target_size
        return np.r_[self.trajectory[step, :2], self.config.target_elevation + th / 2.0]

    def _check_step(self, step: int) -> None:
        if int(step) != step or not 0 <= step < self.n_steps:
            raise InputError(f"time step must be an integer in 0..{self.n_steps - 1}, got {step!r}")

    def _check_camera(self, camera: int) -> None:
        if int(camera) != camera or not 0 <= camera < len(self.cameras):
            raise InputError(f"camera must be an integer in 0..{len(self.cameras) - 1}, got {camera!r}")

    # --- rendering ---------------------------------------------------------------------------
    def render(self, camera: int, step: int, *, clean: bool = False) -> Tuple[np.ndarray, FrameTruth]:
        """Image (uint8, height x width) of ``camera`` at ``step`` and its ground truth.

        ``clean=True`` skips the degradations (blur, noise, illumination, JPEG).
        """
        self._check_camera(camera)
        self._check_step(step)
        cam = self.cameras[camera]
        target = self.target(step)
        return self.render_view(cam, target, rng=np.random.default_rng([int(self.config.seed), camera, step]),
                                clean=clean, camera_index=camera, step=step)

    def render_view(self, cam: Camera, target: Optional[BoxObject], rng: np.random.Generator, *,
                    clean: bool = False, camera_index: int = -1, step: int = -1,
                    static: bool = True) -> Tuple[np.ndarray, FrameTruth]:
        """Render any camera with the target at any pose (e.g. for calibration); see :meth:`render`."""
        import cv2

        W, Hh = cam.intrinsics.width, cam.intrinsics.height
        yy = np.linspace(0.0, 1.0, Hh, dtype=np.float32)[:, None]
        canvas = np.broadcast_to(150.0 + 40.0 * (1.0 - yy), (Hh, W)).astype(np.float32).copy()
        ids = np.full((Hh, W), -1, np.int16)
        surfaces: List[Surface] = []
        objects: List[Tuple[float, List[Surface]]] = []
        if static:
            surfaces += self.surfaces_static
            if self.decoy is not None:
                surfaces.append(self.decoy)
            for g, b in enumerate(self.clutter):
                objects.append((math.hypot(b.centre[0] - cam.position[0], b.centre[1] - cam.position[1]),
                                b.surfaces(10 + g, "clutter")))
        if target is not None:
            objects.append((math.hypot(target.centre[0] - cam.position[0], target.centre[1] - cam.position[1]),
                            target.surfaces(5, "target", faces=True)))
        for _, surfs in sorted(objects, key=lambda o: -o[0]):
            surfaces += surfs
        light_dir = self.light
        index: List[Surface] = []
        for s in surfaces:
            n = s.normal
            if np.dot(n, cam.position - s.centre) <= 0:
                continue  # back face
            shade = 1.0
            if s.kind in ("clutter", "target"):
                shade = 0.7 + 0.3 * max(0.0, float(np.dot(n, light_dir))) if abs(n[2]) < 0.5 else 1.05
            _draw(canvas, ids, cam, s, self._textures[s.texture], len(index), shade)
            index.append(s)
        # ground truth from the id buffer
        counts = np.bincount(ids[ids >= 0].ravel(), minlength=len(index)) if len(index) else np.zeros(0, int)
        vis = np.zeros(4, np.int64)
        decoy_px = 0
        tmask = np.zeros((Hh, W), bool)
        for i, s in enumerate(index):
            if s.kind == "target" and counts[i]:
                vis[s.face] += counts[i]
                tmask |= ids == i
            elif s.kind == "decoy":
                decoy_px += int(counts[i])
        box = None
        if tmask.any():
            ys, xs = np.nonzero(tmask)
            # pixel centres are integers: pixel i covers [i - 0.5, i + 0.5]
            box = (float(xs.min()) - 0.5, float(ys.min()) - 0.5, float(xs.max()) + 0.5, float(ys.max()) + 0.5)
        if target is not None:
            tc = np.r_[target.centre, target.elevation + target.size[2] / 2]
        else:
            tc = np.array([np.nan, np.nan, np.nan])
        Xc = cam.to_camera(tc)[0]
        truth = FrameTruth(camera_index, step, vis, bool(vis.sum() >= self.config.min_visible_px), box,
                           tc[:2].copy(), float(Xc[2]), float(math.atan2(Xc[0], Xc[2])), decoy_px)
        img = canvas if clean else _degrade(canvas, rng, self.config)
        img = np.clip(np.round(img), 0, 255).astype(np.uint8)
        if not clean and self.config.jpeg_quality < 100:
            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(self.config.jpeg_quality)])
            img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
        return img, truth

    def with_config(self, **changes) -> "World":
        """A new world built from this one's config with some fields changed."""
        return World(replace(self.config, **changes))


def _draw(canvas: np.ndarray, ids: np.ndarray, cam: Camera, s: Surface, pyramid: List[np.ndarray],
          sid: int, shade: float) -> bool:
    """Paint one surface into ``canvas`` (float32) and ``ids``; False when it is not in view."""
    import cv2

    Hh, W = canvas.shape
    Xc = cam.to_camera(s.corners)
    poly = clip_near(Xc, NEAR)
    if len(poly) < 3:
        return False
    K = cam.intrinsics
    uv = np.stack([K.fx * poly[:, 0] / poly[:, 2] + K.cx, K.fy * poly[:, 1] / poly[:, 2] + K.cy], 1)
    x0 = max(0, int(math.floor(uv[:, 0].min())))
    y0 = max(0, int(math.floor(uv[:, 1].min())))
    x1 = min(W, int(math.ceil(uv[:, 0].max())) + 1)
    y1 = min(Hh, int(math.ceil(uv[:, 1].max())) + 1)
    if x1 <= x0 or y1 <= y0:
        return False
    H = plane_homography(cam, s.origin, s.axis_u, s.axis_v)
    # on-screen scale (pixels per texel) at the visible part's centre -> mip-map level
    c = np.clip(uv.mean(axis=0), [x0, y0], [x1 - 1, y1 - 1])
    scale = 1.0
    try:
        with np.errstate(divide="ignore", invalid="ignore"):
            p = np.linalg.solve(H, np.r_[c, 1.0])
            p = p[:2] / p[2]
            wden = H[2, 0] * p[0] + H[2, 1] * p[1] + H[2, 2]
            J = (H[:2, :2] - np.outer(c, H[2, :2])) / wden
            if np.isfinite(J).all():
                scale = math.sqrt(abs(float(np.linalg.det(J))))
    except np.linalg.LinAlgError:  # plane seen edge-on: any level will do
        pass
    level = 0
    if 0 < scale < 1:
        level = min(len(pyramid) - 1, int(math.floor(math.log2(1.0 / scale))))
    tex = pyramid[level]
    f = float(2 ** level)
    Hl = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1]], float) @ H @ np.diag([f, f, 1.0])
    warped = cv2.warpPerspective(tex, Hl, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REPLICATE)
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    pts = np.round((uv - [x0, y0]) * 16).astype(np.int32)
    cv2.fillPoly(mask, [pts], 255, cv2.LINE_AA, shift=4)
    m = mask.astype(np.float32) / 255.0
    roi = canvas[y0:y1, x0:x1]
    roi += m * (shade * warped - roi)
    ids[y0:y1, x0:x1][mask >= 128] = sid
    return True


def _degrade(canvas: np.ndarray, rng: np.random.Generator, cfg: SimConfig) -> np.ndarray:
    """Illumination change, vignetting, blur and noise of a rendered frame (float32 in, float out)."""
    import cv2

    img = canvas.astype(np.float32)
    Hh, W = img.shape
    if cfg.illumination > 0:
        a = cfg.illumination
        gain = 1.0 + a * rng.uniform(-0.3, 0.25)
        bias = a * rng.uniform(-15, 15)
        gamma = float(np.exp(a * rng.uniform(-0.25, 0.25)))
        yy, xx = np.mgrid[0:Hh, 0:W].astype(np.float32)
        r2 = ((xx - W / 2) ** 2 + (yy - Hh / 2) ** 2) / ((W / 2) ** 2 + (Hh / 2) ** 2)
        gx, gy = rng.uniform(-0.15, 0.15, 2) * a
        light = (1.0 - 0.35 * a * r2) * (1.0 + gx * (xx / W - 0.5) + gy * (yy / Hh - 0.5))
        img = np.clip(img * gain * light + bias, 0, 255)
        img = 255.0 * (img / 255.0) ** gamma
    if cfg.blur > 0:
        sb = cfg.blur * rng.uniform(0.5, 1.3)
        img = cv2.GaussianBlur(img, (0, 0), sb)
    if cfg.noise > 0:
        img = img + rng.normal(0.0, cfg.noise, size=img.shape).astype(np.float32)
    return img


def build_world(config: Optional[SimConfig] = None, **kwargs) -> World:
    """Build the simulated world of ``config`` (or of ``SimConfig(**kwargs)``)."""
    if config is None:
        config = SimConfig(**kwargs)
    elif kwargs:
        config = replace(config, **kwargs)
    if not isinstance(config, SimConfig):
        raise InputError(f"config must be a SimConfig, got {type(config).__name__}")
    return World(config)


def camera_views(world: World, step: int, clean: bool = False) -> Tuple[List[np.ndarray], List[FrameTruth]]:
    """All cameras' images and truths at one time step."""
    imgs, truths = [], []
    for c in range(len(world.cameras)):
        img, tr = world.render(c, step, clean=clean)
        imgs.append(img)
        truths.append(tr)
    return imgs, truths


__all__: Sequence[str] = ["SimConfig", "World", "FrameTruth", "Surface", "BoxObject", "build_world",
                          "camera_views", "NEAR", "KINDS"]
