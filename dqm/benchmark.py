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

A CLUSTERS file made elsewhere (``dqm match``, ``dqm run`` / ``dqm coordinator``)
is scored by the same code (:func:`clusters_benchmark`, :func:`evaluate_clusters`):
against its own ``point_ids`` (generated data) or against a homography data
set's truth at its keypoints. Data-set names become file names through
:func:`file_stem` only.
"""
from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import evaluation
from .core import DEFAULT_RHO, quickmatch
from .core.tree import merge_clusters
from .validation import InputError
from .vision import baselines, datasets, features

LOG = logging.getLogger("dqm.benchmark")

OXFORD = ("graf", "wall", "boat", "bikes")
DATASETS = OXFORD + ("hotel",)
#: thresholds of the PR curves (the defaults, rho 0.9 and ratio 0.75, are on the grids). rho stops at 1.1:
#: beyond it QuickMatch's candidate edges explode on dense data (Oxford wall, 65k
#: features: 3.0M edges and 40 s at 1.1, 35M edges and 100 s at 1.25) while recall
#: has nearly saturated (graf: 0.330 at 1.0, 0.352 at 1.25, 0.357 at 1.5)
DEFAULT_RHOS = (0.3, 0.4, 0.5, 0.6, 0.67, 0.75, 0.85, 0.9, 0.95, 1.0, 1.1)
DEFAULT_RATIOS = (0.4, 0.5, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95, 1.0)

METHODS: dict[str, str] = {
    "quickmatch": "QuickMatch",
    "quickmatch-verify": "QuickMatch, geometrically verified",
    "quickmatch-guided": "QuickMatch, grown by geometry",
    "bf": "BF pairs",
    "flann": "FLANN pairs",
    "bf-drop-track": "BF tracks, drop track (OpenMVG)",
    "bf-drop-later": "BF tracks, drop later (Theia)",
    "flann-drop-track": "FLANN tracks, drop track (OpenMVG)",
    "flann-drop-later": "FLANN tracks, drop later (Theia)",
}


def file_stem(name: str, taken: Collection[str] = ()) -> str:
    """A data-set name as a safe, portable piece of a file name (``scene:3`` -> ``scene-3``).

    Every character other than ASCII letters, digits, ``.``, ``_`` and ``-``
    (``:``, ``/``, spaces, ...) becomes ``-``; runs of ``-`` collapse; leading
    and trailing ``-`` / ``.`` go (no hidden files, no ``..``); an empty
    result is ``data``. With ``taken`` (stems already used in one output
    folder, compared without case, as on macOS and Windows), ``-2``, ``-3``,
    ... is appended until the stem is new. Every command that names a file
    after a data set (``pr_<stem>.png`` ...) uses this one function.
    """
    stem = re.sub(r"-{2,}", "-", re.sub(r"[^A-Za-z0-9._-]", "-", str(name))).strip("-.") or "data"
    used = {t.lower() for t in taken}
    out, k = stem, 1
    while out.lower() in used:
        k += 1
        out = f"{stem}-{k}"
    return out


@dataclass
class Benchmark:
    """Features of one dataset and the ground truth that scores matches between them.

    ``descriptors`` may have zero columns when a CLUSTERS file without them is
    scored (:func:`clusters_benchmark`): scoring needs only the image ids, the
    keypoints (homography truth) or the point ids (landmark truth).
    """

    name: str
    kind: str  # "homography" or "landmarks"
    descriptors: np.ndarray
    image_ids: np.ndarray
    keypoints: np.ndarray  # (n, 4) x, y, size, angle
    images: list  # paths or arrays, image id k at position k
    homography: Callable[[int, int], np.ndarray] | None = None
    point_ids: np.ndarray | None = None
    tol: float = 5.0
    stats: dict[str, float] = field(default_factory=dict)
    _truth: evaluation.HomographyTruth | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.image_ids)

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
        """Precision / recall / F1 of the pairs that clusters ``labels`` imply."""
        return self.score(*evaluation.cluster_pairs(labels, self.image_ids))

    def score_clusters(self, labels) -> tuple[evaluation.Scores, evaluation.Violations]:
        """Scores and C1/C2 counts of clusters (or tracks) ``labels``: what a table row shows."""
        a, b = evaluation.cluster_pairs(labels, self.image_ids)
        return self.score(a, b), evaluation.consistency_violations(a, b, self.image_ids)


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


@dataclass
class DataSource:
    """A data set found but not yet described: its images and what its ground truth is.

    ``kind``: ``"homography"`` (``homography(i, j)`` maps image i pixels to
    image j pixels) or ``"landmarks"`` (``landmarks``: the labelled sequence).
    ``images``: paths or arrays, image id k at position k.
    """

    name: str
    kind: str
    images: list
    homography: Callable[[int, int], np.ndarray] | None = None
    landmarks: datasets.LandmarkSequence | None = None


def locate(spec: str | Path, data_root=None) -> DataSource:
    """A data set by name (graf, wall, boat, bikes, hotel, scene[:SEED]) or folder path, without features."""
    spec = str(spec)
    m = re.fullmatch(r"scene(?::(\d+))?", spec)
    if m:
        from .vision.scenes import generate_scene

        sc = generate_scene(seed=int(m.group(1) or 0))
        return DataSource(spec, "homography", list(sc.images), homography=sc.homography)
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
        seq = datasets.load_landmark_sequence(folder)
        return DataSource(seq.name, "landmarks", list(seq.image_paths), landmarks=seq)
    seq = datasets.load_homography_sequence(folder)
    return DataSource(seq.name, "homography", list(seq.image_paths), homography=seq.homography)


def load_benchmark(spec: str | Path, data_root=None, *, preset: str = features.DEFAULT_PRESET, max_features: int = 0,
                   tol: float = 5.0, patch: float = 24.0, progress=None) -> Benchmark:
    """A dataset by name (graf, wall, boat, bikes, hotel, scene[:SEED]) or folder path, features extracted."""
    if tol <= 0:
        raise InputError(f"tol must be positive (pixels), got {tol}")
    src = locate(spec, data_root)
    if src.kind == "landmarks":
        return _from_landmarks(src.landmarks, patch)
    return _from_images(src.name, src.images, src.homography, preset, max_features, tol, progress)


def _image_shape(image) -> tuple[int, int]:
    """(height, width) of an image path or array."""
    if isinstance(image, np.ndarray):
        return int(image.shape[0]), int(image.shape[1])
    return features.read_gray(image).shape[:2]


def _clusters_arrays(clusters: Mapping[str, np.ndarray], origin: str, needs: str, why: str):
    """labels, image ids and the ``needs`` array ("keypoints" or "point_ids") of a CLUSTERS dict, checked.

    ``why``: the end of the message when ``needs`` is missing.
    """
    from .validation import check_image_ids

    labels = np.asarray(clusters["labels"])
    if labels.ndim != 1 or not np.issubdtype(labels.dtype, np.integer):
        raise InputError(f"{origin}: labels must be a 1-D integer array, got {labels.dtype} {labels.shape}")
    if "image_ids" not in clusters:
        raise InputError(f"{origin}: no 'image_ids' array; scoring needs every feature's image")
    ids = check_image_ids(clusters["image_ids"], len(labels), f"{origin}: image_ids")
    if len(labels) == 0:
        raise InputError(f"{origin}: no features to score")
    if ids.min() < 0:
        raise InputError(f"{origin}: image ids must be >= 0, got {int(ids.min())}")
    if needs not in clusters:
        raise InputError(f"{origin}: no {needs!r} array; {why}")
    arr = np.asarray(clusters[needs])
    if needs == "keypoints":
        if arr.ndim != 2 or arr.shape[0] != len(labels) or arr.shape[1] < 2:
            raise InputError(f"{origin}: keypoints must be (n, 2..4) for the {len(labels)} features, got {arr.shape}")
        arr = arr.astype(np.float64)
        if not np.isfinite(arr[:, :2]).all():
            raise InputError(f"{origin}: keypoints contain NaN or inf")
    else:
        arr = check_image_ids(arr, len(labels), f"{origin}: point_ids")
    return labels.astype(np.int64), ids, arr


def _check_images_fit(clusters: Mapping[str, np.ndarray], ids: np.ndarray, xy: np.ndarray | None,
                      src: DataSource, origin: str) -> None:
    """The clusters' images are the data set's: same count, same sizes (or keypoints inside), same order."""
    names = [str(n) for n in clusters["image_names"].tolist()] if "image_names" in clusters else None
    n_data = len(src.images)
    n_file = len(names) if names is not None else int(ids.max()) + 1
    if n_file != n_data or int(ids.max()) >= n_data:
        raise InputError(f"{origin} does not fit data set {src.name}: the clusters come from "
                         f"{n_file} image(s), the data set has {n_data}")
    data_names = [Path(p).name for p in src.images] if not isinstance(src.images[0], np.ndarray) else None
    if names is not None and data_names is not None:
        mine = [Path(n).name for n in names]
        if sorted(mine) == sorted(data_names) and mine != data_names:
            k = next(i for i, (a, b) in enumerate(zip(mine, data_names)) if a != b)
            raise InputError(f"{origin} does not fit data set {src.name}: its image {k} is {mine[k]}, "
                             f"the data set's image {k} is {data_names[k]} (same images, other order)")
    for k in range(n_data):
        h, w = _image_shape(src.images[k])
        if names is not None and Path(names[k]).is_file():
            hk, wk = _image_shape(names[k])
            if (hk, wk) != (h, w):
                raise InputError(f"{origin} does not fit data set {src.name}: its image {k} "
                                 f"({Path(names[k]).name}) is {wk}x{hk}, the data set's is {w}x{h}")
        p = xy[ids == k] if xy is not None else np.zeros((0, 2))
        if len(p) and ((p < -1).any() or (p[:, 0] > w + 1).any() or (p[:, 1] > h + 1).any()):
            raise InputError(f"{origin} does not fit data set {src.name}: keypoints of image {k} lie outside "
                             f"its {w}x{h} pixels")


def clusters_benchmark(clusters: Mapping[str, np.ndarray], source: DataSource | None = None, *, tol: float = 5.0,
                       origin: str = "clusters") -> tuple[Benchmark, np.ndarray]:
    """The :class:`Benchmark` that scores a CLUSTERS file (as :func:`dqm.io.load_clusters` reads it), and its labels.

    Without ``source``: landmark truth from the file's ``point_ids`` (generated
    data). With a homography ``source``: its truth at the file's keypoints,
    after checking that the file's images are the data set's (count, order,
    sizes; keypoints inside the images). A landmark ``source`` scores by the
    file's ``point_ids`` after the image count check. ``origin`` names the file
    in errors. Raises :class:`InputError` naming the first problem.
    """
    if tol <= 0:
        raise InputError(f"tol must be positive (pixels), got {tol}")
    kind = "landmarks" if source is None or source.kind == "landmarks" else "homography"
    why = ("homography truth scores features by their keypoints" if kind == "homography" else
           "without a data set, a clusters file is scored against its point_ids (generated data)" if source is None
           else f"{source.name} has landmark truth (labelled points), which scores a clusters file only through "
                "its point_ids")
    labels, ids, arr = _clusters_arrays(clusters, origin, "point_ids" if kind == "landmarks" else "keypoints", why)
    kp = arr if kind == "homography" else None
    if kp is None and "keypoints" in clusters:
        kp = np.asarray(clusters["keypoints"], np.float64)
        kp = kp if kp.ndim == 2 and kp.shape[0] == len(labels) and kp.shape[1] >= 2 else None
    if source is not None:
        _check_images_fit(clusters, ids, None if kp is None else kp[:, :2], source, origin)
    kp = np.zeros((len(labels), 4)) if kp is None else kp
    desc = np.asarray(clusters["descriptors"]) if "descriptors" in clusters else np.zeros((len(labels), 0), np.float32)
    if source is None:
        name = Path(origin).stem
        images = [str(n) for n in clusters["image_names"].tolist()] if "image_names" in clusters \
            else list(range(int(ids.max()) + 1))
        return Benchmark(name, "landmarks", desc, ids, kp, images, point_ids=arr, tol=tol), labels
    if kind == "landmarks":
        return Benchmark(source.name, "landmarks", desc, ids, kp, list(source.images), point_ids=arr, tol=tol), labels
    return Benchmark(source.name, "homography", desc, ids, arr, list(source.images), homography=source.homography,
                     tol=tol), labels


def quickmatch_rho_path(result, rhos: Sequence[float]) -> list[np.ndarray]:
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
    """One method on one dataset: its default operating point and its PR curve.

    ``time_s``: None when unknown (a CLUSTERS file scored as it is); ``name``:
    the row's label when the method is not one of :data:`METHODS`.
    """

    method: str
    threshold_name: str
    threshold: float
    scores: evaluation.Scores
    violations: evaluation.Violations
    time_s: float | None
    curve: evaluation.PRCurve
    name: str | None = None

    @property
    def label(self) -> str:
        """The row's name in tables and findings."""
        return self.name or METHODS[self.method]

    @property
    def swept(self) -> bool:
        """Whether the curve is a threshold sweep (more than one point), so best F1 and PR AUC mean something."""
        return len(self.curve.thresholds) > 1

    def as_dict(self) -> dict[str, object]:
        return {"method": self.method, "label": self.label, "threshold_name": self.threshold_name,
                    "threshold": self.threshold, "scores": self.scores.as_dict(),
                    "violations": self.violations.as_dict(),
                    "time_s": self.time_s, "curve": self.curve.as_dict()}


def _tracks_key(matcher: str, policy: str) -> str:
    return f"{matcher}-{policy}"


def grown_labels(bench: Benchmark, result=None, *, rho: float = DEFAULT_RHO, seed: int = 0) -> np.ndarray:
    """The clusters of the ``quickmatch-guided`` method, as :func:`evaluate` scores them: QuickMatch's (``result``,
    or QuickMatch at ``rho``) grown by the image pairs' geometry (:func:`dqm.vision.guided.guided_labels`, USAC
    seeded with ``seed``)."""
    from .vision.guided import guided_labels

    r = quickmatch(bench.descriptors, bench.image_ids, rho=rho) if result is None else result
    return guided_labels(r, bench.keypoints, bench.descriptors, seed=seed, images=bench.images)[0]


def evaluate(bench: Benchmark, methods: Sequence[str] | None = None, *, rho: float = DEFAULT_RHO,
             ratio: float = baselines.DEFAULT_RATIO, rhos: Sequence[float] = DEFAULT_RHOS,
             ratios: Sequence[float] = DEFAULT_RATIOS, seed: int = 0, curves: bool = True,
             log: Callable[[str], None] | None = None) -> list[MethodResult]:
    """Run and score every method (default: all of :data:`METHODS`) on one dataset.

    ``curves=False`` skips the threshold sweeps (each curve is then the single
    default point) for a quick comparison at the operating points.
    """
    methods = list(METHODS) if methods is None else list(methods)
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise InputError(f"unknown method(s) {unknown}; choose from {list(METHODS)}")
    rhos = sorted({float(r) for r in rhos} | {float(rho)}) if curves else [float(rho)]
    ratios = sorted({float(r) for r in ratios} | {float(ratio)}) if curves else [float(ratio)]
    say = log or LOG.info  # what it is doing: shown with dqm -v
    ids = bench.image_ids
    out: list[MethodResult] = []
    if any(m.startswith("quickmatch") for m in methods):
        say(f"{bench.name}: QuickMatch at rho={rho:g}")
        r = quickmatch(bench.descriptors, ids, rho=rho)  # shared by both QuickMatch methods
        t_qm = float(r.stats["time_total"])
    if "quickmatch" in methods:
        s, v = bench.score_clusters(r.labels)
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
        s, v = bench.score_clusters(labels)
        out.append(MethodResult("quickmatch-verify", "rho", rho, s, v, t_v,
                                evaluation.pr_curve("quickmatch-verify", "rho", [rho], [s])))
    if "quickmatch-guided" in methods:
        say(f"{bench.name}: geometry-guided growth of the QuickMatch clusters")
        t0 = time.perf_counter()
        labels = grown_labels(bench, r, seed=seed)
        t_g = t_qm + time.perf_counter() - t0  # clustering plus verification and growth
        s, v = bench.score_clusters(labels)
        out.append(MethodResult("quickmatch-guided", "rho", rho, s, v, t_g,
                                evaluation.pr_curve("quickmatch-guided", "rho", [rho], [s])))
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
            curve = evaluation.pr_curve(key, "ratio", ratios, [
                bench.score_labels(baselines.build_tracks(*cand.select(x), ids, policy)) for x in ratios])
            out.append(MethodResult(key, "ratio", ratio, *bench.score_clusters(labels), t_knn + t_tracks, curve))
    order = {m: k for k, m in enumerate(METHODS)}
    return sorted(out, key=lambda m: order[m.method])


def markdown_table(results: dict[str, list[MethodResult]], benches: dict[str, Benchmark] | None = None) -> str:
    """One markdown table of every dataset's results (best F1, best-threshold F1 and AUC in bold).

    "best F1 (at)" is the highest F1 along the method's PR sweep and the
    threshold giving it: an oracle choice of threshold, which shows how much of
    a difference at the default threshold is the default's choice. A row
    without a sweep (one operating point: QuickMatch verified, a CLUSTERS
    file) shows "-" there and in PR AUC, and competes for neither bold; an
    unknown threshold or time shows "-".
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
        best_auc = max((round(r.curve.auc(), 3) for r in rows if r.swept), default=None)
        best_oracle = max((round(r.curve.best_f1()[0], 3) for r in rows if r.swept), default=None)
        head = name
        if benches and name in benches:
            b = benches[name]
            head = f"{name} ({len(b)} feat., {b.n_images} img.)"
        for r in rows:
            f1, auc = round(r.scores.f1, 3), round(r.curve.auc(), 3)
            of1, at = r.curve.best_f1()
            oracle = f"{bold(f'{of1:.3f}', round(of1, 3) == best_oracle)} ({at:g})" if r.swept else "-"
            area = bold(f"{auc:.3f}", auc == best_auc) if r.swept else "-"
            when = "-" if r.time_s is None else f"{r.time_s:.2f}"
            at_point = f"{r.threshold_name} {r.threshold:g}" if np.isfinite(r.threshold) else "-"
            lines.append(
                f"| {head} | {r.label} | {at_point} | {r.scores.precision:.3f} | "
                f"{r.scores.recall:.3f} | {bold(f'{f1:.3f}', f1 == best_f1)} | {oracle} | {area} | "
                f"{r.violations.c1_features} | {r.violations.c2_tracks} | {when} |")
            head = ""
    return "\n".join(lines) + "\n"


def _word(ours: float, theirs: float) -> str:
    """**wins** / **loses**, or ties where the two agree to the 3 decimals the table shows."""
    if round(ours, 3) == round(theirs, 3):
        return "ties"
    return "**wins**" if ours > theirs else "**loses**"


def _against_baselines(qm: MethodResult, base: list[MethodResult]) -> str:
    """How one QuickMatch variant compares with the best BF / FLANN baseline of each measure."""
    bf1 = max(base, key=lambda r: r.scores.f1)
    line = (f"{qm.label} {_word(qm.scores.f1, bf1.scores.f1)} in F1 at the defaults "
            f"({qm.scores.f1:.3f} vs {bf1.scores.f1:.3f}, {bf1.label})")
    swept = [r for r in base if r.swept]
    if qm.swept and swept:
        qf, qat = qm.curve.best_f1()
        bor = max(swept, key=lambda r: r.curve.best_f1()[0])
        bauc = max(swept, key=lambda r: r.curve.auc())
        line += (f"; at each method's best threshold it {_word(qf, bor.curve.best_f1()[0])} "
                 f"({qf:.3f} at {qm.threshold_name} {qat:g} vs {bor.curve.best_f1()[0]:.3f}, {bor.label}); "
                 f"in PR AUC it {_word(qm.curve.auc(), bauc.curve.auc())} "
                 f"({qm.curve.auc():.3f} vs {bauc.curve.auc():.3f}, {bauc.label})")
    elif not qm.swept:
        line += " (one operating point: no threshold sweep, so no best-threshold F1 or PR AUC)"
    line += "."
    tracks = [r for r in base if "-drop-" in r.method]
    if tracks:
        verdict = {r.label: _word(qm.scores.f1, r.scores.f1) for r in tracks}
        lost = [label for label, w in verdict.items() if w == "**loses**"]
        tied = [label for label, w in verdict.items() if w == "ties"]
        line += (f" Default F1 against the {len(tracks)} track variant(s): beats {len(tracks) - len(lost) - len(tied)}"
                 + (f", ties with {'; '.join(tied)}" if tied else "")
                 + (f", loses to {'; '.join(lost)}" if lost else "") + ".")
        line += (f" Precision {qm.scores.precision:.3f} vs {max(r.scores.precision for r in tracks):.3f} "
                 f"(most precise track), recall {qm.scores.recall:.3f} vs "
                 f"{max(r.scores.recall for r in tracks):.3f} (highest-recall track).")
    timed = [r for r in base if r.time_s is not None]
    if timed and qm.time_s is not None:
        fastest = min(timed, key=lambda r: r.time_s)
        if fastest.time_s < 0.8 * qm.time_s:
            line += f" Faster than {qm.label} ({qm.time_s:.2f} s): {fastest.label} ({fastest.time_s:.2f} s)."
    return line


def _verification(plain: MethodResult, verified: MethodResult) -> str:
    """What geometric verification (or guided growth) does to QuickMatch's own clusters (a change, not a rival)."""
    p, v = plain.scores, verified.scores
    what = ("Geometry-guided growth of QuickMatch's clusters (verified, then joined along links the image pairs' "
            "geometry supports)" if verified.method == "quickmatch-guided" else
            "Geometric verification of QuickMatch's clusters (the same clusters, members without geometric "
            "support split off)")
    line = (f"{what}: precision {p.precision:.3f} -> {v.precision:.3f}, recall {p.recall:.3f} -> "
            f"{v.recall:.3f}, F1 {p.f1:.3f} -> {v.f1:.3f} ({v.f1 - p.f1:+.3f})")
    if plain.time_s is not None and verified.time_s is not None:
        line += f"; time {plain.time_s:.2f} -> {verified.time_s:.2f} s"
    return line + "."


def findings(results: Mapping[str, Sequence[MethodResult]]) -> list[str]:
    """Computed (not hand-written) markdown bullets: where QuickMatch wins and loses against the BF / FLANN rows.

    Every QuickMatch variant in a dataset's rows (plain, geometrically
    verified, guided) is compared with the best BF / FLANN baseline of each
    measure, never with another QuickMatch variant; when plain QuickMatch and
    a variant are present, a sub-bullet says what the variant changes. A dataset with
    neither QuickMatch nor a baseline gives no bullet.
    """
    out = []
    for name, rows in results.items():
        base = [r for r in rows if not r.method.startswith("quickmatch")]
        ours = [r for r in rows if r.method.startswith("quickmatch")]
        parts = [_against_baselines(qm, base) for qm in ours] if base else []
        by = {r.method: r for r in ours}
        for variant in ("quickmatch-verify", "quickmatch-guided"):
            if "quickmatch" in by and variant in by:
                parts.append(_verification(by["quickmatch"], by[variant]))
        if not parts:
            continue
        out.append(f"- **{name}**: {parts[0]}")
        out += [f"  - {p}" for p in parts[1:]]
    return out


def evaluate_clusters(clusters: Mapping[str, np.ndarray], source: DataSource | None = None, *, tol: float = 5.0,
                      origin: str = "clusters") -> tuple[Benchmark, MethodResult]:
    """Score a CLUSTERS file (:func:`dqm.io.load_clusters`'s dict) as one table row.

    Truth as in :func:`clusters_benchmark`; the scores and C1/C2 counts come
    from :meth:`Benchmark.score_clusters`, the code that scores QuickMatch's
    row in :func:`evaluate`. The row's threshold is the file's rho (from its
    params, NaN if unrecorded), its curve the single operating point, its time
    unknown (None).
    """
    bench, labels = clusters_benchmark(clusters, source, tol=tol, origin=origin)
    s, v = bench.score_clusters(labels)
    params = clusters.get("params") if isinstance(clusters.get("params"), dict) else {}
    rho = float(params.get("rho", float("nan")))
    verified = ", guided" if params.get("guided") else ", verified" if params.get("verify") else ""
    label = f"{Path(origin).name} (rho {rho:g}{verified})" if params else Path(origin).name
    row = MethodResult("clusters", "rho", rho, s, v, None, evaluation.pr_curve("clusters", "rho", [rho], [s]),
                       name=label)
    return bench, row
