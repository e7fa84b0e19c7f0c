"""Clustered random points for the engine tests (a test helper: ``from generators.points import clustered``)."""
import numpy as np


def clustered(seed, n_images=6, n_points=60, dim=16, clutter=20, noise=0.15):
    """Random points seen in several images with noise, plus clutter (float64)."""
    rng = np.random.default_rng(seed)
    centers = rng.normal(size=(n_points, dim))
    X, ids = [], []
    for img in range(n_images):
        seen = rng.random(n_points) < 0.7
        X.append(centers[seen] + noise * rng.normal(size=(seen.sum(), dim)))
        X.append(rng.normal(size=(clutter, dim)))
        ids += [img] * (seen.sum() + clutter)
    return np.vstack(X), np.array(ids)
