"""More 3-D points from a finished model: matches guided by the model's own cameras, then triangulation.

QuickMatch's clusters give the mapper precise matches and good cameras, but fewer 3-D points than a
pairwise matcher (docs/sfm.md). Once the cameras are known, a match no longer needs a descriptor that
stands out in the whole image: it needs one that stands out among the few features near the epipolar
line that the model's relative pose and intrinsics draw. :func:`model_guided_matches` matches each
registered image with the ``PARTNERS`` (8) images that share the most 3-D points with it, at least 15
(:func:`covisible_partners`, as hloc's pairs from covisibility), so the work grows with the images, not
with their pairs. Every covisible pair (all 928 of dtu/scan24's mapper model) gave more observations but
fewer, longer points than 8 partners (257 pairs): the widest pairs' matches merge tracks, and their
matching took 19.5 s against 6.6 s; 8 partners made more points at a lower reprojection error on both
dtu/scan24 (41,961 against 35,996; 0.43 against 0.47 px) and nerf_lego (19,169 against 18,553; 0.44
against 0.48 px). For each such pair it finds:

* every feature's keypoint in the model's undistorted frame (COLMAP's camera model inverted, scaled
  by the camera's focal length, so distances are in pixels); a keypoint the camera model cannot invert
  (COLMAP gives NaN where a strong radial distortion folds back: the mapper estimated k = -3 to -4 at
  f = 1,500 px for cmu_hotel's 512 x 480 frames, so pixels more than 290-330 px from the centre have
  no undistorted position) takes no part;
* the candidates: the other image's features within ``threshold`` pixels (Sampson distance) of the
  epipolar geometry of the model's relative pose (:func:`dqm.vision.guided.consistent_pairs`, no
  n x n);
* the matches: mutual nearest descriptors among the candidates, each passing Lowe's ratio against
  the second nearest candidate (:func:`dqm.vision.guided.propose_links`).

:func:`triangulate` adds them to the database's verified matches (beside the clusters' own) and runs
COLMAP's triangulator with the model's poses and intrinsics fixed
(``pycolmap.triangulate_points``): it creates points from the new correspondences, extends the
existing tracks and merges points, checking every observation in every view against
``max_error`` pixels. New points seen in fewer than 3 images are dropped (COLMAP's triangulator
makes two-view points; its incremental mapper does not create them, and the comparison with it
stays fair).

Then, by default, one **bundle adjustment** of the whole model with COLMAP's defaults
(``pycolmap.bundle_adjustment``: poses, points, focal lengths and distortion; principal points
fixed): the mapper adjusted its cameras against its own points, two to three times fewer
observations than the model now has. Measured on the mapper models of three scenes with ground-truth
cameras (seed 0), pairwise pose AUC@1/2/5 degrees before -> after: nerf_lego 0.629 / 0.754 / 0.842 ->
0.698 / 0.795 / 0.860 (7 s), dtu/scan24 0.507 / 0.753 / 0.901 -> 0.527 / 0.763 / 0.905 (16 s),
strecha/entry-P10 0.627 / 0.811 / 0.924 -> 0.643 / 0.822 / 0.929 (1 s); adjusting poses and points only
gained a third as much or less (0.650 / 0.765 / 0.846 on nerf_lego). ``bundle_adjust=False`` keeps the
mapper's cameras bit for bit and only adds points and observations.
Deterministic: the matches do not depend on the threads, the triangulator is seeded, and with one
thread (``num_threads=1``, dqm sfm's default) the adjustment gives the same model bit for bit.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import signals
from ..core.pairs import default_threads
from ..progress import ProgressArg, resolve_progress, ticking
from .colmap import colmap_log_kept, glog_info_dropped, require_pycolmap
from .guided import DEFAULT_RATIO, propose_links
from .verify import PairModel

LOG = logging.getLogger("dqm.vision")

#: a guided match fits the model's epipolar geometry within this many pixels (Sampson distance)
DEFAULT_THRESHOLD = 0.5
#: the triangulator's reprojection limit for creating, completing and merging tracks (COLMAP's is 4 px)
DEFAULT_MAX_ERROR = 2.0
#: image pairs are matched when they share at least this many 3-D points of the model
MIN_SHARED_POINTS = 15
#: each image is matched with at most this many others: those that share the most points with it
PARTNERS = 8


@dataclass
class TriangulationStats:
    """What :func:`triangulate` did."""

    n_pairs: int  # image pairs matched under the model's geometry
    n_matches: int  # guided matches found
    n_new_matches: int  # of them not among the database's verified matches
    points_before: int
    points_after: int
    observations_before: int
    observations_after: int
    time_match: float
    time_triangulate: float
    reproj_before_adjust: float | None = None  # mean reprojection error (px) before the bundle adjustment
    reproj_after_adjust: float | None = None  # and after it; both None when it did not run
    time_adjust: float = 0.0

    def summary(self) -> str:
        line = (f"model-guided triangulation: {self.n_new_matches:,} new matches in {self.n_pairs} image pairs "
                f"({self.time_match:.1f} s), 3-D points {self.points_before:,} -> {self.points_after:,}, "
                f"observations {self.observations_before:,} -> {self.observations_after:,} "
                f"({self.time_triangulate:.1f} s)")
        if self.reproj_after_adjust is not None:
            line += (f"; bundle adjustment: mean reprojection error {self.reproj_before_adjust:.3f} -> "
                     f"{self.reproj_after_adjust:.3f} px ({self.time_adjust:.1f} s)")
        return line


def _undistorted(rec, image_id: int, keypoints_xy: np.ndarray) -> np.ndarray:
    """Keypoints (OpenCV convention) in the camera's undistorted frame, in pixels: f * (x/z, y/z)."""
    cam = rec.cameras[rec.images[image_id].camera_id]
    normalised = np.asarray(cam.cam_from_img(np.asarray(keypoints_xy, np.float64) + 0.5))  # COLMAP's +0.5
    return normalised * float(cam.mean_focal_length())


def _pair_model(rec, a: int, b: int) -> PairModel:
    """The fundamental matrix between the undistorted frames of images a and b, from the model's poses."""
    Pa = np.asarray(rec.images[a].cam_from_world().matrix(), np.float64)
    Pb = np.asarray(rec.images[b].cam_from_world().matrix(), np.float64)
    R = Pb[:, :3] @ Pa[:, :3].T
    t = Pb[:, 3] - R @ Pa[:, 3]
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
    fa = float(rec.cameras[rec.images[a].camera_id].mean_focal_length())
    fb = float(rec.cameras[rec.images[b].camera_id].mean_focal_length())
    F = np.diag([1 / fb, 1 / fb, 1.0]) @ E @ np.diag([1 / fa, 1 / fa, 1.0])
    empty = np.zeros((0, 2), np.int64)
    return PairModel(a, b, "F", F, empty, empty)


def _shared_points(rec) -> dict[tuple[int, int], int]:
    """How many 3-D points each pair (a < b) of image ids observes in common."""
    counts: dict[tuple[int, int], int] = {}
    for point in rec.points3D.values():
        ids = sorted({el.image_id for el in point.track.elements})
        for i in range(len(ids)):
            for j in range(i + 1, len(ids)):
                counts[(ids[i], ids[j])] = counts.get((ids[i], ids[j]), 0) + 1
    return counts


def covisible_pairs(rec, min_shared: int = MIN_SHARED_POINTS) -> list[tuple[int, int]]:
    """Pairs (a < b) of registered image ids that observe at least ``min_shared`` common 3-D points."""
    return sorted(p for p, c in _shared_points(rec).items() if c >= min_shared)


def covisible_partners(rec, partners: int = PARTNERS, min_shared: int = MIN_SHARED_POINTS) -> list[tuple[int, int]]:
    """Pairs (a < b): each registered image with the ``partners`` images that share the most 3-D points with it
    (at least ``min_shared``; ties by the lower image id), as hloc's pairs from covisibility; the union."""
    ranked: dict[int, list[tuple[int, int]]] = {}
    for (a, b), c in _shared_points(rec).items():
        if c >= min_shared:
            ranked.setdefault(a, []).append((-c, b))
            ranked.setdefault(b, []).append((-c, a))
    return sorted({(min(a, b), max(a, b)) for a, lst in ranked.items() for _, b in sorted(lst)[:partners]})


def model_guided_matches(rec, keypoints: dict, descriptors: dict, *, threshold: float = DEFAULT_THRESHOLD,
                         ratio: float = DEFAULT_RATIO, min_shared: int = MIN_SHARED_POINTS,
                         partners: int = PARTNERS, n_threads: int | None = None,
                         progress: Callable[[int, int], None] | None = None) -> dict[tuple[int, int], np.ndarray]:
    """Matches under the model's geometry (module docstring), ``{(image id a, image id b): (m, 2) keypoint
    indices}``, a < b; ``keypoints`` / ``descriptors``: per registered image id, (n, >= 2) OpenCV pixel
    coordinates and (n, d) descriptors, in the database's keypoint order. ``progress(done, total)``: image
    pairs matched."""
    pairs = covisible_partners(rec, partners, min_shared)
    ids = sorted({i for p in pairs for i in p})
    offsets = np.cumsum([0] + [len(keypoints[i]) for i in ids])
    start = {i: int(o) for i, o in zip(ids, offsets)}
    if not ids:
        return {}
    xy = np.vstack([_undistorted(rec, i, np.asarray(keypoints[i])[:, :2]) for i in ids])
    X = np.vstack([np.asarray(descriptors[i]) for i in ids])
    no_bound = np.full(len(X), np.inf)
    invertible = np.isfinite(xy).all(axis=1)  # where the camera model has an undistorted position
    usable = {i: start[i] + np.flatnonzero(invertible[start[i]:start[i] + len(keypoints[i])]) for i in ids}

    def match(pair):
        a, b = pair
        rows, cols = usable[a], usable[b]
        i, j, _ = propose_links(_pair_model(rec, a, b), rows, cols, X, xy, no_bound, threshold=threshold,
                                ratio=ratio, max_sigma=1.0)
        return np.stack([i - start[a], j - start[b]], axis=1)

    workers = max(1, default_threads() if n_threads is None else int(n_threads))
    found = []
    with ThreadPoolExecutor(workers) as pool:
        for m in pool.map(match, pairs):  # in pair order whatever the threads do
            found.append(m)
            if progress is not None:
                progress(len(found), len(pairs))
    return {p: m for p, m in zip(pairs, found) if len(m)}


def triangulate(rec, database, image_dir, out_dir, keypoints: dict, descriptors: dict, *,
                threshold: float = DEFAULT_THRESHOLD, ratio: float = DEFAULT_RATIO,
                max_error: float = DEFAULT_MAX_ERROR, seed: int = 0, num_threads: int = -1,
                n_threads: int | None = None, bundle_adjust: bool = True, progress: ProgressArg = None):
    """The model with the points that model-guided matches add, bundle-adjusted unless ``bundle_adjust`` is
    False (module docstring), written to ``out_dir``, and what was done. ``database``: the model's COLMAP
    database, whose verified matches gain the new ones; ``rec`` is not changed; ``num_threads``: COLMAP's
    (-1: all cores). ``progress`` (:data:`dqm.progress.ProgressArg`): the image pairs matched,
    ``progress(done, total)``; COLMAP's triangulator and bundle adjustment report none, so with ``True`` a
    terminal shows the time each has taken instead."""
    pycolmap = require_pycolmap()
    t0 = time.perf_counter()
    found = model_guided_matches(rec, keypoints, descriptors, threshold=threshold, ratio=ratio,
                                 n_threads=n_threads, progress=resolve_progress(progress, "model-guided matches",
                                                                                unit="pairs"))
    n_matches = sum(len(m) for m in found.values())
    n_new = 0
    db = pycolmap.Database.open(str(database))
    try:
        for (a, b), m in found.items():
            if db.exists_two_view_geometry(a, b):
                geometry = db.read_two_view_geometry(a, b)
            else:  # images that share points through others, without a verified pair of their own
                geometry = pycolmap.TwoViewGeometry()
                geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            old = np.asarray(geometry.inlier_matches, np.int64).reshape(-1, 2)
            both = np.unique(np.vstack([old, m]), axis=0)
            n_new += len(both) - len(old)
            geometry.inlier_matches = np.ascontiguousarray(both.astype(np.uint32))
            if db.exists_two_view_geometry(a, b):
                db.update_two_view_geometry(a, b, geometry)
            else:
                db.write_two_view_geometry(a, b, geometry)
    finally:
        db.close()
    t1 = time.perf_counter()
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = int(seed)
    options.num_threads = int(num_threads)
    options.triangulation.complete_max_reproj_error = max_error
    options.triangulation.merge_max_reproj_error = max_error
    options.mapper.filter_max_reproj_error = max_error
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    before = (rec.num_points3D(), rec.compute_num_observations())
    last_id = max(rec.point3D_ids(), default=0)
    with ticking(progress, "triangulation (COLMAP's triangulator)"):
        dense = signals.interruptible(pycolmap.triangulate_points, pycolmap.Reconstruction(rec), str(database),
                                      str(image_dir), str(out), clear_points=False, options=options)
    # COLMAP's triangulator creates two-view points, which its incremental mapper never does: the new
    # points must be seen in 3 images or more, as the mapper's are when it creates them (the model's
    # own points keep their ids and stay)
    for point_id in [i for i in dense.point3D_ids() if i > last_id and dense.points3D[i].track.length() < 3]:
        dense.delete_point3D(point_id)
    stats = TriangulationStats(len(found), n_matches, n_new, before[0], dense.num_points3D(), before[1],
                               dense.compute_num_observations(), t1 - t0, time.perf_counter() - t1)
    if bundle_adjust:
        t2 = time.perf_counter()
        stats.reproj_before_adjust = dense.compute_mean_reprojection_error()
        ba = pycolmap.BundleAdjustmentOptions()  # COLMAP's defaults: the principal points stay
        ba.print_summary = LOG.isEnabledFor(logging.INFO)  # its report only with -v
        ba.ceres.solver_options.num_threads = int(num_threads)
        with glog_info_dropped(), ticking(progress, "bundle adjustment"), colmap_log_kept(pycolmap):
            signals.interruptible(pycolmap.bundle_adjustment, dense, ba)
        stats.reproj_after_adjust = dense.compute_mean_reprojection_error()
        stats.time_adjust = time.perf_counter() - t2
    dense.write(str(out))
    return dense, stats
