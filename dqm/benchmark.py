"""QuickMatch against the pairwise baselines on data with ground truth.

One :class:`Benchmark` is one dataset ready to match: features, their images
and the ground truth that scores a set of matches. :func:`evaluate` runs every
method on it at its default threshold (P, R, F1, C1/C2 violations, time) and
over a range of thresholds (PR curve, PR AUC):

==============================  ===========  ==================================
method                          threshold    what it outputs
==============================  ===========  ==================================
``quickmatch``                  rho          clusters (QuickMatch)
``bf`` / ``flann``              ratio        raw pairwise ratio-test matches
``bf-drop-track`` ...           ratio        union-find tracks, OpenMVG policy
``bf-drop-later`` ...           ratio        union-find tracks, Theia policy
==============================  ===========  ==================================

Clusters and tracks are scored by the pairs they imply
(:func:`dqm.evaluation.cluster_pairs`), pairwise matchers by their matches.
Times are matching times only (SIFT extraction is shared by all methods and
reported once per dataset); a track method's time includes its pairwise
matching.

Datasets (:func:`load_benchmark`): ``graf``, ``wall``, ``boat``, ``bikes``
(Oxford homography sequences, SIFT detected in every image, a pair correct
within ``tol`` pixels), ``hotel`` (CMU hotel, SIFT described at the 30
labelled landmarks of every frame), ``scene[:SEED]`` (a generated scene, see
:mod:`dqm.vision.scenes`), or any folder in one of those layouts.
"""
from __future__ import annotations

import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Union

import numpy as np

from . import evaluation
from .vision import baselines, datasets, features
from .core import DEFAULT_RHO, quickmatch
from .core.tree import merge_clusters
from .validation import InputError

OXFORD = ("graf", "wall", "boat", "bikes")
DATASETS = OXFORD + ("hotel",)
#: thresholds of the PR curves (the defaults, rho 0.9 and ratio 0.75, are on the grids). rho stops at 1.1:
#: beyond it QuickMatch's candidate edges explode on dense data (Oxford wall, 65k
#: features: 3.0M edges and 40 s at 1.1, 35M edges and 100 s at 1.25) while recall
#: has nearly saturated (graf: 0.330 at 1.0, 0.352 at 1.25, 0.357 at 1.5)
DEFAULT_RHOS = (0.3, 0.4, 0.5, 0.6, 0.67, 0.75, 0.85, 0.9, 0.95, 1.0, 1.1)
DEFAULT_RATIOS = (0.4, 0.5, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95, 1.0)

METHODS: Dict[str, str] = {
    "quickmatch": "QuickMatch",
    "quickmatch-verify": "QuickMatch, geometrically verified",
    "bf": "BF pairs",
    "flann": "FLANN pairs",
    "bf-drop-track": "BF tracks, drop track (OpenMVG)",
    "bf-drop-later": "BF tracks, drop later (Theia)",
    "flann-drop-track": "FLANN tracks, drop track (OpenMVG)",
    "flann-drop-later": "FLANN tracks, drop later (Theia)",
}


@dataclass
class Benchmark:
    """Features of one dataset and the ground truth that scores matches between them."""

    name: str
    kind: str  # "homography" or "landmarks"
    descriptors: np.ndarray
    image_ids: np.ndarray
    keypoints: np.ndarray  # (n, 4) x, y, size, angle
    images: list  # paths or arrays, image id k at position k
    homography: Optional[Callable[[int, int], np.ndarray]] = None
    point_ids: Optional[np.ndarray] = None
    tol: float = 5.0
    stats: Dict[str, float] = field(default_factory=dict)
    _truth: Optional[evaluation.HomographyTruth] = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.descriptors)

    @property
    def n_images(self) -> int:
        return len(self.images)

    def truth(self) -> evaluation.HomographyTruth:
        """The one-to-one homography truth, computed once and reused for every match set."""
        if self.kind != "homography":
            raise InputError(f"{self.name} has landmark truth, not homographies")
        if self._truth is None:
            self._truth = evaluation.HomographyTruth(self.keypoints, self.image_ids, self.homography, self.tol)
        return self._truth

    def score(self, a, b) -> evaluation.Scores:
        """Precision / recall / F1 of the matches (a[k], b[k]) against this dataset's truth."""
        if self.kind == "landmarks":
            return evaluation.landmark_scores(a, b, self.point_ids, self.image_ids)
        return self.truth().score(a, b)

    def correct(self, a, b) -> np.ndarray:
        """Per match (a[k], b[k]): is it correct?"""
        a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
        if self.kind == "landmarks":
            return (self.point_ids[a] == self.point_ids[b]) & (self.point_ids[a] >= 0)
        return self.truth().correct(a, b)[0]

    def score_labels(self, labels) -> evaluation.Scores:
        return self.score(*evaluation.cluster_pairs(labels, self.image_ids))


def _from_images(name: str, images: list, homography, preset: str, max_features: int, tol: float,
                 progress=None) -> Benchmark:
    t = time.perf_counter()
    D, ids, kp = features.extract_many(images, preset=preset, max_features=max_features, progress=progress)
    if len(np.unique(ids)) < 2:
        raise InputError(f"{name}: SIFT found features in fewer than two images; nothing to match")
    return Benchmark(name, "homography", D, ids, kp, list(images), homography=homography, tol=tol,
                     stats={"time_extract": time.perf_counter() - t})


def _from_landmarks(seq: datasets.LandmarkSequence, patch: float) -> Benchmark:
    t = time.perf_counter()
    D, ids, lm, kp = features.landmark_descriptors(seq, size=patch)
    return Benchmark(seq.name, "landmarks", D, ids, kp, list(seq.image_paths), point_ids=lm,
                     stats={"time_extract": time.perf_counter() - t})


def default_data_root() -> Path:
    """``$DQM_SHARED/data`` or ``../shared/data`` next to the project checkout / working directory."""
    import os

    env = os.environ.get("DQM_SHARED")
    if env:
        return Path(env) / "data"
    here = Path(__file__).resolve().parents[2] / "shared" / "data"
    return here if here.exists() else Path.cwd().parent / "shared" / "data"


def load_benchmark(spec: Union[str, Path], data_root=None, *, preset: str = features.DEFAULT_PRESET, max_features: int = 0,
                   tol: float = 5.0, patch: float = 24.0, progress=None) -> Benchmark:
    """A dataset by name (graf, wall, boat, bikes, hotel, scene[:SEED]) or folder path."""
    spec = str(spec)
    if tol <= 0:
        raise InputError(f"tol must be positive (pixels), got {tol}")
    m = re.fullmatch(r"scene(?::(\d+))?", spec)
    if m:
        from .vision.scenes import generate_scene

        seed = int(m.group(1) or 0)
        sc = generate_scene(seed=seed)
        return _from_images(spec, sc.images, sc.homography, preset, max_features, tol, progress)
    root = Path(data_root) if data_root is not None else default_data_root()
    if spec in OXFORD:
        folder = root / "oxford" / spec
    elif spec == "hotel":
        folder = root / "cmu_hotel"
    else:
        folder = Path(spec)
    if not folder.is_dir():
        raise InputError(f"dataset {spec!r}: folder {folder} not found"
                         + ("" if spec not in DATASETS else " (pass --data-root or set DQM_SHARED)"))
    if any(re.fullmatch(r".+\.seq\d+", p.stem) for p in folder.iterdir()):
        return _from_landmarks(datasets.load_landmark_sequence(folder), patch)
    seq = datasets.load_homography_sequence(folder)
    return _from_images(seq.name, list(seq.image_paths), seq.homography, preset, max_features, tol, progress)


def quickmatch_rho_path(result, rhos: Sequence[float]) -> List[np.ndarray]:
    """QuickMatch labels at every ``rho <= result.rho`` from one run at the largest rho.

    The tree does not depend on rho: a feature's parent is its nearest
    higher-density feature, kept only if within ``rho * sigma`` (an edge that
    long can never merge). So the break/merge step of a run at a large rho,
    repeated with a smaller rho, gives exactly the labels of a run at that rho
    (checked in tests/test_benchmark.py).
    """
    _, image_index = np.unique(result.image_ids, return_inverse=True)
    image_index = image_index.ravel().astype(np.int64)
    out = []
    for rho in rhos:
        if rho > result.rho:
            raise InputError(f"rho {rho} exceeds the run's rho {result.rho}; run at the largest rho")
        out.append(merge_clusters(result.parent, result.parent_distance, result.sigma, image_index, float(rho)))
    return out


@dataclass
class MethodResult:
    """One method on one dataset: its default operating point and its PR curve."""

    method: str
    threshold_name: str
    threshold: float
    scores: evaluation.Scores
    violations: evaluation.Violations
    time_s: float
    curve: evaluation.PRCurve

    @property
    def label(self) -> str:
        return METHODS[self.method]

    def as_dict(self) -> Dict[str, object]:
        return dict(method=self.method, label=self.label, threshold_name=self.threshold_name,
                    threshold=self.threshold, scores=self.scores.as_dict(), violations=self.violations.as_dict(),
                    time_s=self.time_s, curve=self.curve.as_dict())


def _tracks_key(matcher: str, policy: str) -> str:
    return f"{matcher}-{policy}"


def evaluate(bench: Benchmark, methods: Optional[Sequence[str]] = None, *, rho: float = DEFAULT_RHO,
             ratio: float = baselines.DEFAULT_RATIO, rhos: Sequence[float] = DEFAULT_RHOS,
             ratios: Sequence[float] = DEFAULT_RATIOS, seed: int = 0, curves: bool = True,
             log: Optional[Callable[[str], None]] = None) -> List[MethodResult]:
    """Run and score every method (default: all of :data:`METHODS`) on one dataset.

    ``curves=False`` skips the threshold sweeps (each curve is then the single
    default point) for a quick comparison at the operating points.
    """
    methods = list(METHODS) if methods is None else list(methods)
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise InputError(f"unknown method(s) {unknown}; choose from {list(METHODS)}")
    rhos = sorted(set(float(r) for r in rhos) | {float(rho)}) if curves else [float(rho)]
    ratios = sorted(set(float(r) for r in ratios) | {float(ratio)}) if curves else [float(ratio)]
    say = log or (lambda s: None)
    ids = bench.image_ids
    out: List[MethodResult] = []
    if "quickmatch" in methods or "quickmatch-verify" in methods:
        say(f"{bench.name}: QuickMatch at rho={rho:g}")
        r = quickmatch(bench.descriptors, ids, rho=rho)  # shared by both QuickMatch methods
        t_qm = float(r.stats["time_total"])
    if "quickmatch" in methods:
        a, b = evaluation.cluster_pairs(r.labels, ids)
        s, v = bench.score(a, b), evaluation.consistency_violations(a, b, ids)
        if curves:
            say(f"{bench.name}: QuickMatch at rho={max(rhos):g} for the PR curve")
            big = quickmatch(bench.descriptors, ids, rho=max(rhos)) if max(rhos) > rho else r
            curve = evaluation.pr_curve("quickmatch", "rho", rhos,
                                        [bench.score_labels(lab) for lab in quickmatch_rho_path(big, rhos)])
        else:
            curve = evaluation.pr_curve("quickmatch", "rho", [rho], [s])
        out.append(MethodResult("quickmatch", "rho", rho, s, v, t_qm, curve))
    if "quickmatch-verify" in methods:
        say(f"{bench.name}: geometric verification of the QuickMatch clusters")
        from .vision.verify import verify_clusters

        t0 = time.perf_counter()
        labels, _ = verify_clusters(r.labels, ids, bench.keypoints, seed=seed)
        t_v = t_qm + time.perf_counter() - t0  # the method's time: clustering plus verification
        a, b = evaluation.cluster_pairs(labels, ids)
        s, v = bench.score(a, b), evaluation.consistency_violations(a, b, ids)
        out.append(MethodResult("quickmatch-verify", "rho", rho, s, v, t_v,
                                evaluation.pr_curve("quickmatch-verify", "rho", [rho], [s])))
    for matcher in baselines.MATCHERS:
        wanted = [m for m in methods if m == matcher or m.startswith(matcher + "-")]
        if not wanted:
            continue
        say(f"{bench.name}: {matcher.upper()} matching of {bench.n_images * (bench.n_images - 1) // 2} image pairs")
        cand = baselines.pairwise_candidates(bench.descriptors, ids, matcher, seed=seed)
        t_knn = cand.stats["time_knn"]
        if matcher in wanted:
            a, b = cand.select(ratio)
            curve = evaluation.pr_curve(matcher, "ratio", ratios, [bench.score(*cand.select(x)) for x in ratios])
            out.append(MethodResult(matcher, "ratio", ratio, bench.score(a, b),
                                    evaluation.consistency_violations(a, b, ids), t_knn, curve))
        for policy in baselines.TRACK_POLICIES:
            key = _tracks_key(matcher, policy)
            if key not in wanted:
                continue
            t = time.perf_counter()
            labels = baselines.build_tracks(*cand.select(ratio), ids, policy)
            t_tracks = time.perf_counter() - t
            a, b = evaluation.cluster_pairs(labels, ids)
            curve = evaluation.pr_curve(key, "ratio", ratios, [
                bench.score_labels(baselines.build_tracks(*cand.select(x), ids, policy)) for x in ratios])
            out.append(MethodResult(key, "ratio", ratio, bench.score(a, b), evaluation.consistency_violations(a, b, ids),
                                    t_knn + t_tracks, curve))
    order = {m: k for k, m in enumerate(METHODS)}
    return sorted(out, key=lambda m: order[m.method])


def markdown_table(results: Dict[str, List[MethodResult]], benches: Optional[Dict[str, Benchmark]] = None) -> str:
    """One markdown table of every dataset's results (best F1, best-threshold F1 and AUC in bold).

    "best F1 (at)" is the highest F1 along the method's PR sweep and the
    threshold giving it: an oracle choice of threshold, which shows how much of
    a difference at the default threshold is the default's choice.
    """
    lines = [
        "| data | method | threshold | P | R | F1 | best F1 (at) | PR AUC | C1 features | C2 tracks | time (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def bold(text: str, yes: bool) -> str:
        return f"**{text}**" if yes else text

    for name, rows in results.items():
        if not rows:
            continue
        best_f1 = max(round(r.scores.f1, 3) for r in rows)
        best_auc = max(round(r.curve.auc(), 3) for r in rows)
        best_oracle = max(round(r.curve.best_f1()[0], 3) for r in rows)
        head = name
        if benches and name in benches:
            b = benches[name]
            head = f"{name} ({len(b)} feat., {b.n_images} img.)"
        for r in rows:
            f1, auc = round(r.scores.f1, 3), round(r.curve.auc(), 3)
            of1, at = r.curve.best_f1()
            lines.append(
                f"| {head} | {r.label} | {r.threshold_name} {r.threshold:g} | {r.scores.precision:.3f} | "
                f"{r.scores.recall:.3f} | {bold(f'{f1:.3f}', f1 == best_f1)} | "
                f"{bold(f'{of1:.3f}', round(of1, 3) == best_oracle)} ({at:g}) | "
                f"{bold(f'{auc:.3f}', auc == best_auc)} | {r.violations.c1_features} | "
                f"{r.violations.c2_tracks} | {r.time_s:.2f} |")
            head = ""
    return "\n".join(lines) + "\n"
