"""Camera poses against ground truth: how good are a reconstruction's cameras?

Ground truth comes in two formats users have:

* **Strecha camera files** (Strecha et al., CVPR 2008; ``NAME.camera`` beside or named after each
  image): lines 1-3 the intrinsic matrix K, line 4 ``0 0 0``, lines 5-7 the rotation R
  (camera to world), line 8 the centre C (world), line 9 the image size the file is for
  (:func:`read_strecha`);
* **a COLMAP model** (a ``sparse/0`` folder, binary or text; :func:`read_colmap_model`).

Both become :class:`Pose` objects keyed by image name (world-to-camera rotation ``R``, centre
``C``). :func:`evaluate_poses` compares a model's cameras with them:

* a **similarity** (scale, rotation, translation; Umeyama 1991, least squares on the camera
  centres of the images both hold) maps the model onto the ground truth; the rotation error
  of an image is the angle of ``R_model Q^T R_gt^T`` (``Q`` the similarity's rotation), its
  centre error the distance between the mapped centre and the true one (ground-truth units);
* the **pairwise relative-pose error** of two images is ``max(rotation error, translation
  direction error)`` of their relative pose, in degrees, needing no alignment (as IMC and
  COLMAP's benchmark report it); a pair with an image the model lacks has an infinite error;
* **AUC@t**: the area under the recall curve (the fraction of pairs whose error is at most
  ``e``) from 0 to ``t`` degrees, over ``t`` (1.0: every pair exact), computed as IMC and
  SuperGlue compute it: the sorted errors joined by straight lines from the origin, flat after
  the last error below ``t``.

Numerics: every angle is computed with ``arccos`` of a clipped cosine in float64, so an
error below about 1e-6 degrees reads as 0.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..validation import InputError

#: the thresholds (degrees) of the pairwise pose AUC, as IMC and COLMAP's benchmark report them
AUC_THRESHOLDS = (1.0, 2.0, 5.0)


@dataclass(frozen=True)
class Pose:
    """A camera: world-to-camera rotation ``R`` (3x3) and centre ``C`` (world), float64."""

    R: np.ndarray
    C: np.ndarray

    @property
    def t(self) -> np.ndarray:
        """The world-to-camera translation: x_cam = R x_world + t."""
        return -self.R @ self.C


def rotation_angle(R: np.ndarray) -> float:
    """The angle of a rotation matrix in degrees (0..180)."""
    cos = (np.trace(R) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, float(cos)))))


def vector_angle(u: np.ndarray, v: np.ndarray) -> float:
    """The angle between two vectors in degrees (0..180); 0 when either has zero length."""
    nu, nv = float(np.linalg.norm(u)), float(np.linalg.norm(v))
    if nu == 0.0 or nv == 0.0:
        return 0.0
    return math.degrees(math.acos(min(1.0, max(-1.0, float(u @ v) / (nu * nv)))))


def _numbers(path: Path, lines: list[str], first: int, count: int, width: int) -> np.ndarray:
    rows = []
    for k in range(first, first + count):
        try:
            values = [float(x) for x in lines[k].split()]
        except (IndexError, ValueError):
            values = []
        if len(values) != width or not np.isfinite(values).all():
            raise InputError(f"{path}:{k + 1}: expected {width} numbers (a Strecha camera file: K, 0 0 0, R, C, "
                             f"size)")
        rows.append(values)
    return np.array(rows, np.float64)


def read_strecha_camera(path) -> tuple[Pose, np.ndarray, tuple[int, int]]:
    """One Strecha ``.camera`` file: the pose, the intrinsic matrix K and the image size it is for."""
    path = Path(path)
    try:
        lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if ln.strip()]
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the camera file ({exc})") from None
    K = _numbers(path, lines, 0, 3, 3)
    R_cam_to_world = _numbers(path, lines, 4, 3, 3)
    C = _numbers(path, lines, 7, 1, 3)[0]
    size = _numbers(path, lines, 8, 1, 2)[0]
    if abs(np.linalg.det(R_cam_to_world) - 1.0) > 1e-3:
        raise InputError(f"{path}:5: the rotation (lines 5-7) is not a rotation (determinant "
                         f"{np.linalg.det(R_cam_to_world):.4f})")
    return Pose(R_cam_to_world.T.copy(), C), K, (int(size[0]), int(size[1]))


def read_strecha(folder) -> dict[str, Pose]:
    """Every ``IMAGE.camera`` file of a folder, keyed by the image's name (the file name without ``.camera``)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"ground truth {folder}: {'not a folder' if folder.exists() else 'no such folder'}")
    out = {}
    for path in sorted(folder.glob("*.camera")):
        out[path.name[: -len(".camera")]] = read_strecha_camera(path)[0]
    if not out:
        raise InputError(f"ground truth {folder}: no *.camera files (Strecha format) in it")
    return out


def poses_of(reconstruction) -> dict[str, Pose]:
    """The registered images of a pycolmap Reconstruction, keyed by image name."""
    out = {}
    for image in reconstruction.images.values():
        if not image.has_pose:
            continue
        m = np.asarray(image.cam_from_world().matrix(), np.float64)
        R, t = m[:, :3], m[:, 3]
        out[image.name] = Pose(R, -R.T @ t)
    return out


def read_colmap_model(folder) -> dict[str, Pose]:
    """The registered images of a COLMAP model folder (cameras, images, points3D; .bin or .txt)."""
    from .colmap import require_pycolmap

    pycolmap = require_pycolmap()
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"ground truth {folder}: {'not a folder' if folder.exists() else 'no such folder'}")
    try:
        rec = pycolmap.Reconstruction(str(folder))
    except Exception as exc:  # noqa: BLE001 - pycolmap raises its own errors for a folder without a model
        raise InputError(f"ground truth {folder}: not a COLMAP model ({type(exc).__name__})") from None
    out = poses_of(rec)
    if not out:
        raise InputError(f"ground truth {folder}: the COLMAP model has no registered image")
    return out


def read_ground_truth(path) -> dict[str, Pose]:
    """Ground-truth poses from a folder of Strecha camera files or a COLMAP model folder, told apart by content."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"--gt {path}: no such folder (give the folder of Strecha *.camera files, or a COLMAP model)")
    if not path.is_dir():
        raise InputError(f"--gt {path}: not a folder (Strecha *.camera files, or a COLMAP model)")
    if any(path.glob("*.camera")):
        return read_strecha(path)
    if any((path / f"images.{ext}").is_file() for ext in ("bin", "txt")):
        return read_colmap_model(path)
    raise InputError(f"--gt {path}: neither Strecha *.camera files nor a COLMAP model (images.bin / images.txt)")


def restrict(truth: dict[str, Pose], image_names, source: str = "ground truth") -> dict[str, Pose]:
    """The ground-truth cameras of the given images (matched by file name); InputError if none has one.

    Images without a ground-truth camera are named in a log line and left out of the scores.
    """
    import logging

    wanted = {Path(str(n)).name for n in image_names}
    by_name = {Path(n).name: n for n in truth}
    out = {by_name[w]: truth[by_name[w]] for w in sorted(wanted) if w in by_name}
    if not out:
        raise InputError(f"{source}: no camera for any of the {len(wanted)} images (it names "
                         f"{', '.join(sorted(by_name)[:3])}...; the images are {', '.join(sorted(wanted)[:3])}...)")
    lacking = sorted(wanted - set(by_name))
    if lacking:
        logging.getLogger("dqm.vision").warning("%s: no camera for %d image(s) (%s); they are left out of the "
                                                "pose scores", source, len(lacking), ", ".join(lacking[:5]))
    return out


def umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity (s, Q, T) minimising sum ||s Q source_i + T - target_i||^2 (Umeyama 1991).

    Needs at least 3 points not on one line for a unique answer; with fewer the rotation is
    whatever the SVD gives (still a rotation), which is fine for errors of 2 cameras.
    """
    src, dst = np.asarray(source, np.float64), np.asarray(target, np.float64)
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    U, S, Vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        sign[2, 2] = -1.0
    Q = U @ sign @ Vt
    var = (a ** 2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ sign) / var) if var > 0 else 1.0
    return s, Q, mu_d - s * Q @ mu_s


def relative_errors(est: dict[str, Pose], gt: dict[str, Pose], names: list[str]) -> np.ndarray:
    """max(rotation, translation-direction) error in degrees of every pair of ``names``, in the order
    (0, 1), (0, 2), ..., (1, 2), ...; inf where ``est`` lacks one of the two."""
    out = []
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            a, b = names[i], names[j]
            if a not in est or b not in est:
                out.append(math.inf)
                continue
            errs = []
            for poses in (est, gt):
                Ra, Rb = poses[a].R, poses[b].R
                R_rel = Rb @ Ra.T
                t_rel = poses[b].t - R_rel @ poses[a].t
                errs.append((R_rel, t_rel))
            (Re, te), (Rg, tg) = errs
            out.append(max(rotation_angle(Re @ Rg.T), vector_angle(te, tg)))
    return np.array(out, np.float64)


def pose_auc(errors, thresholds=AUC_THRESHOLDS) -> list[float]:
    """Area under the recall curve of ``errors`` up to each threshold, over the threshold (0..1)."""
    e = np.sort(np.asarray(errors, np.float64))
    if len(e) == 0:
        return [float("nan")] * len(thresholds)
    recall = np.arange(1, len(e) + 1) / len(e)
    e = np.r_[0.0, e]
    recall = np.r_[0.0, recall]
    out = []
    for t in thresholds:
        last = int(np.searchsorted(e, t, side="right"))
        x = np.r_[e[:last], t]
        y = np.r_[recall[:last], recall[last - 1]]
        out.append(float(np.sum((x[1:] - x[:-1]) * (y[1:] + y[:-1]) / 2.0) / t))
    return out


@dataclass
class PoseScores:
    """A model's cameras against ground truth (:func:`evaluate_poses`)."""

    n_truth: int
    registered: int
    median_rotation_deg: float
    median_centre_error: float
    auc: dict[float, float] = field(default_factory=dict)
    unmatched_names: list[str] = field(default_factory=list)

    def line(self) -> str:
        """One line: registered images, medians and the AUCs."""
        aucs = ", ".join(f"AUC@{t:g}° {v:.3f}" for t, v in self.auc.items())
        return (f"cameras against ground truth: {self.registered} of {self.n_truth} registered, median rotation error "
                f"{self.median_rotation_deg:.3f}°, median centre error {self.median_centre_error:.4g} "
                f"(ground-truth units), pairwise {aucs}")

    def as_dict(self) -> dict:
        return {"n_truth": self.n_truth, "registered": self.registered,
                "median_rotation_deg": self.median_rotation_deg, "median_centre_error": self.median_centre_error,
                "auc": {f"{t:g}": v for t, v in self.auc.items()}}


def evaluate_poses(est: dict[str, Pose], gt: dict[str, Pose], thresholds=AUC_THRESHOLDS) -> PoseScores:
    """A model's poses against the ground truth, matched by image name (see the module docstring).

    Names are matched as given, then by their last path component when that is unique on both
    sides (a model names ``seq/0001.jpg`` where the camera file is ``0001.jpg.camera``).
    Images of ``est`` that the ground truth lacks are left out; ground-truth images the model
    lacks count as unregistered.
    """
    if not gt:
        raise InputError("the ground truth holds no camera")
    est = _rename_to(est, gt)
    names = sorted(gt)
    common = [n for n in names if n in est]
    rot, centre = [], []
    if len(common) >= 2:
        s, Q, T = umeyama(np.array([est[n].C for n in common]), np.array([gt[n].C for n in common]))
        for n in common:
            rot.append(rotation_angle(est[n].R @ Q.T @ gt[n].R.T))
            centre.append(float(np.linalg.norm(s * Q @ est[n].C + T - gt[n].C)))
    errors = relative_errors(est, gt, names)
    auc = dict(zip(thresholds, pose_auc(errors, thresholds)))
    return PoseScores(len(names), len(common), float(np.median(rot)) if rot else math.nan,
                      float(np.median(centre)) if centre else math.nan, auc,
                      sorted(set(est) - set(gt)))


def _rename_to(est: dict[str, Pose], gt: dict[str, Pose]) -> dict[str, Pose]:
    """``est`` keyed by ground-truth names: exact names, else unique last path components."""
    if set(est) <= set(gt):
        return est
    base = {}
    for n in gt:
        base.setdefault(Path(n).name, []).append(n)
    out = {}
    for n, pose in est.items():
        if n in gt:
            out[n] = pose
            continue
        hits = base.get(Path(n).name, [])
        if len(hits) == 1:
            out[hits[0]] = pose
        else:
            out[n] = pose
    return out
