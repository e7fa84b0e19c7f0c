"""Every number and finding of a camera-network experiment, computed once.

:func:`build_summary` turns an :class:`~dqm.camnet.experiment.ExperimentResult`
(and the other seeds' :func:`seed_row` rows) into a :class:`CamnetSummary`:
the per-method scores, the online-vs-batch and kernel comparisons, the
comparison with the seed paper, the other seeds' table and its means. Both
outputs of :mod:`dqm.camnet.report` read that one object - ``camnet.json`` is
:meth:`CamnetSummary.as_json` and ``camnet.md`` is rendered from its fields -
so the JSON and the markdown cannot disagree. Nothing here formats text.
"""
from __future__ import annotations

import dataclasses
import math
import os
import platform
from dataclasses import dataclass
from typing import Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from ..evaluation import PRCurve
from .experiment import (
    Calibration,
    ErrorStats,
    ExperimentResult,
    Sweep,
    common_errors,
    detection_curve,
    localization_errors,
    operating_point,
)
from .pipeline import KERNEL, LABELS, PAPER_METHODS, PAPER_RHO, PipelineConfig
from .simulator import SimConfig

#: the QuickMatch variants compared in the online section, in table order
QM_VARIANTS = ("quickmatch", "quickmatch-quadratic", "quickmatch-online")
#: a localization error above this (metres) counts as a large error in the comparison with the paper
LARGE_ERROR_M = 1.0
#: PR AUCs closer than this: the other cameras "add little" to QuickMatch
SAME_AUC = 0.02


class _Fields:
    """``as_json``: every field of a summary dataclass as it is (numbers, strings and nested plain data)."""

    def as_json(self) -> Dict[str, object]:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class PaperResult(_Fields):
    """One method's numbers in the seed paper's camera-network experiment."""

    auc: float  #: detection PR AUC
    mean: float  #: localization error, metres
    std: float


#: the seed paper's results (camera-network experiment)
PAPER: Dict[str, PaperResult] = {
    "quickmatch": PaperResult(0.64, 0.21, 0.43),
    "bf": PaperResult(0.49, 0.23, 0.40),
    "flann": PaperResult(0.45, 0.62, 1.17),
}


def method_label(pipeline: PipelineConfig, method: str) -> str:
    """A method's name with the parameter it ran at, as the tables and figures show it."""
    if method == "quickmatch":
        return f"QuickMatch (rho {pipeline.rho:g})"
    if method == "quickmatch-quadratic":
        return f"QuickMatch quadratic kernel (rho {pipeline.rho:g})"
    if method == "quickmatch-online":
        return f"QuickMatch online, quadratic (rho {pipeline.rho:g})"
    return f"{LABELS[method]} (ratio {pipeline.ratio:g})"


@dataclass(frozen=True)
class OperatingPoint(_Fields):
    """A method at the detection rule (score >= ``min_matches``): see :func:`~dqm.camnet.experiment.operating_point`."""

    min_matches: int
    detections: int
    true_positives: int
    false_positives: int
    positives: int
    precision: float
    recall: float


@dataclass(frozen=True)
class ErrorSummary(_Fields):
    """Localization errors (metres; NaN when there are none): see :class:`~dqm.camnet.experiment.ErrorStats`."""

    mean: float
    std: float
    median: float
    n: int  #: detections with a position
    mean_tp: float  #: over the true positives only
    std_tp: float
    median_tp: float
    n_tp: int
    n_detections: int
    n_without_estimate: int  #: detections whose homography gave no box

    @classmethod
    def of(cls, stats: ErrorStats) -> "ErrorSummary":
        return cls(**stats.as_dict())


@dataclass(frozen=True)
class SweepRow:
    """One value of a method's matching parameter (``rho`` or ``ratio``) at the detection rule."""

    value: float
    auc: float  #: detection PR AUC over the match count
    precision: float
    recall: float
    mean_score_positive: float  #: mean best-reference matches, target visible
    mean_score_negative: float  #: the same, target not visible

    @classmethod
    def of(cls, parameter: str, row: Mapping[str, float]) -> "SweepRow":
        return cls(row[parameter], row["auc"], row["precision"], row["recall"], row["mean_score_positive"],
                   row["mean_score_negative"])

    def as_json(self, parameter: str) -> Dict[str, float]:
        return {parameter: self.value, "auc": self.auc, "precision": self.precision, "recall": self.recall,
                "mean_score_positive": self.mean_score_positive, "mean_score_negative": self.mean_score_negative}


@dataclass(frozen=True)
class SweepSummary:
    """A method's detection over its own matching parameter: one :class:`SweepRow` per value and the PR curve."""

    parameter: str  #: "rho" or "ratio"
    table: Tuple[SweepRow, ...]
    curve: PRCurve

    @classmethod
    def of(cls, sweep: Sweep, min_matches: int) -> "SweepSummary":
        return cls(sweep.parameter, tuple(SweepRow.of(sweep.parameter, r) for r in sweep.table(min_matches)),
                   sweep.curve(min_matches))

    def row(self, value: float, tol: float = 0.0) -> Optional[SweepRow]:
        """The row at ``value`` (exactly, or within ``tol``), None if the sweep has none."""
        return next((r for r in self.table if (r.value == value if tol == 0 else abs(r.value - value) < tol)), None)

    def as_json(self) -> Dict[str, object]:
        return {"parameter": self.parameter, "table": [r.as_json(self.parameter) for r in self.table],
                "curve": self.curve.as_dict()}


@dataclass(frozen=True)
class MethodSummary:
    """One method's scores: detection PR curve and AUC, the rule's operating point, localization errors."""

    method: str
    label: str  #: :func:`method_label`
    pr_auc: float
    curve: PRCurve  #: over the minimum match count
    at_rule: OperatingPoint
    errors: ErrorSummary
    paper: Optional[PaperResult]  #: the seed paper's numbers (its three methods only)
    kernel: Optional[str]  #: QuickMatch's kernel (QuickMatch variants only)
    sweep: Optional[SweepSummary]  #: over the matching parameter (with ``sweep=True``)

    def as_json(self) -> Dict[str, object]:
        d: Dict[str, object] = {"label": self.label, "pr_auc": self.pr_auc, "curve": self.curve.as_dict(),
                                "at_rule": self.at_rule.as_json(), "errors": self.errors.as_json(),
                                "paper": self.paper.as_json() if self.paper else None}
        if self.kernel is not None:
            d["kernel"] = self.kernel
        if self.sweep is not None:
            d["sweep"] = self.sweep.as_json()
        return d


@dataclass(frozen=True)
class ScoreComparison(_Fields):
    """Online against batch QuickMatch (quadratic kernel), frame by frame: the best-reference scores."""

    frames: int
    same_score: int
    same_score_last_camera: int  #: frames of the last camera, whose online set is the batch one
    last_camera_frames: int
    mean_abs_score_difference: float
    max_abs_score_difference: int
    online_higher: int
    online_lower: int
    detection_differs: int  #: frames where the rule (score >= min_matches) decides differently


@dataclass(frozen=True)
class MethodContrast:
    """Two methods side by side: detection PR AUC and mean localization error (metres)."""

    first: str
    second: str
    pr_auc: Tuple[float, float]
    error_mean: Tuple[float, float]

    @classmethod
    def of(cls, methods: Mapping[str, MethodSummary], first: str, second: str) -> "MethodContrast":
        a, b = methods[first], methods[second]
        return cls(first, second, (a.pr_auc, b.pr_auc), (a.errors.mean, b.errors.mean))

    def as_json(self) -> Dict[str, object]:
        return {"methods": [self.first, self.second], "pr_auc": list(self.pr_auc),
                "error_mean": list(self.error_mean)}


@dataclass(frozen=True)
class OnlineSummary:
    """Online QuickMatch against batch: clustering times, per-frame score differences, kernel and online effects."""

    stats: Dict[str, float]  #: :meth:`dqm.camnet.online.OnlineMatcher.stats` (update times, set sizes)
    batch_per_step_s: Dict[str, float]  #: batch QuickMatch's clustering time per time step, per variant
    online_per_step_s: Optional[float]  #: one update per camera: the online clustering time per step
    vs_batch_quadratic: Optional[ScoreComparison]
    #: one online update / one batch run (quadratic) over the whole step
    update_over_batch: Optional[float]
    #: the online clustering time per step / batch (quadratic) per step
    online_over_batch: Optional[float]
    kernel: Optional[MethodContrast]  #: Gaussian vs quadratic kernel, both batch
    online_vs_batch: Optional[MethodContrast]  #: online vs batch, both quadratic (with the score comparison)

    @property
    def has_update_times(self) -> bool:
        return "update_mean_s" in self.stats

    @property
    def features_mean(self) -> float:
        """Features present in the online set on average."""
        return self.stats.get("features_mean", 0)

    @property
    def references_s(self) -> float:
        """The references' one-time add, seconds."""
        return self.stats.get("references_s", 0)

    def as_json(self) -> Dict[str, object]:
        out: Dict[str, object] = dict(self.stats)
        out["batch_per_step_s"] = dict(self.batch_per_step_s)
        if self.online_per_step_s is not None:
            out["online_per_step_s"] = self.online_per_step_s
        if self.vs_batch_quadratic is not None:
            out["vs_batch_quadratic"] = self.vs_batch_quadratic.as_json()
        for name in ("update_over_batch", "online_over_batch"):
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        for name in ("kernel", "online_vs_batch"):
            if getattr(self, name) is not None:
                out[f"contrast_{name}"] = getattr(self, name).as_json()
        return out


def online_summary(result: ExperimentResult, methods: Mapping[str, MethodSummary]) -> OnlineSummary:
    """Online QuickMatch against batch (the run must include ``quickmatch-online``)."""
    steps, C = result.world.n_steps, len(result.world.cameras)
    stats = dict(result.online)
    per_step = {m: result.timings[f"match_{m}"] / steps for m in ("quickmatch", "quickmatch-quadratic")
                if f"match_{m}" in result.timings and steps}
    online_step = stats["update_mean_s"] * C if "update_mean_s" in stats else None
    vs = None
    if "quickmatch-quadratic" in result.methods:
        on, ba = result.arrays("quickmatch-online"), result.arrays("quickmatch-quadratic")
        diff = on["score"] - ba["score"]
        k = result.pipeline.min_matches
        last = on["camera"] == C - 1
        vs = ScoreComparison(
            frames=int(len(diff)), same_score=int((diff == 0).sum()),
            same_score_last_camera=int((diff[last] == 0).sum()), last_camera_frames=int(last.sum()),
            mean_abs_score_difference=float(np.abs(diff).mean()) if len(diff) else 0.0,
            max_abs_score_difference=int(np.abs(diff).max()) if len(diff) else 0,
            online_higher=int((diff > 0).sum()), online_lower=int((diff < 0).sum()),
            detection_differs=int(((on["score"] >= k) != (ba["score"] >= k)).sum()))
    b = per_step.get("quickmatch-quadratic")
    timed = "update_mean_s" in stats and bool(b)
    return OnlineSummary(
        stats, per_step, online_step, vs,
        update_over_batch=stats["update_mean_s"] / b if timed else None,
        online_over_batch=online_step / b if timed else None,
        kernel=(MethodContrast.of(methods, "quickmatch", "quickmatch-quadratic")
                if "quickmatch" in methods and "quickmatch-quadratic" in methods else None),
        online_vs_batch=MethodContrast.of(methods, "quickmatch-online", "quickmatch-quadratic") if vs else None)


# --- several seeds ---------------------------------------------------------------------------
@dataclass(frozen=True)
class SeedRow:
    """One seed's headline numbers (the robustness table); JSON form: :func:`seed_row`."""

    seed: int
    frames: int
    positives: int
    auc: Dict[str, float]  #: detection PR AUC per method
    error: Dict[str, Tuple[float, float, int]]  #: per method: localization error mean, std, count
    auc_quickmatch_paper_rho: Optional[float] = None  #: QuickMatch at the paper's rho (if swept)
    auc_quickmatch_per_camera: Optional[float] = None  #: each camera clustered with the references alone

    @classmethod
    def of(cls, result: ExperimentResult) -> "SeedRow":
        auc: Dict[str, float] = {}
        error: Dict[str, Tuple[float, float, int]] = {}
        for m in result.methods:
            auc[m] = detection_curve(result, m).auc()
            e = localization_errors(result, m)
            error[m] = (e.mean, e.std, len(e.errors))
        paper_rho = per_camera = None
        sw = result.sweeps.get("quickmatch")
        if sw is not None and PAPER_RHO in sw.scores:
            t = {r["rho"]: r for r in sw.table(result.pipeline.min_matches)}
            paper_rho = t[PAPER_RHO]["auc"]
        abl = result.sweeps.get("quickmatch-per-camera")
        if abl is not None:
            per_camera = abl.table(result.pipeline.min_matches)[0]["auc"]
        return cls(result.sim.seed, result.n_frames, result.n_positive, auc, error, paper_rho, per_camera)

    @classmethod
    def from_json(cls, row: Mapping[str, object]) -> "SeedRow":
        return cls(row["seed"], row["frames"], row["positives"], dict(row["auc"]),
                   {m: tuple(e) for m, e in row["error"].items()}, row.get("auc_quickmatch_paper_rho"),
                   row.get("auc_quickmatch_per_camera"))

    def as_json(self) -> Dict[str, object]:
        d: Dict[str, object] = {"seed": self.seed, "frames": self.frames, "positives": self.positives,
                                "auc": dict(self.auc), "error": dict(self.error)}
        if self.auc_quickmatch_paper_rho is not None:
            d["auc_quickmatch_paper_rho"] = self.auc_quickmatch_paper_rho
        if self.auc_quickmatch_per_camera is not None:
            d["auc_quickmatch_per_camera"] = self.auc_quickmatch_per_camera
        return d


def seed_row(result: ExperimentResult) -> Dict[str, object]:
    """One seed's headline numbers (for the robustness table), QuickMatch at the paper's rho if swept."""
    return SeedRow.of(result).as_json()


@dataclass(frozen=True)
class SeedMeans(_Fields):
    """The robustness table's last row: each column's mean over the seeds (errors: over seeds that have one)."""

    auc: Dict[str, float]
    auc_quickmatch_paper_rho: Optional[float]
    auc_quickmatch_per_camera: Optional[float]
    error: Dict[str, float]


def _nanmean(values) -> float:
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else math.nan


@dataclass(frozen=True)
class SeedsSummary:
    """This and other seeds' runs: the rows, which optional columns all have, and (2+ seeds) the means."""

    rows: Tuple[SeedRow, ...]
    methods: Tuple[str, ...]  #: the table's methods (the main run's)
    paper_rho_column: bool
    per_camera_column: bool
    means: Optional[SeedMeans]

    @classmethod
    def of(cls, rows: Sequence[SeedRow], methods: Sequence[str]) -> "SeedsSummary":
        paper_col = all(r.auc_quickmatch_paper_rho is not None for r in rows)
        pc_col = all(r.auc_quickmatch_per_camera is not None for r in rows)
        means = None
        if len(rows) > 1:
            means = SeedMeans(
                {m: float(np.mean([r.auc[m] for r in rows])) for m in methods},
                float(np.mean([r.auc_quickmatch_paper_rho for r in rows])) if paper_col else None,
                float(np.mean([r.auc_quickmatch_per_camera for r in rows])) if pc_col else None,
                {m: _nanmean([r.error[m][0] for r in rows]) for m in methods})
        return cls(tuple(rows), tuple(methods), paper_col, pc_col, means)


# --- the comparison with the paper -----------------------------------------------------------
@dataclass(frozen=True)
class ScoreDifference:
    """|score(a) - score(b)| per frame: mean and maximum (matches with the best reference)."""

    mean: float
    max: int


@dataclass(frozen=True)
class RhoFinding:
    """QuickMatch at the paper's rho against the rho used here (from the rho sweep)."""

    paper: SweepRow  #: at :data:`~dqm.camnet.pipeline.PAPER_RHO`
    used: SweepRow  #: at the run's rho
    best_baseline_auc: float  #: the best of BF / FLANN at their ratio
    above_best_baseline: bool  #: the paper rho's AUC >= that
    seeds_at_or_above: Optional[int]  #: over 2+ seeds: seeds where the paper rho's AUC >= their best baseline


@dataclass(frozen=True)
class SweepEnd:
    """Where a method's PR curve over its matching parameter ends: largest recall and largest parameter."""

    method: str
    recall: float
    parameter: float


@dataclass(frozen=True)
class PerCameraFinding:
    """QuickMatch with each camera clustered alone with the references, against all cameras at once."""

    auc_per_camera: float
    auc_all: float
    effect: str  #: of the other cameras: "little", "help" or "hurt"
    quickmatch: SweepRow  #: QuickMatch's sweep row at the run's rho
    bf: SweepRow  #: BF's sweep row at the run's ratio


@dataclass(frozen=True)
class FalseDetections:
    """False detections at the rule, by what was in view."""

    total: int
    decoy: int  #: the decoy poster in view
    partial: int  #: some of the target in view, below the visibility threshold
    scene: int  #: neither: the scene's own texture


@dataclass(frozen=True)
class LargeErrors:
    """Detections localized more than :data:`LARGE_ERROR_M` off, and how many of them are false detections."""

    n: int
    n_false: int


@dataclass(frozen=True)
class PaperComparison(_Fields):
    """The comparison with the seed paper over its methods present in the run (at least two of them)."""

    methods: Tuple[str, ...]  #: of quickmatch, bf, flann, in that order
    quickmatch_highest: Optional[bool]  #: QuickMatch's PR AUC is the highest (None without QuickMatch)
    bf_vs_flann: Optional[ScoreDifference]  #: with QuickMatch, BF and FLANN
    seeds_quickmatch_highest: Optional[int]  #: over 2+ seeds: seeds where QuickMatch's AUC is the highest
    n_seeds: int
    rho: Optional[RhoFinding]  #: with QuickMatch's sweep including the paper's rho
    sweep_ends: Tuple[SweepEnd, ...]  #: QuickMatch first, then the swept baselines (with ``rho`` only)
    per_camera: Optional[PerCameraFinding]
    false_detections: Dict[str, FalseDetections]
    largest_spread: str  #: the method whose localization error has the largest std
    large_errors: Dict[str, LargeErrors]
    calibration_error_pct: float  #: measured range constant vs its ideal value, percent


def paper_comparison(result: ExperimentResult, methods: Mapping[str, MethodSummary],
                     quickmatch_per_camera: Optional[SweepRow],
                     seed_rows: Sequence[SeedRow] = ()) -> Optional[PaperComparison]:
    """The comparison with the seed paper; None with fewer than two of the paper's methods."""
    have = tuple(m for m in PAPER_METHODS if m in methods)
    if len(have) < 2:
        return None
    pl = result.pipeline
    auc = {m: methods[m].pr_auc for m in have}
    baselines = [m for m in have if m != "quickmatch"]
    qm = methods.get("quickmatch") if "quickmatch" in have else None
    first = bf_flann = wins = None
    if qm is not None:
        first = sorted(have, key=lambda m: -auc[m])[0] == "quickmatch"
        if "bf" in have and "flann" in have:
            diff = np.abs(result.arrays("bf")["score"] - result.arrays("flann")["score"])
            bf_flann = ScoreDifference(float(diff.mean()), int(diff.max()))
        if len(seed_rows) > 1:
            wins = sum(all(r.auc["quickmatch"] >= r.auc[m] for m in baselines) for r in seed_rows)
    rho, ends = None, ()
    if qm is not None and qm.sweep is not None:
        paper = qm.sweep.row(PAPER_RHO)
        if paper is not None:
            best = max(auc[m] for m in baselines)
            seeds = None
            if len(seed_rows) >= 2 and seed_rows[0].auc_quickmatch_paper_rho is not None:
                seeds = sum(r.auc_quickmatch_paper_rho >= max(r.auc[m] for m in baselines) for r in seed_rows)
            used = qm.sweep.row(pl.rho)
            if used is None:
                raise ValueError(f"QuickMatch's sweep lacks the run's rho {pl.rho:g}")
            rho = RhoFinding(paper, used, best, paper.auc >= best, seeds)
            ends = tuple(SweepEnd(m, float(np.max(s.curve.recall)), float(np.max(s.curve.thresholds)))
                         for m in have for s in [methods[m].sweep] if s is not None)
    per_camera = None
    if quickmatch_per_camera is not None and qm is not None and "bf" in have and qm.sweep is not None \
            and methods["bf"].sweep is not None:
        pc = quickmatch_per_camera.auc
        effect = "little" if abs(pc - auc["quickmatch"]) < SAME_AUC else (
            "help" if auc["quickmatch"] > pc else "hurt")
        t_q, t_b = qm.sweep.row(pl.rho, 1e-9), methods["bf"].sweep.row(pl.ratio, 1e-9)
        if t_q is None or t_b is None:
            raise ValueError("the QuickMatch / BF sweeps lack the run's rho / ratio")
        per_camera = PerCameraFinding(pc, auc["quickmatch"], effect, t_q, t_b)
    false, large = {}, {}
    for m in have:
        a = result.arrays(m)
        det = a["score"] >= pl.min_matches
        fp = det & ~a["visible"]
        decoy = fp & (a["decoy"] > 0)
        partial = fp & ~decoy & (a["target_px"] > 0)
        false[m] = FalseDetections(int(fp.sum()), int(decoy.sum()), int(partial.sum()),
                                   int((fp & ~decoy & ~partial).sum()))
        loc = det & np.isfinite(a["estimate"]).all(axis=1)
        big = loc & (np.linalg.norm(a["estimate"] - a["truth"], axis=1) > LARGE_ERROR_M)
        large[m] = LargeErrors(int(big.sum()), int((big & ~a["visible"]).sum()))
    errs = {m: methods[m].errors for m in have}
    spread = max(have, key=lambda m: errs[m].std if errs[m].n else -1)
    cal = result.calibration
    return PaperComparison(have, first, bf_flann, wins, len(seed_rows), rho, ends, per_camera, false, spread, large,
                           100 * abs(cal.range_constant / cal.ideal - 1))


# --- the whole summary -----------------------------------------------------------------------
@dataclass(frozen=True)
class WorldFacts(_Fields):
    """Counts of the simulated world the report quotes."""

    n_references: int  #: target sides (reference images)
    n_cameras: int
    n_steps: int
    n_clutter: int  #: clutter boxes placed
    n_clutter_textures: int  #: textures the clutter boxes share


@dataclass(frozen=True)
class MachineInfo(_Fields):
    """The machine the report was made on (its times are this machine's)."""

    cores: Optional[int]
    processor: str

    @classmethod
    def here(cls) -> "MachineInfo":
        return cls(os.cpu_count(), platform.processor() or platform.machine())


@dataclass(frozen=True)
class CamnetSummary:
    """Every number of one camera-network experiment (plus other seeds' headline rows), as the report shows it."""

    sim: SimConfig
    pipeline: PipelineConfig
    frames: int
    positives: int  #: frames with the target visible
    calibration: Calibration
    features: Dict[str, float]  #: mean features per reference / camera image
    timings_s: Dict[str, float]  #: measured stage times of the main run
    world: WorldFacts
    machine: MachineInfo
    methods: Dict[str, MethodSummary]  #: in the run's order
    #: the paper's methods over the frames that all of them detected and localized
    common_detections: Optional[Dict[str, ErrorSummary]]
    #: the same over the QuickMatch variants (2+ of them)
    common_detections_quickmatch: Optional[Dict[str, ErrorSummary]]
    online: Optional[OnlineSummary]  #: with ``quickmatch-online``
    quickmatch_per_camera: Optional[SweepRow]  #: the per-camera ablation (with the sweep)
    seeds: Optional[SeedsSummary]  #: when seed rows were given
    comparison: Optional[PaperComparison]  #: with 2+ of the paper's methods

    @property
    def method_names(self) -> Tuple[str, ...]:
        return tuple(self.methods)

    @property
    def several_seeds(self) -> bool:
        return self.seeds is not None and len(self.seeds.rows) > 1

    def as_json(self) -> Dict[str, object]:
        """Plain JSON-able data (``camnet.json``); numpy scalars may remain, NaN marks a missing number."""
        out: Dict[str, object] = {
            "sim": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(self.sim).items()},
            "pipeline": dict(vars(self.pipeline)),
            "frames": self.frames,
            "positives": self.positives,
            "calibration": dict(vars(self.calibration)),
            "features": self.features,
            "timings_s": self.timings_s,
            "methods": {m: d.as_json() for m, d in self.methods.items()},
        }
        if self.common_detections is not None:
            out["common_detections"] = {m: e.as_json() for m, e in self.common_detections.items()}
        if self.common_detections_quickmatch is not None:
            out["common_detections_quickmatch"] = {m: e.as_json() for m, e in
                                                   self.common_detections_quickmatch.items()}
        if self.online is not None:
            out["online"] = self.online.as_json()
        if self.quickmatch_per_camera is not None:
            out["quickmatch_per_camera"] = self.quickmatch_per_camera.as_json("rho")
        if self.seeds is not None:
            out["seeds"] = [r.as_json() for r in self.seeds.rows]
            if self.seeds.means is not None:
                out["seeds_mean"] = self.seeds.means.as_json()
        out["world"] = self.world.as_json()
        out["machine"] = self.machine.as_json()
        if self.comparison is not None:
            out["comparison_with_paper"] = self.comparison.as_json()
        return out


def build_summary(result: ExperimentResult,
                  seed_rows: Sequence[Union[Mapping[str, object], SeedRow]] = ()) -> CamnetSummary:
    """Compute every number the report shows from one run and (optionally) several seeds' rows.

    ``seed_rows``: :func:`seed_row` (or :class:`SeedRow`) of this and other seeds' runs, for the robustness table.
    """
    pl = result.pipeline
    methods: Dict[str, MethodSummary] = {}
    for m in result.methods:
        curve = detection_curve(result, m)
        sweep = result.sweeps.get(m)
        methods[m] = MethodSummary(m, method_label(pl, m), curve.auc(), curve,
                                   OperatingPoint(**operating_point(result, m)),
                                   ErrorSummary.of(localization_errors(result, m)), PAPER.get(m), KERNEL.get(m),
                                   SweepSummary.of(sweep, pl.min_matches) if sweep is not None else None)
    paper = [m for m in result.methods if m in PAPER_METHODS]
    common = ({m: ErrorSummary.of(e) for m, e in common_errors(result, methods=paper).items()}
              if paper else None)
    qm = [m for m in QM_VARIANTS if m in result.methods]
    common_qm = ({m: ErrorSummary.of(e) for m, e in common_errors(result, methods=qm).items()}
                 if len(qm) > 1 else None)
    abl = result.sweeps.get("quickmatch-per-camera")
    per_camera = SweepRow.of("rho", abl.table(pl.min_matches)[0]) if abl is not None else None
    rows: List[SeedRow] = [r if isinstance(r, SeedRow) else SeedRow.from_json(r) for r in seed_rows]
    world = result.world
    facts = WorldFacts(len(world.references), len(world.cameras), world.n_steps, len(world.clutter),
                       max(1, (result.sim.n_clutter + 1) // 2))
    return CamnetSummary(
        sim=result.sim, pipeline=pl, frames=result.n_frames, positives=result.n_positive,
        calibration=result.calibration, features=result.n_features, timings_s=result.timings, world=facts,
        machine=MachineInfo.here(), methods=methods, common_detections=common, common_detections_quickmatch=common_qm,
        online=online_summary(result, methods) if "quickmatch-online" in result.methods else None,
        quickmatch_per_camera=per_camera, seeds=SeedsSummary.of(rows, result.methods) if rows else None,
        comparison=paper_comparison(result, methods, per_camera, rows))
