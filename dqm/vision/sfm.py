"""Sparse reconstruction from dqm's tracks with pycolmap's incremental mapper, and a figure of it.

Used by ``dqm sfm`` (images -> model in one command) and ``scripts/bench_sfm.py``.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .colmap import require_pycolmap


def reconstruct(database, image_dir, out_dir):
    """The largest model of pycolmap's incremental mapping of ``database`` (most registered images,
    then most points; None if no model) and the mapping time in seconds. Models go to ``out_dir``."""
    pycolmap = require_pycolmap()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    recs = pycolmap.incremental_mapping(str(database), str(image_dir), str(out))
    dt = time.perf_counter() - t0
    if not recs:
        return None, dt
    return max(recs.values(), key=lambda r: (r.num_reg_images(), r.num_points3D())), dt


def model_numbers(rec) -> dict:
    """Registered images, 3-D points, mean track length and mean reprojection error (px) of a model."""
    if rec is None:
        return {"registered": 0, "points": 0, "track": float("nan"), "reproj": float("nan")}
    return {"registered": rec.num_reg_images(), "points": rec.num_points3D(),
            "track": rec.compute_mean_track_length(), "reproj": rec.compute_mean_reprojection_error()}


def model_figure(rec, path, title: str) -> None:
    """A sparse model from the front (the points' two main axes) and from above (main and depth axes)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    P = np.array([p.xyz for p in rec.points3D.values()])
    C = np.array([im.projection_center() for im in rec.images.values() if im.has_pose])
    centre = np.median(P, axis=0)
    _, _, vt = np.linalg.svd(P - centre, full_matrices=False)
    p3, c3 = (P - centre) @ vt.T, (C - centre) @ vt.T
    lim = np.percentile(np.abs(p3), 98, axis=0) * 1.2 + 1e-12
    fig, (front, top) = plt.subplots(1, 2, figsize=(11, 5), dpi=110)
    front.scatter(p3[:, 0], p3[:, 1], s=2, c="#4575b4", alpha=0.7)
    front.set_xlim(-lim[0], lim[0])
    front.set_ylim(-lim[1], lim[1])
    front.set_title(f"front: {len(P):,} 3-D points")
    top.scatter(p3[:, 0], p3[:, 2], s=2, c="#4575b4", alpha=0.7, label="3-D points")
    top.scatter(c3[:, 0], c3[:, 2], s=45, c="#d73027", marker="^", label=f"{len(C)} cameras")
    top.set_title("from above, with the cameras")
    top.legend(loc="best")
    for ax, yl in ((front, "main axis 2"), (top, "depth axis")):
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel("main axis 1 (model units)")
        ax.set_ylabel(yl)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
