"""The plain file formats between dqm's stages (numpy ``.npz``, no pickles).

FEATURES file (input of ``dqm match``)::

    descriptors   (n, d)  uint8 or float     one row per feature
    image_ids     (n,)    int                image of every feature
    keypoints     (n, 4)  float32, optional  x, y, size, angle (OpenCV, 0-based px)
    image_names   (m,)    str, optional      name of image id k at row k (every id in 0..m-1)
    point_ids     (n,)    int, optional      ground-truth physical point (-1 unknown)
    feature_ids   (n,)    int64, optional    global feature ids (unique, >= 0), e.g. rows of
                                             the file that ``dqm split`` cut up

Image ids belong to their file: two FEATURES files that both number their
images 0, 1, 2 hold six different images. Where files are combined (``dqm
match a.npz b.npz``, the agents of a distributed job), :func:`combine_images`
keeps the ids when no two files share one, and numbers the images afresh,
file after file, when they do.

CLUSTERS file (output of ``dqm match``, ``dqm run``, ``dqm coordinator`` and
``dqm stream``): every FEATURES field that was present (a distributed job's:
all but the descriptors, which stay with the agents), plus::

    labels           (n,) int64    cluster of every feature (0..k-1)
    sigma            (n,) float64  distinctiveness (not in a distributed job's)
    density          (n,) float64  (not in a distributed job's)
    parent           (n,) int64    tree parent within reach, -1 if none (not in a distributed job's)
    parent_distance  (n,) float64  inf if no parent (not in a distributed job's)
    params           ()   str      JSON: rho, ratio_density, kernel, parent mode, dqm version
                                   (a distributed job's: its algorithm parameters, agents, seed, job)

TRACKS CSV (``dqm match --tracks-csv``): one row per feature of every cluster
with at least two features, sorted by track then image; columns ``track``
(0, 1, ... in order of cluster label), ``label`` (the CLUSTERS label),
``image_id``, ``image`` (name, if known), ``feature`` (row in the FEATURES
arrays), ``x``, ``y``, ``size``, ``angle`` (empty if no keypoints).
"""
from __future__ import annotations

import csv
import json
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import numpy as np

from . import outputs
from .validation import InputError, check_descriptors, check_image_ids, has_repeats

#: the optional per-feature and per-image arrays of a FEATURES file, in the order they are written
OPTIONAL_FIELDS = ("keypoints", "image_names", "point_ids", "feature_ids")


@dataclass
class FeatureSet:
    """The arrays of a FEATURES file (see the module docstring); ``validate`` checks them."""

    descriptors: np.ndarray
    image_ids: np.ndarray
    keypoints: Optional[np.ndarray] = None
    image_names: Optional[np.ndarray] = None
    point_ids: Optional[np.ndarray] = None
    feature_ids: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return len(self.image_ids)

    def global_ids(self) -> np.ndarray:
        """The features' global ids (int64): ``feature_ids`` where the file has them, else the row numbers, as a
        distributed job numbers them and its CLUSTERS file keys its rows."""
        if self.feature_ids is None:
            return np.arange(len(self), dtype=np.int64)
        return np.asarray(self.feature_ids, np.int64)

    def validate(self, source: str = "features") -> "FeatureSet":
        """Check every array against the format; raise InputError naming ``source``, the array and the row."""
        check_descriptors(self.descriptors, f"{source}: descriptors", keep_integer=True)  # no float64 copy
        n = len(self.descriptors)
        self.image_ids = check_image_ids(self.image_ids, n, f"{source}: image_ids")
        if self.keypoints is not None:
            kp = np.asarray(self.keypoints)
            if kp.ndim != 2 or kp.shape[0] != n or not 2 <= kp.shape[1] <= 4 or kp.dtype.kind not in "fiu":
                raise InputError(f"{source}: keypoints must be numbers of shape (n, 2..4) with n = {n}, "
                                 f"got {kp.dtype} {kp.shape}")
        if self.point_ids is not None:
            pid = np.asarray(self.point_ids)
            if pid.shape != (n,) or pid.dtype.kind not in "iu":
                raise InputError(f"{source}: point_ids must be one integer per feature ({n}), got {pid.dtype} "
                                 f"{pid.shape}")
        if self.image_names is not None:
            check_image_names(self.image_names, self.image_ids, source)
        if self.feature_ids is not None:
            check_feature_ids(self.feature_ids, n, source)
        return self


def check_image_names(names, image_ids: np.ndarray, source: str = "features") -> None:
    """``image_names`` must be strings, one per image id: row k names image k, so every id is a row."""
    names = np.asarray(names)
    if names.ndim != 1 or names.dtype.kind not in "US":
        raise InputError(f"{source}: image_names must be a 1-D array of strings, got {names.dtype} {names.shape}")
    if len(image_ids) == 0:
        return
    bad = np.unique(image_ids[(image_ids < 0) | (image_ids >= len(names))])
    if len(bad):
        raise InputError(f"{source}: image_names has {len(names)} name(s) (rows 0..{len(names) - 1}), but image "
                         f"id(s) {', '.join(str(b) for b in bad[:5])}{' ...' if len(bad) > 5 else ''} have no row; "
                         "row k of image_names names image id k")


def check_feature_ids(feature_ids, n: int, source: str = "features") -> np.ndarray:
    """Global feature ids: one non-negative integer per feature, no two alike (they key the results)."""
    fid = np.asarray(feature_ids)
    if fid.shape != (n,) or fid.dtype.kind not in "iu":
        raise InputError(f"{source}: feature_ids must be one integer per feature ({n}), got {fid.dtype} {fid.shape}")
    fid = fid.astype(np.int64)
    if n and fid.min() < 0:
        raise InputError(f"{source}: feature_ids must be >= 0; row {int(np.argmax(fid < 0))} holds {int(fid.min())}")
    srt = np.sort(fid)
    dup = srt[1:][srt[1:] == srt[:-1]]
    if len(dup):
        raise InputError(f"{source}: feature id {int(dup[0])} appears more than once (feature ids must be unique)")
    return fid


def combine_images(local_ids: Sequence[np.ndarray]) -> Tuple[List[np.ndarray], bool]:
    """Image ids for images from several sources (FEATURES files, agents), each numbering its own.

    ``local_ids[s]``: the distinct image ids that source ``s`` holds. Returns, per source, the id of
    each of those images in the combined set, and whether any changed: when no id is held by two
    sources the ids stay as they are; otherwise the images are numbered 0, 1, ... source after
    source, in id order within each (the image names say which is which).
    """
    local = [np.unique(np.asarray(ids, np.int64)) for ids in local_ids]
    everything = np.concatenate(local) if local else np.zeros(0, np.int64)
    if not has_repeats(everything):
        return local, False
    out, start = [], 0
    for ids in local:
        out.append(np.arange(start, start + len(ids), dtype=np.int64))
        start += len(ids)
    return out, True


def shared_image_ids(local_ids: Sequence[np.ndarray]) -> np.ndarray:
    """The image ids held by more than one source (sorted), for messages."""
    everything = np.concatenate([np.unique(np.asarray(i, np.int64)) for i in local_ids]) if local_ids else \
        np.zeros(0, np.int64)
    values, counts = np.unique(everything, return_counts=True)
    return values[counts > 1]


#: zlib level of the npz files dqm writes: level 1 packs descriptors and labels nearly as tightly as
#: numpy's default (6) in less time (90k COLMAP features' CLUSTERS: 0.47 -> 0.28 s, 1.5% larger)
NPZ_LEVEL = 1
#: an array is stored as it is, not deflated, when zlib shrinks a sample of it by less than this:
#: SIFT descriptors deflate to about 0.83 of their bytes at 24 MB/s (0.49 of the 0.67 s that writing
#: 90k COLMAP features' CLUSTERS took), float keypoints, sigma and densities to 0.8-0.9
NPZ_STORE_ABOVE = 0.8
#: bytes of an array's sample for that test (its head, as it lies in memory)
NPZ_SAMPLE = 1 << 18


def _compressible(value: np.ndarray) -> bool:
    """Whether deflating ``value`` pays: zlib at :data:`NPZ_LEVEL` on its first :data:`NPZ_SAMPLE` bytes
    leaves at most :data:`NPZ_STORE_ABOVE` of them."""
    if value.size == 0:
        return True
    if value.ndim:  # the first rows only: no copy of a large array that is not contiguous
        per_row = max(1, value.size // len(value)) * value.itemsize
        value = value[:max(1, NPZ_SAMPLE // per_row)]
    head = np.ascontiguousarray(value).reshape(-1).view(np.uint8)[:NPZ_SAMPLE].tobytes()
    return len(head) < 256 or len(zlib.compress(head, NPZ_LEVEL)) <= NPZ_STORE_ABOVE * len(head)


def _savez_fast(path: str, arrays: dict) -> None:
    """An npz (``np.load`` reads it as any): each array deflated with zlib level :data:`NPZ_LEVEL`, or stored
    as it is where deflating does not pay (:func:`_compressible`). Members carry a fixed date, so the same
    arrays give the same bytes."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=NPZ_LEVEL) as zf:
        for name, value in arrays.items():
            value = np.asanyarray(value)
            info = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED if value.dtype.hasobject or _compressible(value) else \
                zipfile.ZIP_STORED
            info.external_attr = 0o600 << 16
            if hasattr(info, "compress_level"):  # Python 3.13 and later
                info.compress_level = NPZ_LEVEL
            else:
                info._compresslevel = NPZ_LEVEL
            with zf.open(info, "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, value, allow_pickle=False)


def _atomic_savez(path: Path, arrays: dict) -> None:
    """Write an npz next to ``path`` and rename it in place: no half-written file."""
    with outputs.atomic_output(path) as tmp:
        _savez_fast(tmp, arrays)


def _feature_arrays(fs: FeatureSet) -> dict:
    """The FEATURES arrays of a feature set (optional ones only when present)."""
    arrays = {"descriptors": fs.descriptors, "image_ids": np.asarray(fs.image_ids, np.int64)}
    if fs.descriptors is None:  # a distributed job's clusters: the descriptors stayed with the agents
        del arrays["descriptors"]
    for name in OPTIONAL_FIELDS:
        v = getattr(fs, name)
        if v is not None:
            arrays[name] = np.asarray(v)
    return arrays


def save_features(path, fs: FeatureSet) -> None:
    _atomic_savez(Path(path), _feature_arrays(fs))


def is_npz(path) -> bool:
    """Whether ``path`` is an existing .npz file (a zip archive), whatever its suffix says."""
    p = Path(path)
    return p.is_file() and zipfile.is_zipfile(p)


def _read_npz(p: Path, what: str) -> dict:
    """Every array of an .npz file, refusing pickled (object) arrays and unreadable files in one line."""
    if not p.exists():
        raise InputError(f"{what} file not found: {p}")
    if p.is_dir():
        raise InputError(f"{p} is a folder, not a {what} .npz file")
    if not zipfile.is_zipfile(p):
        with open(p, "rb") as fh:
            looks_json = fh.read(1) in (b"{", b"[")
        hint = " (it looks like JSON: a job report, not a CLUSTERS file)" if looks_json else ""
        raise InputError(f"{p}: not an .npz {what} file{hint} (an .npz is a zip archive of numpy arrays; "
                         "see docs/formats.md)")
    key = None
    try:
        with np.load(p, allow_pickle=False) as z:
            out = {}
            for key in z.files:
                try:
                    out[key] = z[key]
                except ValueError as exc:  # numpy refuses object arrays without allow_pickle
                    if "allow_pickle" not in str(exc):
                        raise
                    raise InputError(f"{p}: array {key!r} holds Python objects (dtype object); save it as a "
                                     "numeric or string array (dqm never unpickles data)") from None
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - any unreadable file
        where = f"array {key!r} cannot be read" if key is not None else f"not a readable .npz {what} file"
        raise InputError(f"{p}: {where} ({_why_unreadable(exc)}); the file is damaged or was cut short, "
                         "write it again") from None
    return out


def _why_unreadable(exc: Exception) -> str:
    """A damaged file's error in words (zlib's class is called ``error``; zip's CRC check is BadZipFile)."""
    if isinstance(exc, zlib.error):
        return f"corrupt compressed data: {exc}"
    if isinstance(exc, zipfile.BadZipFile):
        return f"corrupt zip member: {exc}"
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def load_features(path) -> FeatureSet:
    """Read and check a FEATURES file; InputError names the file, the array and the problem."""
    p = Path(path)
    z = _read_npz(p, "features")
    for key in ("descriptors", "image_ids"):
        if key not in z:
            raise InputError(f"{p}: missing array {key!r} (has {sorted(z)})")
    fs = FeatureSet(descriptors=z["descriptors"], image_ids=z["image_ids"],
                    **{name: z.get(name) for name in OPTIONAL_FIELDS})
    return fs.validate(str(p))


def merge_features(sets: Sequence[FeatureSet], sources: Sequence[str]) -> Tuple[FeatureSet, str]:
    """Several FEATURES sets as one (``dqm match a.npz b.npz``): images combined by
    :func:`combine_images`; returns the set and a note ("" when the image ids stayed).

    Descriptors must agree in dimension. An optional array present in only some
    sets is left out (point_ids: -1 where unknown); feature ids are kept only
    when every set has them and no two coincide.
    """
    if len(sets) == 1:
        return sets[0], ""
    dims = {fs.descriptors.shape[1] for fs in sets}
    if len(dims) > 1:
        detail = ", ".join(f"{src}: {fs.descriptors.shape[1]}" for src, fs in zip(sources, sets))
        raise InputError(f"the FEATURES files have descriptors of different dimensions ({detail})")
    new_ids, renumbered = combine_images([fs.image_ids for fs in sets])
    image_ids = []
    for fs, out in zip(sets, new_ids):
        local = np.unique(fs.image_ids)
        image_ids.append(out[np.searchsorted(local, fs.image_ids)])
    merged = FeatureSet(np.concatenate([fs.descriptors for fs in sets]), np.concatenate(image_ids))
    if all(fs.keypoints is not None for fs in sets) and len({fs.keypoints.shape[1] for fs in sets}) == 1:
        merged.keypoints = np.concatenate([fs.keypoints for fs in sets])
    if all(fs.image_names is not None for fs in sets):
        top = int(max(int(ids.max()) for ids in new_ids if len(ids))) + 1 if any(len(i) for i in new_ids) else 0
        names = [""] * top
        for fs, out in zip(sets, new_ids):
            for local, new in zip(np.unique(fs.image_ids).tolist(), out.tolist()):
                names[new] = str(fs.image_names[local])
        merged.image_names = np.array(names)
    if any(fs.point_ids is not None for fs in sets):
        merged.point_ids = np.concatenate([np.asarray(fs.point_ids, np.int64) if fs.point_ids is not None
                                           else np.full(len(fs), -1, np.int64) for fs in sets])
    if all(fs.feature_ids is not None for fs in sets):
        fid = np.concatenate([np.asarray(fs.feature_ids, np.int64) for fs in sets])
        if not has_repeats(fid):
            merged.feature_ids = fid
    note = ""
    if renumbered:
        shared = shared_image_ids([fs.image_ids for fs in sets])
        note = (f"image id(s) {', '.join(str(i) for i in shared[:5].tolist())}{' ...' if len(shared) > 5 else ''} "
                f"appear in more than one file; each file numbers its own images, so the "
                f"{sum(len(i) for i in new_ids)} images are numbered 0.. file after file")
    return merged, note


def absolute_if_exists(name: str) -> str:
    """The absolute path of an existing file, else the name as given."""
    p = Path(str(name))
    return str(p.resolve()) if p.is_file() else str(name)


def find_image(name: str, image_dir=None) -> Optional[Path]:
    """The image a FEATURES / CLUSTERS file names: as named, else under ``image_dir`` by its relative name, else
    by its file name alone (the names are absolute where the images were found, and images move); None if none
    of these is a file."""
    p = Path(str(name))
    candidates = [p] if image_dir is None else [p, Path(image_dir) / p, Path(image_dir) / p.name]
    return next((c for c in candidates if c.is_file()), None)


def save_clusters(path, fs: FeatureSet, result, extra_params: Optional[dict] = None) -> None:
    """Write ``dqm match``'s CLUSTERS file: the features, a QuickMatchResult and its parameters."""
    params = {"rho": result.rho, "ratio_density": result.ratio_density, "kernel": result.kernel,
              "parent": result.parent_mode}
    if "n_neighbors" in result.stats:  # the approximate mode
        params.update(approximate=True, n_neighbors=int(result.stats["n_neighbors"]))
    engine = "knn" if "n_neighbors" in result.stats else "exact"
    params["engine"] = "fast" if "engine_fast" in result.stats else engine
    if "engine_fast" in result.stats:
        params.update(n_lists=int(result.stats["n_lists"]), n_probe=int(result.stats["n_probe"]))
    params.update(extra_params or {})
    write_clusters(path, fs, {"labels": result.labels, "sigma": result.sigma, "density": result.density,
                              "parent": result.parent, "parent_distance": result.parent_distance}, params)


def write_clusters(path, fs: FeatureSet, per_feature: dict, params: dict) -> None:
    """Write a CLUSTERS file: the FEATURES arrays of ``fs`` (descriptors may be None), the per-feature
    result arrays (``labels`` at least) and ``params`` (JSON, with the dqm version added); atomically."""
    from . import __version__

    arrays = _feature_arrays(fs)
    if "image_names" in arrays:  # absolute, so the file can be used from any folder
        arrays["image_names"] = np.array([absolute_if_exists(n) for n in arrays["image_names"].tolist()])
    arrays.update(per_feature, params=np.array(json.dumps({**params, "dqm_version": __version__})))
    _atomic_savez(Path(path), arrays)


def load_clusters(path) -> dict:
    """Every array of a CLUSTERS file (``params`` parsed); InputError for anything else."""
    p = Path(path)
    out = _read_npz(p, "clusters")
    if "labels" not in out:
        raise InputError(f"{p}: not a clusters file (no 'labels' array; has {sorted(out)})")
    out["params"] = json.loads(str(out["params"])) if "params" in out else {}
    return out


def check_one_feature_an_image(labels, image_ids, image_names, source: str, use: str) -> None:
    """InputError naming the cluster, the image and two rows where a cluster of ``labels`` holds two features of
    one image: clusters are QuickMatch's (constraint C2), and what ``use`` does with them (matches between every
    two members) would pair an image with itself."""
    labels, ids = np.asarray(labels), np.asarray(image_ids)
    if labels.shape != ids.shape or labels.ndim != 1:
        return  # not one label an image id: the callers' own checks name that
    order = np.lexsort((ids, labels))
    twice = np.flatnonzero((np.diff(labels[order]) == 0) & (np.diff(ids[order]) == 0))
    if len(twice):
        a, b = sorted(order[twice[0]:twice[0] + 2].tolist())
        image = image_names[ids[a]] if image_names is not None else ids[a]
        raise InputError(f"{source}: cluster {labels[a]} holds two features of image {image} (rows {a} and {b}); "
                         f"{use} takes clusters of at most one feature an image")


def save_tracks_csv(path, labels, image_ids, keypoints=None, image_names=None, min_size: int = 2) -> int:
    """Write the clusters with ``min_size`` or more features as a TRACKS CSV; returns the track count."""
    labels = np.asarray(labels)
    image_ids = np.asarray(image_ids)
    if labels.shape != image_ids.shape or labels.ndim != 1:
        raise InputError("labels and image_ids must be 1-D arrays of equal length")
    if min_size < 1:
        raise InputError(f"min_size must be >= 1, got {min_size}")
    kp = None if keypoints is None else np.asarray(keypoints, dtype=np.float64)
    sizes = np.bincount(labels) if len(labels) else np.zeros(0, np.int64)
    keep = np.flatnonzero(sizes[labels] >= min_size) if len(labels) else np.zeros(0, np.int64)
    order = keep[np.lexsort((keep, image_ids[keep], labels[keep]))]
    track_of = {lab: k for k, lab in enumerate(np.unique(labels[order]).tolist())}
    with outputs.atomic_output(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["track", "label", "image_id", "image", "feature", "x", "y", "size", "angle"])
        for f in order.tolist():
            img = int(image_ids[f])
            name = str(image_names[img]) if image_names is not None and 0 <= img < len(image_names) else ""
            geo = [""] * 4
            if kp is not None:
                geo = [f"{v:.3f}" for v in kp[f, :4]] + [""] * (4 - min(4, kp.shape[1]))
            w.writerow([track_of[int(labels[f])], int(labels[f]), img, name, f, *geo[:4]])
    return len(track_of)
