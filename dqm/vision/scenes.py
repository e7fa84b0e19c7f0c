"""Generated multi-view image scenes with exact ground truth (no download needed).

A scene is a procedurally drawn planar texture (smooth multi-scale noise under
random filled shapes, strokes and glyphs) seen by ``n_images`` virtual cameras.
View k is the texture warped by a known homography; the viewpoint change grows
along the sequence as in the Oxford sequences (view 0 is the reference), and
every view gets its own photometric change (gain, bias, gamma), blur and
sensor noise. ``homographies[k]`` maps view-0 pixels to view-k pixels, exactly:
the same ground truth as :class:`dqm.vision.datasets.HomographySequence`, and
:meth:`Scene.write` saves a scene in that layout (``img1.png``.., ``H1to2p``..)
so every tool that reads Oxford folders reads it too.

Deterministic for a given seed (pure numpy RNG + OpenCV drawing).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import List, Tuple

import numpy as np

from ..validation import InputError

#: the canvas is this much larger than a view, so warped views never leave it
_CANVAS_MARGIN = 0.35


@dataclass(frozen=True)
class Scene:
    """Views of a planar scene: ``homographies[k]`` maps view-0 pixels to view-k pixels."""

    name: str
    images: List[np.ndarray]  # uint8 grayscale views, all of one size
    homographies: np.ndarray  # (N, 3, 3), homographies[0] = identity

    def __len__(self) -> int:
        return len(self.images)

    def homography(self, i: int, j: int) -> np.ndarray:
        """Homography mapping pixels of view ``i`` to view ``j`` (normalised, H[2,2] = 1)."""
        H = self.homographies[j] @ np.linalg.inv(self.homographies[i])
        return H / H[2, 2]

    def write(self, folder) -> "object":
        """Save as an Oxford-layout folder and return it loaded as a HomographySequence."""
        import cv2

        from ..outputs import atomic_output
        from .datasets import load_homography_sequence

        root = Path(folder)
        for k, img in enumerate(self.images):
            with atomic_output(root / f"img{k + 1}.png") as tmp:
                if not cv2.imwrite(tmp, img):
                    raise InputError(f"cannot write {root / f'img{k + 1}.png'}")
        for k in range(1, len(self.images)):
            with atomic_output(root / f"H1to{k + 1}p") as tmp:
                np.savetxt(tmp, self.homographies[k] / self.homographies[k][2, 2], fmt="%.12e")
        return load_homography_sequence(root)


def _smooth_noise(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Multi-octave value noise in [0, 1] (sum of upsampled random grids)."""
    import cv2

    out = np.zeros((h, w), np.float32)
    amp, total = 1.0, 0.0
    for cells in (4, 9, 21, 47):
        grid = rng.random((cells, int(cells * w / h) + 1)).astype(np.float32)
        out += amp * cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= 0.55
    out /= total
    return (out - out.min()) / max(float(out.max() - out.min()), 1e-6)


def texture(height: int, width: int, seed: int = 0, density: float = 1.0) -> np.ndarray:
    """A procedurally drawn uint8 texture: smooth noise under shapes, strokes and glyphs.

    ``density`` scales the number of drawn elements (about one per 1600 px^2).
    """
    import cv2

    if height < 16 or width < 16:
        raise InputError(f"texture needs at least 16x16 pixels, got {height}x{width}")
    if not density > 0:
        raise InputError(f"density must be positive, got {density}")
    rng = np.random.default_rng(seed)
    img = np.round(60 + 130 * _smooth_noise(rng, height, width)).astype(np.uint8)
    n = int(density * height * width / 1600)
    fonts = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
             cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_SCRIPT_SIMPLEX)
    glyphs = "ABCDEFGHJKLMNPQRSTUVWXYZabdefghkmnpqrtwxyz0123456789#&%@$?"
    for _ in range(n):
        kind = rng.integers(0, 5)
        c = (int(rng.integers(0, 256)),)
        x, y = int(rng.integers(0, width)), int(rng.integers(0, height))
        r = int(rng.integers(3, 28))
        if kind == 0:
            axes = (r, max(2, int(r * rng.uniform(0.3, 1.0))))
            cv2.ellipse(img, (x, y), axes, float(rng.uniform(0, 180)), 0, 360, c, -1, cv2.LINE_AA)
        elif kind == 1:
            k = int(rng.integers(3, 7))
            ang = np.sort(rng.uniform(0, 2 * np.pi, k))
            rad = r * rng.uniform(0.5, 1.0, k)
            pts = np.stack([x + rad * np.cos(ang), y + rad * np.sin(ang)], 1).astype(np.int32)
            cv2.fillPoly(img, [pts], c, cv2.LINE_AA)
        elif kind == 2:
            a = rng.uniform(0, 2 * np.pi)
            p2 = (int(x + 2 * r * np.cos(a)), int(y + 2 * r * np.sin(a)))
            cv2.line(img, (x, y), p2, c, int(rng.integers(1, 5)), cv2.LINE_AA)
        elif kind == 3:
            ch = glyphs[int(rng.integers(0, len(glyphs)))]
            cv2.putText(img, ch, (x, y), fonts[int(rng.integers(0, len(fonts)))], r / 14.0, c,
                        int(rng.integers(1, 4)), cv2.LINE_AA)
        else:
            w2, h2 = r, max(2, int(r * rng.uniform(0.3, 1.0)))
            box = cv2.boxPoints(((x, y), (2 * w2, 2 * h2), float(rng.uniform(0, 90)))).astype(np.int32)
            cv2.drawContours(img, [box], 0, c, -1 if rng.random() < 0.6 else 2, cv2.LINE_AA)
    return cv2.GaussianBlur(img, (0, 0), 0.7)


def _view_homography(rng: np.random.Generator, canvas: Tuple[int, int], view: Tuple[int, int],
                     strength: float) -> np.ndarray:
    """Canvas -> view homography: the view rectangle, jittered in perspective by ``strength``."""
    import cv2

    ch, cw = canvas
    vh, vw = view
    cx, cy = cw / 2.0, ch / 2.0
    rect = np.array([[0, 0], [vw, 0], [vw, vh], [0, vh]], np.float64)
    quad = rect - [vw / 2.0, vh / 2.0]
    if strength > 0:
        angle = rng.uniform(-0.35, 0.35) * strength
        scale = np.exp(rng.uniform(-0.25, 0.25) * strength)
        R = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        quad = (quad @ R.T) * scale
        quad = quad + rng.uniform(-0.18, 0.18, size=(4, 2)) * strength * [vw, vh]
        quad = quad + rng.uniform(-0.1, 0.1, size=2) * strength * [vw, vh]
    quad = quad + [cx, cy]
    quad[:, 0] = np.clip(quad[:, 0], 0, cw - 1)
    quad[:, 1] = np.clip(quad[:, 1], 0, ch - 1)
    G = cv2.getPerspectiveTransform(quad.astype(np.float32), rect.astype(np.float32)).astype(np.float64)
    return G / G[2, 2]


def generate_scene(
    n_images: int = 6,
    size: Tuple[int, int] = (480, 640),
    *,
    seed: int = 0,
    viewpoint: float = 1.0,
    photometric: float = 1.0,
    blur: float = 1.0,
    noise: float = 3.0,
    density: float = 1.0,
    name: str = "",
) -> Scene:
    """Generate a multi-view scene of a planar texture with exact homographies.

    Parameters
    ----------
    n_images : number of views (>= 2).
    size : (height, width) of every view in pixels.
    seed : RNG seed; the same seed gives the same scene.
    viewpoint : strength of the perspective change of the last view relative to
        view 0 (0 = none; 1 = up to ~20 degrees rotation, ~25% scale change and
        ~18% corner displacement); it grows linearly along the sequence.
    photometric : strength of per-view gain (up to +-30%), bias (+-20 levels) and
        gamma (0.8..1.25) changes (0 = none).
    blur : largest Gaussian blur sigma of a view (pixels).
    noise : standard deviation of additive Gaussian sensor noise (grey levels).
    density : scales the number of drawn texture elements.
    """
    import cv2

    if int(n_images) != n_images or n_images < 2:
        raise InputError(f"a scene needs at least 2 images, got {n_images}")
    h, w = (int(v) for v in size)
    if h < 32 or w < 32:
        raise InputError(f"views must be at least 32x32 pixels, got {h}x{w}")
    for label, v in (("viewpoint", viewpoint), ("photometric", photometric), ("blur", blur), ("noise", noise)):
        if not (np.isfinite(v) and v >= 0):
            raise InputError(f"{label} must be a finite number >= 0, got {v!r}")
    rng = np.random.default_rng(seed)
    ch, cw = int(h * (1 + 2 * _CANVAS_MARGIN)), int(w * (1 + 2 * _CANVAS_MARGIN))
    tex = texture(ch, cw, seed=int(rng.integers(0, 2**31)), density=density).astype(np.float32)
    Gs, images = [], []
    for k in range(int(n_images)):
        strength = viewpoint * k / (n_images - 1)
        G = _view_homography(rng, (ch, cw), (h, w), strength)
        view = cv2.warpPerspective(tex, G, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        gain = 1.0 + photometric * rng.uniform(-0.3, 0.3)
        bias = photometric * rng.uniform(-20, 20)
        gamma = float(np.exp(photometric * rng.uniform(-0.22, 0.22)))
        view = 255.0 * (np.clip(view * gain + bias, 0, 255) / 255.0) ** gamma
        sb = blur * rng.uniform(0.2, 1.0) if k else blur * 0.2
        if sb > 0.05:
            view = cv2.GaussianBlur(view, (0, 0), sb)
        if noise > 0:
            view = view + rng.normal(0.0, noise, size=view.shape)
        images.append(np.clip(np.round(view), 0, 255).astype(np.uint8))
        Gs.append(G)
    G0inv = np.linalg.inv(Gs[0])
    Hs = np.stack([G @ G0inv for G in Gs])
    Hs /= Hs[:, 2:3, 2:3]
    return Scene(name or f"scene-{seed}", images, Hs)
