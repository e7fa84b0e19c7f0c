"""Run the camera-network experiment and score it against the simulator's ground truth.

:func:`run_experiment` simulates every time step, runs the pipeline of
:mod:`dqm.camnet.pipeline` for every method and returns an
:class:`ExperimentResult` holding every detection with its truth;
:func:`detection_curve` and :func:`localization_errors` turn it into the
numbers the seed paper reports:

* **detection PR curve** of each method over its detection threshold (the
  minimum number of matches with one reference, 0, 1, ..., up to the largest
  score): a (camera, time step) is a positive when the target is visible in
  it (>= ``SimConfig.min_visible_px`` pixels of its sides, exact from the
  renderer's id buffer); precision = detections that are positives /
  detections, recall = detected positives / positives; area by
  :func:`dqm.evaluation.pr_auc`;
* optionally (``sweep=True``) the PR curve over each method's own matching
  parameter (QuickMatch's ``rho``, the baselines' Lowe ratio) at the paper's
  10-match rule;
* **localization error**: distance in the ground plane between the estimated
  and the true target centre, over the detections at the paper's rule
  (score >= 10) that produced a position; mean +- std over all of them (what
  a user of the system sees, false detections included) and over the true
  positives only.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..evaluation import PRCurve, pr_auc
from ..progress import ProgressArg, resolve_progress
from ..validation import InputError, check_choice
from ..vision.features import ImageFeatures, extract
from .geometry import Camera, bounding_box, calibrate_range, estimate_homography, projected_quad
from .pipeline import (
    METHODS,
    PAPER_METHODS,
    Detection,
    PipelineConfig,
    detect,
    match_all,
    pairwise_pair_candidates,
    quickmatch_matches,
)
from .simulator import FrameTruth, SimConfig, World, build_world

DEFAULT_RHOS = (0.5, 0.6, 0.75, 0.9, 1.0, 1.1, 1.2, 1.4, 1.6)
DEFAULT_RATIOS = (0.6, 0.7, 0.75, 0.8, 0.85, 0.9)


@dataclass(frozen=True)
class Calibration:
    """The range constant measured on a known object (see :func:`calibrate`)."""

    range_constant: float
    distance: float
    box_height: float
    ideal: float  # fy * object height, for comparison
    matches: int


@dataclass
class Snapshot:
    """One time step kept for the feature-discovery figures: images, features and QuickMatch labels."""

    step: int
    images: List[np.ndarray]  # references first, then cameras
    features: List[ImageFeatures]
    labels: np.ndarray
    truths: List[FrameTruth]


@dataclass(frozen=True)
class Sweep:
    """A method's detection scores (per frame, frames in time-step-major order) at each parameter value."""

    method: str
    parameter: str  # "rho" or "ratio"
    scores: Dict[float, np.ndarray]
    visible: np.ndarray

    def curve(self, min_matches: int) -> PRCurve:
        """PR curve over the parameter at a fixed detection rule (score >= min_matches)."""
        qs = sorted(self.scores)
        pts = [_pr_points(self.scores[q], self.visible, [min_matches]) for q in qs]
        return PRCurve(self.method, self.parameter, np.array(qs, float), np.array([p[0][0] for p in pts]),
                       np.array([p[1][0] for p in pts]))

    def table(self, min_matches: int) -> List[Dict[str, float]]:
        """Per parameter value: detection PR AUC over the match count, precision and recall at the rule."""
        out = []
        for q in sorted(self.scores):
            sc = self.scores[q]
            thr = np.arange(0, int(sc.max()) + 1 if len(sc) else 1)
            p, r = _pr_points(sc, self.visible, thr)
            (p1,), (r1,) = _pr_points(sc, self.visible, [min_matches])
            out.append({self.parameter: q, "auc": pr_auc(r, p), "precision": float(p1), "recall": float(r1),
                        "mean_score_positive": float(sc[self.visible].mean()) if self.visible.any() else 0.0,
                        "mean_score_negative": float(sc[~self.visible].mean()) if (~self.visible).any() else 0.0})
        return out


@dataclass
class ExperimentResult:
    """Every detection of every method with the ground truth of its frame."""

    sim: SimConfig
    pipeline: PipelineConfig
    methods: Tuple[str, ...]
    world: World
    calibration: Calibration
    truths: Dict[Tuple[int, int], FrameTruth]  # (step, camera) -> truth
    detections: Dict[str, List[Detection]]
    sweeps: Dict[str, "Sweep"] = field(default_factory=dict)
    snapshot: Optional[Snapshot] = None
    timings: Dict[str, float] = field(default_factory=dict)
    n_features: Dict[str, float] = field(default_factory=dict)
    #: ``quickmatch-online`` only: :meth:`dqm.camnet.online.OnlineMatcher.stats` (update time per frame, ...)
    online: Dict[str, float] = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return len(self.truths)

    @property
    def n_positive(self) -> int:
        return int(sum(t.visible for t in self.truths.values()))

    def arrays(self, method: str) -> Dict[str, np.ndarray]:
        """Per-frame arrays of a method (frames in step-major order).

        ``score``, ``visible``, ``estimate`` (n, 2; NaN = none), ``truth`` (n, 2),
        ``camera``, ``step``, ``decoy`` and ``target_px`` (pixels of decoy / target in view).
        """
        check_choice(method, "method", self.methods)
        dets = self.detections[method]
        tr = [self.truths[(d.step, d.camera)] for d in dets]
        est = np.array([d.estimate if d.estimate is not None else (np.nan, np.nan) for d in dets], float)
        return {
            "score": np.array([d.score for d in dets], np.int64),
            "visible": np.array([t.visible for t in tr], bool),
            "estimate": est.reshape(-1, 2),
            "truth": np.array([t.position for t in tr], float).reshape(-1, 2),
            "camera": np.array([d.camera for d in dets], np.int64),
            "step": np.array([d.step for d in dets], np.int64),
            "decoy": np.array([t.decoy_px for t in tr], np.int64),
            "target_px": np.array([t.target_px for t in tr], np.int64),
        }


def _pr_points(score: np.ndarray, positive: np.ndarray, thresholds: Sequence[float]):
    n_pos = int(positive.sum())
    prec, rec = [], []
    for m in thresholds:
        det = score >= m
        n = int(det.sum())
        tp = int((det & positive).sum())
        prec.append(tp / n if n else 1.0)
        rec.append(tp / n_pos if n_pos else 1.0)
    return np.array(prec), np.array(rec)


def detection_curve(result: ExperimentResult, method: str) -> PRCurve:
    """Detection PR curve of one method over the minimum match count 0, 1, ..., max score."""
    a = result.arrays(method)
    top = int(a["score"].max()) if len(a["score"]) else 0
    thr = np.arange(0, top + 1)
    p, r = _pr_points(a["score"], a["visible"], thr)
    return PRCurve(method, "min matches", thr.astype(float), p, r)


def operating_point(result: ExperimentResult, method: str, min_matches: Optional[int] = None) -> Dict[str, float]:
    """Precision, recall and counts of a method at one detection threshold (default: the config's)."""
    m = result.pipeline.min_matches if min_matches is None else int(min_matches)
    a = result.arrays(method)
    det = a["score"] >= m
    tp = int((det & a["visible"]).sum())
    n, pos = int(det.sum()), int(a["visible"].sum())
    return {"min_matches": m, "detections": n, "true_positives": tp, "false_positives": n - tp,
            "positives": pos, "precision": tp / n if n else 1.0, "recall": tp / pos if pos else 1.0}


@dataclass(frozen=True)
class ErrorStats:
    """Localization errors (metres) of the detections at the paper's rule."""

    errors: np.ndarray  # all detections with an estimate
    errors_tp: np.ndarray  # true positives with an estimate
    n_detections: int
    n_without_estimate: int

    @staticmethod
    def _ms(e: np.ndarray) -> Tuple[float, float, float]:
        if len(e) == 0:
            return math.nan, math.nan, math.nan
        return float(e.mean()), float(e.std()), float(np.median(e))

    @property
    def mean(self) -> float:
        return self._ms(self.errors)[0]

    @property
    def std(self) -> float:
        return self._ms(self.errors)[1]

    @property
    def median(self) -> float:
        return self._ms(self.errors)[2]

    def as_dict(self) -> Dict[str, float]:
        m, s, med = self._ms(self.errors)
        mt, st, medt = self._ms(self.errors_tp)
        return {"mean": m, "std": s, "median": med, "n": int(len(self.errors)),
                "mean_tp": mt, "std_tp": st, "median_tp": medt, "n_tp": int(len(self.errors_tp)),
                "n_detections": self.n_detections, "n_without_estimate": self.n_without_estimate}


def localization_errors(result: ExperimentResult, method: str, min_matches: Optional[int] = None) -> ErrorStats:
    """Ground-plane distance between estimated and true target centre for every detection."""
    m = result.pipeline.min_matches if min_matches is None else int(min_matches)
    a = result.arrays(method)
    det = a["score"] >= m
    has = det & np.isfinite(a["estimate"]).all(axis=1)
    err = np.linalg.norm(a["estimate"] - a["truth"], axis=1)
    return ErrorStats(err[has], err[has & a["visible"]], int(det.sum()), int((det & ~has).sum()))


def common_errors(result: ExperimentResult, min_matches: Optional[int] = None,
                  methods: Optional[Sequence[str]] = None) -> Dict[str, ErrorStats]:
    """Localization errors of every method over the frames that **all** methods detected and localized.

    Removes the selection effect of comparing methods on different frames (a
    stricter method localizes only the easy ones). ``methods``: the methods
    compared (default: all of the run's).
    """
    m = result.pipeline.min_matches if min_matches is None else int(min_matches)
    methods = result.methods if methods is None else tuple(methods)
    arrs = {meth: result.arrays(meth) for meth in methods}
    ok = np.ones(result.n_frames, bool)
    for a in arrs.values():
        ok &= (a["score"] >= m) & np.isfinite(a["estimate"]).all(axis=1)
    out = {}
    for meth, a in arrs.items():
        err = np.linalg.norm(a["estimate"] - a["truth"], axis=1)
        out[meth] = ErrorStats(err[ok], err[ok & a["visible"]], int(ok.sum()), 0)
    return out


def calibrate(world: World, refs: Sequence[ImageFeatures], config: PipelineConfig,
              distance: float = 2.0) -> Calibration:
    """Measure the range constant as one would with a real object of known size.

    The target is placed with side 0 fronto-parallel at ``distance`` metres in
    front of a level camera (no clutter, no degradation), its box is measured
    by the pipeline itself (SIFT, BF matching with reference 0, RANSAC
    homography, box) and ``k = box height x distance``.
    """
    from .simulator import BoxObject

    cfg = world.config
    cam = Camera("calibration", np.array([0.0, 0.0, cfg.camera_height]), 0.0, 0.0, world.intrinsics)
    tw, td, th = cfg.target_size
    target = BoxObject("target", (distance + td / 2.0, 0.0), math.pi, cfg.target_size, cfg.target_elevation,
                       ("target0", "target1", "target2", "target3"), cfg.target_px_per_m)
    img, _ = world.render_view(cam, target, np.random.default_rng(0), clean=True, static=False)
    feats = extract(img, config.preset, config.max_features)
    cand = pairwise_pair_candidates(refs[0], feats, "bf", config.seed)
    a, b = cand.select(config.ratio)
    H, _ = estimate_homography(refs[0].keypoints[a, :2], feats.keypoints[b, :2], config.ransac_threshold,
                               seed=config.seed)
    ref_h, ref_w = world.references[0].shape
    quad = projected_quad(H, ref_w, ref_h) if H is not None else None
    if quad is None:
        raise RuntimeError("calibration failed: the target at the calibration distance was not matched")
    box = bounding_box(quad)
    h = box[3] - box[1]
    return Calibration(calibrate_range(h, distance), distance, h, world.intrinsics.fy * th, len(a))


def _behind(world: World) -> List[float]:
    tw, td, _ = world.config.target_size
    return [td / 2.0, tw / 2.0, td / 2.0, tw / 2.0]


def run_experiment(sim: Optional[SimConfig] = None, pipeline: Optional[PipelineConfig] = None,  # noqa: C901 - the steps in order
                   methods: Sequence[str] = METHODS, *, sweep: bool = False,
                   rhos: Sequence[float] = DEFAULT_RHOS, ratios: Sequence[float] = DEFAULT_RATIOS,
                   snapshot_step: Optional[int] = -1, progress: ProgressArg = None) -> ExperimentResult:
    """Simulate, match, detect and localize at every time step; keep everything for scoring.

    ``snapshot_step``: the time step whose QuickMatch clustering is kept for the
    feature-discovery figures (-1: the step where the target is visible in the
    most cameras; None: keep none; needs ``"quickmatch"`` in ``methods``).
    ``sweep``: also keep every frame's score at each of ``rhos`` (QuickMatch,
    re-run per rho) and ``ratios`` (BF, FLANN): :class:`Sweep`; plus the
    ablation ``sweeps["quickmatch-per-camera"]``: QuickMatch over the references
    and one camera at a time (no help from the other cameras), at ``rho``.
    The QuickMatch variants (``quickmatch-quadratic``, ``quickmatch-online``)
    are not swept.

    ``quickmatch-online`` feeds one :class:`dqm.camnet.online.OnlineMatcher`
    the frames camera by camera within each step (the order they arrive in);
    its update times go to ``result.online``.
    """
    sim = sim if sim is not None else SimConfig()
    pipeline = pipeline if pipeline is not None else PipelineConfig()
    if not isinstance(sim, SimConfig):
        raise InputError(f"sim must be a SimConfig, got {type(sim).__name__}")
    if not isinstance(pipeline, PipelineConfig):
        raise InputError(f"pipeline must be a PipelineConfig, got {type(pipeline).__name__}")
    methods = tuple(methods)
    if not methods:
        raise InputError("no methods given")
    for m in methods:
        check_choice(m, "method", METHODS)
    if len(set(methods)) != len(methods):
        raise InputError(f"methods repeat: {methods}")
    for name, vals in (("rhos", rhos), ("ratios", ratios)):
        if sweep and (not len(vals) or not all(isinstance(v, (int, float)) and v > 0 for v in vals)):
            raise InputError(f"{name} must be positive numbers, got {vals!r}")
    t_start = time.perf_counter()
    world = build_world(sim)
    timings = {"simulate": 0.0, "sift": 0.0}
    t = time.perf_counter()
    refs = [extract(r, pipeline.preset, pipeline.max_features) for r in world.references]
    if min(len(r) for r in refs) < 4:
        raise RuntimeError(f"a reference image has fewer than 4 SIFT features ({[len(r) for r in refs]})")
    timings["sift"] += time.perf_counter() - t
    ref_sizes = [(r.shape[1], r.shape[0]) for r in world.references]
    calib = calibrate(world, refs, pipeline)
    behind = _behind(world)
    truths: Dict[Tuple[int, int], FrameTruth] = {}
    dets: Dict[str, List[Detection]] = {m: [] for m in methods}
    sweep_scores: Dict[str, Dict[float, List[int]]] = {m: {} for m in methods}
    sweep_visible: List[bool] = []
    per_cam: List[int] = []
    n_feat: List[int] = []
    best_vis, snap = -1, None
    want_snap = snapshot_step is not None and "quickmatch" in methods
    online = None
    if "quickmatch-online" in methods:
        from .online import OnlineMatcher

        t = time.perf_counter()
        online = OnlineMatcher(refs, len(world.cameras), pipeline.rho)
        timings["match_quickmatch-online"] = time.perf_counter() - t
    bar = resolve_progress(progress, "camnet")
    for step in range(world.n_steps):
        t = time.perf_counter()
        views = [world.render(c, step) for c in range(len(world.cameras))]
        timings["simulate"] += time.perf_counter() - t
        t = time.perf_counter()
        cams = [extract(img, pipeline.preset, pipeline.max_features) for img, _ in views]
        timings["sift"] += time.perf_counter() - t
        n_feat += [len(f) for f in cams]
        for c, (_, tr) in enumerate(views):
            truths[(step, c)] = tr
            sweep_visible.append(tr.visible)
        for method in methods:
            if method == "quickmatch-online":  # frames arrive one camera at a time; each scored on arrival
                for c, cam in enumerate(world.cameras):
                    t = time.perf_counter()
                    row = online.update(step, c, cams[c])
                    timings[f"match_{method}"] += time.perf_counter() - t
                    t = time.perf_counter()
                    dets[method].append(detect(method, step, c, row, refs, ref_sizes, cams[c], cam,
                                               calib.range_constant, behind, pipeline))
                    timings[f"localize_{method}"] = (timings.get(f"localize_{method}", 0.0)
                                                     + time.perf_counter() - t)
                continue
            t = time.perf_counter()
            matches, extra = match_all(method, refs, cams, pipeline)
            timings[f"match_{method}"] = timings.get(f"match_{method}", 0.0) + time.perf_counter() - t
            t = time.perf_counter()
            for c, cam in enumerate(world.cameras):
                dets[method].append(detect(method, step, c, matches[c], refs, ref_sizes, cams[c], cam,
                                           calib.range_constant, behind, pipeline))
            timings[f"localize_{method}"] = timings.get(f"localize_{method}", 0.0) + time.perf_counter() - t
            if sweep and method in PAPER_METHODS:
                t = time.perf_counter()
                params = rhos if method == "quickmatch" else ratios
                for q in params:
                    if method == "quickmatch":
                        mm = matches if q == pipeline.rho else quickmatch_matches(refs, cams, q)[0]
                        row = [max(len(m[0]) for m in mm[c]) for c in range(len(cams))]
                    else:
                        cands = extra["candidates"]
                        row = [max(int((cd.ratio < q).sum()) for cd in cands[c]) for c in range(len(cams))]
                    sweep_scores[method].setdefault(float(q), []).extend(row)
                if method == "quickmatch":  # ablation: each camera clustered with the references alone
                    per_cam.extend(max(len(m[0]) for m in quickmatch_matches(refs, [cam_f], pipeline.rho)[0][0])
                                   for cam_f in cams)
                timings[f"sweep_{method}"] = timings.get(f"sweep_{method}", 0.0) + time.perf_counter() - t
            if method == "quickmatch" and want_snap:
                nvis = sum(tr.visible for _, tr in views)
                take = (step == snapshot_step) if snapshot_step >= 0 else nvis > best_vis
                if take:
                    best_vis = nvis
                    snap = Snapshot(step, list(world.references) + [img for img, _ in views], list(refs) + cams,
                                    extra["labels"], [tr for _, tr in views])
        if bar is not None:
            bar(step + 1, world.n_steps)
    timings["total"] = time.perf_counter() - t_start
    sweeps = {m: Sweep(m, "rho" if m == "quickmatch" else "ratio",
                       {q: np.array(v, np.int64) for q, v in sweep_scores[m].items()}, np.array(sweep_visible, bool))
              for m in methods if m in PAPER_METHODS} if sweep else {}
    if per_cam:
        sweeps["quickmatch-per-camera"] = Sweep("quickmatch-per-camera", "rho",
                                                {float(pipeline.rho): np.array(per_cam, np.int64)},
                                                np.array(sweep_visible, bool))
    nf = np.array(n_feat, float)
    return ExperimentResult(sim, pipeline, methods, world, calib, truths, dets, sweeps, snap, timings,
                            {"per_camera_image_mean": float(nf.mean()) if len(nf) else 0.0,
                             "per_reference_mean": float(np.mean([len(r) for r in refs]))},
                            online.stats() if online is not None else {})
