"""Detection and localization of a known object in a network of cameras, per time step.

The seed paper's pipeline, per method:

1. SIFT features of every reference image (one per side of the target) and
   of every camera's image (``preset="paper"``, :data:`dqm.vision.features.PRESETS`).
2. Matches between each camera and each reference image:

   * ``quickmatch``: one QuickMatch run over all reference images **and** all
     cameras of the time step at once; a camera feature and a reference
     feature match when they fall in the same cluster (so a match may be
     supported by other cameras' views of the same point);
   * ``quickmatch-quadratic``: the same with the quadratic (finite) kernel
     instead of the Gaussian one (the kernel online QuickMatch supports);
   * ``quickmatch-online``: one online QuickMatch (quadratic kernel) over the
     whole run, fed frame by frame: the references stay, each camera keeps
     only its latest frame, and a camera is scored on the clusters as they
     are right after its frame arrived (:mod:`dqm.camnet.online`);
   * ``bf`` / ``flann``: pairwise, each reference against each camera
     (queries from the reference, OpenCV brute force or FLANN, Lowe's ratio
     test, 0.75), see :mod:`dqm.vision.baselines`.

3. Detection: the camera's **score** is its largest number of matches with one
   reference image; it sees the target when the score is >= ``min_matches``
   (10 in the paper).
4. Localization: RANSAC homography (threshold 10 px) from that reference to
   the camera image; the reference's corners mapped by it give the bounding
   box; box height -> depth, box centre -> bearing (calibrated range constant,
   :mod:`dqm.camnet.geometry`); with the camera's pose -> a world position,
   moved half the target's depth along the line of sight to its centre.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..core import quickmatch
from ..validation import InputError, check_choice
from ..vision.baselines import DEFAULT_RATIO, PairwiseCandidates, pairwise_candidates
from ..vision.features import PRESETS, ImageFeatures, create_sift
from .geometry import Camera, bounding_box, estimate_homography, localize_from_box, projected_quad

METHODS = ("quickmatch", "bf", "flann", "quickmatch-quadratic", "quickmatch-online")
#: the methods of the seed paper's comparison (the others are dqm's variants of QuickMatch)
PAPER_METHODS = ("quickmatch", "bf", "flann")
LABELS = {"quickmatch": "QuickMatch", "bf": "BF", "flann": "FLANN", "quickmatch-quadratic": "QuickMatch quadratic",
          "quickmatch-online": "QuickMatch online"}
#: QuickMatch's kernel per method (online QuickMatch supports only the quadratic, finite kernel)
KERNEL = {"quickmatch": "gaussian", "quickmatch-quadratic": "quadratic", "quickmatch-online": "quadratic"}
#: the seed paper's camera-network settings (its rho is not ours: see docs/camnet.md)
PAPER_RHO = 1.1
#: QuickMatch's rho for target detection. Detection by ">= 10 matches" rewards
#: precision: chance matches in views without the target fire the rule. Measured
#: on seed 0 (docs/camnet.md): PR AUC 0.872 at rho 0.75, 0.814 at dqm's general
#: default 0.9 (tuned for multi-image F1 on Oxford / hotel), 0.765 at the paper's 1.1.
DETECTION_RHO = 0.75
PAPER_MIN_MATCHES = 10
PAPER_RANSAC_THRESHOLD = 10.0


@dataclass(frozen=True)
class PipelineConfig:
    """Matching, detection and localization settings.

    Defaults are the seed paper's (SIFT preset, ratio 0.75, 10 matches, RANSAC
    10 px) except QuickMatch's ``rho``: ``DETECTION_RHO`` = 0.75 rather than the
    paper's 1.1, which under dqm's (the reference code's) merge rule clusters
    unrelated features, and rather than dqm's general default (0.9, chosen for
    multi-image F1); docs/camnet.md shows all three.
    """

    preset: str = "paper"
    max_features: int = 0
    rho: float = DETECTION_RHO
    ratio: float = DEFAULT_RATIO
    min_matches: int = PAPER_MIN_MATCHES
    ransac_threshold: float = PAPER_RANSAC_THRESHOLD
    seed: int = 0

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise InputError(f"unknown SIFT preset {self.preset!r}; choose from {sorted(PRESETS)}")
        create_sift(self.preset, self.max_features)  # validates max_features
        for name in ("rho", "ratio", "ransac_threshold"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise InputError(f"{name} must be a positive number, got {v!r}")
        if int(self.min_matches) != self.min_matches or self.min_matches < 4:
            raise InputError(f"min_matches must be an integer >= 4 (a homography needs 4), got {self.min_matches!r}")


Matches = Tuple[np.ndarray, np.ndarray]  # (reference feature indices, camera feature indices)


def _stack(refs: Sequence[ImageFeatures], cams: Sequence[ImageFeatures]):
    feats = list(refs) + list(cams)
    D = np.vstack([f.descriptors for f in feats]) if feats else np.zeros((0, 128), np.uint8)
    ids = np.concatenate([np.full(len(f), k, np.int64) for k, f in enumerate(feats)]) if feats else np.zeros(0, int)
    offsets = np.r_[0, np.cumsum([len(f) for f in feats])]
    return D, ids, offsets


def quickmatch_matches(refs: Sequence[ImageFeatures], cams: Sequence[ImageFeatures], rho: float,
                       labels: Optional[np.ndarray] = None, kernel: str = "gaussian"
                       ) -> Tuple[List[List[Matches]], np.ndarray]:
    """QuickMatch over all references and cameras: ``matches[c][r]`` and the cluster labels.

    ``labels`` (one per stacked feature, references first) skips the clustering.
    """
    D, ids, offsets = _stack(refs, cams)
    R, C = len(refs), len(cams)
    if labels is None:
        labels = quickmatch(D, ids, rho=rho, kernel=kernel).labels if len(D) else np.zeros(0, np.int64)
    labels = np.asarray(labels)
    if labels.shape != (len(D),):
        raise InputError(f"labels must have one entry per feature ({len(D)}), got shape {labels.shape}")
    K = int(labels.max()) + 1 if len(labels) else 0
    table = np.full((K, R + C), -1, np.int64)
    table[labels, ids] = np.arange(len(D))  # C2: at most one feature per image per cluster
    out: List[List[Matches]] = []
    for c in range(C):
        row = []
        col = table[:, R + c]
        for r in range(R):
            both = (col >= 0) & (table[:, r] >= 0)
            row.append((table[both, r] - offsets[r], col[both] - offsets[R + c]))
        out.append(row)
    return out, labels


def pairwise_pair_candidates(ref: ImageFeatures, cam: ImageFeatures, matcher: str, seed: int = 0) -> PairwiseCandidates:
    """Nearest neighbours of the reference's features in the camera image (local indices)."""
    D = np.vstack([ref.descriptors, cam.descriptors])
    ids = np.r_[np.zeros(len(ref), np.int64), np.ones(len(cam), np.int64)]
    cand = pairwise_candidates(D, ids, matcher, seed=seed)
    return PairwiseCandidates(cand.query, cand.train - len(ref), cand.distance, cand.ratio, matcher, cand.n_features)


def pairwise_matches_all(refs: Sequence[ImageFeatures], cams: Sequence[ImageFeatures], matcher: str,
                         ratio: float = DEFAULT_RATIO, seed: int = 0
                         ) -> Tuple[List[List[Matches]], List[List[PairwiseCandidates]]]:
    """Ratio-test matches ``matches[c][r]`` of every camera with every reference, and the candidates."""
    cands = [[pairwise_pair_candidates(ref, cam, matcher, seed) for ref in refs] for cam in cams]
    return [[c.select(ratio) for c in row] for row in cands], cands


@dataclass(frozen=True)
class Detection:
    """One method's result for one camera at one time step.

    ``counts[r]``: matches with reference r; ``score``: their maximum;
    ``reference``: the reference reaching it (-1 when no match); ``inliers``:
    RANSAC inliers of its homography; ``box``: the mapped reference's bounding
    box (None when no homography or a degenerate one); ``estimate``: world
    (x, y) of the target centre, None when there is no box.
    """

    method: str
    step: int
    camera: int
    counts: Tuple[int, ...]
    score: int
    reference: int
    inliers: int
    box: Optional[Tuple[float, float, float, float]]
    estimate: Optional[Tuple[float, float]]

    def detected(self, min_matches: int) -> bool:
        return self.score >= min_matches


def localize(matches: Matches, ref: ImageFeatures, cam_feats: ImageFeatures, ref_size: Tuple[int, int],
             camera: Camera, range_constant: float, behind: float, threshold: float = PAPER_RANSAC_THRESHOLD,
             seed: int = 0):
    """Homography, box and world position from matches of one reference: ``(inliers, box, estimate)``."""
    a, b = matches
    H, mask = estimate_homography(ref.keypoints[a, :2], cam_feats.keypoints[b, :2], threshold, seed=seed)
    if H is None:
        return int(mask.sum()), None, None
    quad = projected_quad(H, *ref_size)
    if quad is None:
        return int(mask.sum()), None, None
    box = bounding_box(quad)
    if box[3] - box[1] < 1.0:
        return int(mask.sum()), box, None
    est = localize_from_box(box, camera, range_constant, behind=behind)
    return int(mask.sum()), box, (float(est[0]), float(est[1]))


def detect(method: str, step: int, camera_index: int, matches_row: Sequence[Matches],
           refs: Sequence[ImageFeatures], ref_sizes: Sequence[Tuple[int, int]], cam_feats: ImageFeatures,
           camera: Camera, range_constant: float, behind: Sequence[float], config: PipelineConfig,
           localize_below: Optional[int] = None) -> Detection:
    """Score one camera against all references and localize the target from the best one.

    Localization runs when the score reaches ``localize_below`` (default
    ``config.min_matches``): frames that are not detections need no position.
    """
    check_choice(method, "method", METHODS)
    counts = tuple(int(len(m[0])) for m in matches_row)
    if not counts or max(counts) == 0:
        return Detection(method, step, camera_index, counts, 0, -1, 0, None, None)
    r = int(np.argmax(counts))
    score = counts[r]
    need = config.min_matches if localize_below is None else localize_below
    inl, box, est = 0, None, None
    if score >= max(4, need):
        inl, box, est = localize(matches_row[r], refs[r], cam_feats, ref_sizes[r], camera, range_constant,
                                 behind[r], config.ransac_threshold, seed=config.seed)
    return Detection(method, step, camera_index, counts, score, r, inl, box, est)


def match_all(method: str, refs: Sequence[ImageFeatures], cams: Sequence[ImageFeatures],
              config: PipelineConfig) -> Tuple[List[List[Matches]], Dict[str, object]]:
    """Matches ``[camera][reference]`` by one batch method, with by-products (labels or candidates)."""
    check_choice(method, "method", METHODS)
    if method == "quickmatch-online":
        raise InputError("quickmatch-online matches one frame at a time: use dqm.camnet.online.OnlineMatcher")
    if method in KERNEL:
        m, labels = quickmatch_matches(refs, cams, config.rho, kernel=KERNEL[method])
        return m, {"labels": labels}
    m, cands = pairwise_matches_all(refs, cams, method, config.ratio, config.seed)
    return m, {"candidates": cands}
