"""Generated SIFT-like multi-image descriptor sets with exact ground truth (no download).

A scene has ``n_points`` physical points, each with a base SIFT-like descriptor;
every image sees each point with probability ``visibility`` and describes it
with noise; every image also has clutter features seen nowhere else. Points are
drawn around a few shared "texture prototypes", so distinct points can look
alike (repeated structure), as in real images.

Descriptors are made like SIFT's: non-negative, normalised, clipped at 0.2,
renormalised, scaled by 512 and stored as uint8.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .validation import InputError


@dataclass(frozen=True)
class DescriptorSet:
    """Descriptors with image ids and ground truth (``point_ids``: -1 for clutter)."""

    descriptors: np.ndarray  # (n, 128) uint8
    image_ids: np.ndarray  # (n,) int64
    point_ids: np.ndarray  # (n,) int64, physical point of every feature, -1 if clutter

    def __len__(self) -> int:
        return len(self.descriptors)


def _siftify(v: np.ndarray) -> np.ndarray:
    v = np.maximum(v, 0.0)
    v /= np.linalg.norm(v, axis=1, keepdims=True) + 1e-12
    np.minimum(v, 0.2, out=v)
    v /= np.linalg.norm(v, axis=1, keepdims=True) + 1e-12
    return np.clip(np.round(v * 512.0), 0, 255).astype(np.uint8)


def sift_like(
    n_images: int = 8,
    n_points: int = 500,
    *,
    visibility: float = 0.7,
    clutter_per_image: int = 150,
    noise: float = 0.25,
    n_prototypes: int = 32,
    seed: int = 0,
    dim: int = 128,
) -> DescriptorSet:
    """Generate a multi-image SIFT-like descriptor set.

    ``noise`` is the per-observation perturbation relative to a descriptor's
    typical component; 0.25 gives matches about as hard as real SIFT under
    moderate viewpoint change. Features are ordered image by image, shuffled
    within each image. Deterministic for a given seed.
    """
    if n_images < 1 or n_points < 0 or clutter_per_image < 0:
        raise InputError("sift_like needs n_images >= 1 and non-negative n_points, clutter_per_image")
    if not 0.0 <= visibility <= 1.0:
        raise InputError(f"visibility must be in [0, 1], got {visibility}")
    rng = np.random.default_rng(seed)
    protos = rng.gamma(0.5, 1.0, size=(n_prototypes, dim))
    which = rng.integers(0, n_prototypes, size=n_points)
    base = 0.6 * protos[which] + rng.gamma(0.5, 1.0, size=(n_points, dim))
    scale = base.mean() if n_points else 1.0  # no points: clutter only
    descs, imgs, pids = [], [], []
    for img in range(n_images):
        seen = np.flatnonzero(rng.random(n_points) < visibility)
        obs = base[seen] * np.exp(rng.normal(0.0, noise, size=(len(seen), dim)))
        obs += rng.normal(0.0, noise * scale, size=obs.shape)
        cw = rng.integers(0, n_prototypes, size=clutter_per_image)
        clutter = 0.6 * protos[cw] + rng.gamma(0.5, 1.0, size=(clutter_per_image, dim))
        d = np.vstack([obs, clutter]) if len(obs) or clutter_per_image else np.zeros((0, dim))
        p = np.concatenate([seen, np.full(clutter_per_image, -1)])
        perm = rng.permutation(len(d))
        descs.append(_siftify(d[perm]) if len(d) else np.zeros((0, dim), np.uint8))
        pids.append(p[perm])
        imgs.append(np.full(len(d), img))
    return DescriptorSet(
        descriptors=np.vstack(descs),
        image_ids=np.concatenate(imgs).astype(np.int64),
        point_ids=np.concatenate(pids).astype(np.int64),
    )


def sized(n_features: int, *, features_per_image: int = 2000, seed: int = 0) -> DescriptorSet:
    """A SIFT-like set of about ``n_features`` features (for benchmarks): images of
    ``features_per_image`` features, 60% of them views of shared points."""
    n_images = max(2, int(round(n_features / features_per_image)))
    per = n_features / n_images
    n_points = max(1, int(per * 0.6 / 0.7))
    clutter = max(0, int(per - n_points * 0.7))
    return sift_like(n_images=n_images, n_points=n_points, clutter_per_image=clutter, seed=seed)
