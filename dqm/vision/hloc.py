"""hloc's local-feature files (HDF5) as dqm FEATURES sets, and back; clusters as hloc matches and pairs.

hloc (https://github.com/cvg/Hierarchical-Localization) stores the local
features of an image folder in one HDF5 file (``feats-superpoint-n4096-r1024.h5``,
``feats-disk.h5``, ...). What this module relies on, checked against hloc's
sources (snapshot of 2025-12, commit c13273b):

* ``hloc/extract_features.py``, function ``main``: one HDF5 group per image,
  created with the image's name relative to the image folder
  (``ImageDataset`` builds the names with ``Path.relative_to(root).as_posix()``,
  so ``seq1/img0.jpg`` is a nested group ``seq1`` / ``img0.jpg`` in h5py).
  Each group holds one dataset per extractor output plus ``image_size``,
  the original image's ``(width, height)``. With ``as_half`` (the default)
  every float32 output, keypoints included, is stored as float16.
* The extractors (``hloc/extractors/superpoint.py`` through SuperGlue's
  SuperPoint, ``hloc/extractors/dog.py``, ...) return ``keypoints`` (N, 2: x, y),
  ``scores`` (N,) and ``descriptors`` transposed, (D, N): ``dog.py`` returns
  ``descriptors.T``. The DoG (SIFT) extractor also writes ``scales`` (N,) and
  ``oris`` (N,, degrees: ``np.rad2deg`` of COLMAP's orientation).
* Keypoint convention: hloc keeps pixel centres at integer coordinates
  (0-based, OpenCV's convention). ``extract_features.main`` rescales with
  ``(kp + 0.5) * scale - 0.5``, and the consumers that hand keypoints to
  COLMAP add the half pixel themselves: ``hloc/triangulation.py``
  ``import_features`` (``+= 0.5``, "COLMAP origin") and
  ``hloc/localize_sfm.py`` (``+= 0.5``, "COLMAP coordinates").
* ``hloc/utils/io.py``: ``list_h5_names`` lists an image for every group that
  directly holds a dataset (parent of each dataset, leading '/' stripped);
  ``get_keypoints`` reads ``file[name]["keypoints"]`` by full name and an
  optional ``uncertainty`` attribute. ``hloc/match_features.py``
  (``FeaturePairsDataset``) loads every dataset of the two groups and needs
  ``image_size``.
* Matches (``hloc/match_features.py``, ``writer_fn``): one group per image pair,
  named ``names_to_pair(name0, name1)`` (``hloc/utils/parsers.py``: each name
  with '/' replaced by '-', the two joined by '/', so a nested group), holding
  ``matches0`` (one entry per keypoint of ``name0``: the index of its match in
  ``name1``, -1 for none; int16 there) and ``matching_scores0`` (float16).
  ``hloc/utils/io.py`` ``find_pair`` / ``get_matches`` look the pair up in both
  orders (and in an older '_'-separated form) and keep the entries != -1.
  The pairs file (``pairs_from_exhaustive.py``, read by ``parse_retrieval`` and
  ``triangulation.import_matches``) holds one ``name0 name1`` line per pair,
  split on white space. ``triangulation.import_features`` reads
  ``file[name]["keypoints"]`` of every image of the COLMAP database and adds
  0.5; ``reconstruction.main`` imports the images of its image folder
  (COLMAP's reader, recursive) and names them relative to it.

dqm's FEATURES keypoints are (n, 4) float32: x, y, size, angle in OpenCV's
conventions (see :mod:`dqm.io`). hloc's x, y are already in that convention and
are copied unchanged (no half-pixel shift). ``size`` and ``angle`` come from
hloc's ``scales`` and ``oris`` where a file has them (DoG / SIFT files; taken
as stored, like :mod:`dqm.vision.colmap` keeps COLMAP's scale and orientation);
otherwise they are :data:`DEFAULT_SIZE` = 0 and :data:`DEFAULT_ANGLE` = -1,
the values of a default-constructed ``cv2.KeyPoint`` ("not set"). Note that
hloc's float16 keypoints are only exact to 1/8 px up to x = 1024 and to 2 px
beyond 2048: dqm reads what is stored.

h5py is optional: ``pip install 'dqm[colmap]'``.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Union

import numpy as np
from numpy.typing import ArrayLike

from ..io import FeatureSet
from ..outputs import atomic_output
from ..validation import InputError
from .colmap import DEFAULT_CLUSTER_MATCHES, cluster_pairs, local_indices

PathLike = Union[str, "os.PathLike[str]"]

#: keypoint size when the file has no ``scales`` (cv2.KeyPoint's default: not set)
DEFAULT_SIZE = 0.0
#: keypoint angle when the file has no ``oris`` (cv2.KeyPoint's default: not set)
DEFAULT_ANGLE = -1.0

_INSTALL_HINT = "pip install 'dqm[colmap]'"


def require_h5py():
    """The h5py module, or InputError saying how to install it."""
    try:
        import h5py
    except ImportError:
        raise InputError(f"hloc feature files (HDF5) need h5py: {_INSTALL_HINT}") from None
    return h5py


def list_image_names(path: PathLike) -> list[str]:
    """The image names in an hloc HDF5 file, sorted: every group that directly holds a dataset."""
    h5py = require_h5py()
    path = _check_h5_file(h5py, Path(path))
    with h5py.File(str(path), "r") as fd:
        return _image_names(h5py, fd)


def _check_h5_file(h5py, path: Path) -> Path:
    if not path.exists():
        raise InputError(f"hloc features file not found: {path}")
    if not path.is_file() or not h5py.is_hdf5(str(path)):
        raise InputError(f"{path}: not an HDF5 file (hloc writes its local features as .h5)")
    return path


def _image_names(h5py, fd) -> list[str]:
    names = set()

    def visit(_, obj):
        if isinstance(obj, h5py.Dataset):
            names.add(obj.parent.name.lstrip("/"))

    fd.visititems(visit)
    names.discard("")  # a dataset at the root belongs to no image
    return sorted(names)


def _kind_hint(keys: Sequence[str]) -> str:
    if "global_descriptor" in keys:
        return " (a global-descriptor file for retrieval? dqm needs hloc's local features)"
    if "matches0" in keys:
        return " (an hloc matches file? dqm needs the features file)"
    return ""


def read_h5_features(path: PathLike, image_dir: PathLike | None = None,
                     names: Sequence[str] | None = None) -> FeatureSet:
    """Read an hloc local-features file as a FEATURES set.

    Images come in sorted name order (Python string order), or in the order of
    ``names`` when given (those images only); they get image ids 0..m-1 in that
    order. Descriptors are transposed from hloc's (D, N) to (N, D) float32;
    keypoints are (N, 4) float32 x, y, size, angle (see the module doc for the
    conventions). ``image_names`` are ``image_dir / name`` when ``image_dir``
    is given, else hloc's names. An image with no keypoints is kept (its id
    simply has no features). Raises InputError naming the problem.
    """
    h5py = require_h5py()
    path = _check_h5_file(h5py, Path(path))
    try:
        fd = h5py.File(str(path), "r")
    except OSError as exc:
        raise InputError(f"{path}: not a readable HDF5 file ({exc})") from None
    with fd:
        present = _image_names(h5py, fd)
        if not present:
            raise InputError(f"{path}: no image groups (no group holds a keypoints / descriptors dataset)")
        if names is None:
            order = present
        else:
            order = [str(n) for n in names]
            if not order:
                raise InputError("names is empty: give at least one image name, or None for all")
            if len(set(order)) != len(order):
                raise InputError("names lists an image twice")
            known = set(present)
            missing = [n for n in order if n not in known]
            if missing:
                raise InputError(f"{path}: no image named {missing[0]!r} ({len(missing)} of the names missing; "
                                 f"the file has e.g. {present[:3]})")
        D: list[np.ndarray] = []
        K: list[np.ndarray] = []
        ids: list[np.ndarray] = []
        dim: int | None = None
        dim_from = ""
        for k, name in enumerate(order):
            desc, kp = _read_group(fd[name], name, path)
            if dim is None:
                dim, dim_from = desc.shape[1], name
            elif desc.shape[1] != dim:
                raise InputError(f"{path}: descriptor dimension differs between images: {dim} in {dim_from!r}, "
                                 f"{desc.shape[1]} in {name!r}")
            D.append(desc)
            K.append(kp)
            ids.append(np.full(len(kp), k, np.int64))
    image_names = [str(Path(image_dir) / n) for n in order] if image_dir is not None else list(order)
    fs = FeatureSet(descriptors=np.concatenate(D), image_ids=np.concatenate(ids), keypoints=np.concatenate(K),
                    image_names=np.array(image_names, dtype=str))
    return fs.validate(str(path))


def _read_group(grp, name: str, path: Path):
    """(descriptors (n, d) float32, keypoints (n, 4) float32) of one image group."""
    keys = list(grp.keys())
    for key in ("keypoints", "descriptors"):
        if key not in keys:
            raise InputError(f"{path}: image {name!r} has no {key!r} dataset (has {sorted(keys)})"
                             + _kind_hint(keys))
    kp = np.asarray(grp["keypoints"][()])
    desc = np.asarray(grp["descriptors"][()])
    for arr, key in ((kp, "keypoints"), (desc, "descriptors")):
        if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)) \
                or arr.dtype == np.bool_:
            raise InputError(f"{path}: image {name!r}: {key} must be numbers, got dtype {arr.dtype}")
    if kp.ndim != 2 or kp.shape[1] < 2:
        raise InputError(f"{path}: image {name!r}: keypoints must be (N, 2) x, y, got shape {kp.shape}")
    n = kp.shape[0]
    if desc.ndim != 2:
        raise InputError(f"{path}: image {name!r}: descriptors must be 2-D (D x N), got shape {desc.shape}")
    if desc.shape[1] != n:
        hint = " (stored N x D? hloc's layout is D x N)" if desc.shape[0] == n else ""
        raise InputError(f"{path}: image {name!r}: {n} keypoints but descriptors of shape {desc.shape}, "
                         f"expected (D, {n}){hint}")
    if desc.shape[0] == 0:
        raise InputError(f"{path}: image {name!r}: descriptors have zero dimensions (shape {desc.shape})")
    desc = np.ascontiguousarray(desc.T, dtype=np.float32)
    if desc.size and not np.isfinite(desc).all():
        bad = np.flatnonzero(~np.isfinite(desc).all(axis=1))
        kind = "NaN" if np.isnan(desc[bad[0]]).any() else "inf"
        raise InputError(f"{path}: image {name!r}: descriptors contain {kind} in {len(bad)} feature(s), "
                         f"first at keypoint {bad[0]}")
    out = np.empty((n, 4), np.float32)
    out[:, :2] = kp[:, :2]
    if n and not np.isfinite(out[:, :2]).all():
        raise InputError(f"{path}: image {name!r}: keypoints contain NaN or inf")
    out[:, 2] = _optional_column(grp, "scales", n, DEFAULT_SIZE, name, path)
    out[:, 3] = _optional_column(grp, "oris", n, DEFAULT_ANGLE, name, path)
    return desc, out


def _optional_column(grp, key: str, n: int, default: float, name: str, path: Path) -> np.ndarray:
    if key not in grp:
        return np.full(n, default, np.float32)
    v = np.asarray(grp[key][()])
    if v.shape != (n,):
        raise InputError(f"{path}: image {name!r}: {key} must have one value per keypoint ({n}), got shape {v.shape}")
    return v.astype(np.float32)


def _check_name(name: str) -> str:
    parts = name.split("/")
    if not name or name.startswith("/") or any(p in ("", ".", "..") for p in parts):
        raise InputError(f"image name {name!r} cannot be an hloc group name: it must be a relative path "
                         "like 'seq1/img0.jpg' (pass image_dir= or names=)")
    return name


def _names_for_writing(fs: FeatureSet, names: Sequence[str] | None, image_dir: PathLike | None,
                       n_ids: int) -> list[str]:
    """hloc's name of every image id: at least ``n_ids`` names, all valid group names, no repeats."""
    if names is not None:
        out = [str(n) for n in names]
    elif fs.image_names is not None:
        out = [str(n) for n in np.asarray(fs.image_names).tolist()]
        if image_dir is not None:
            root = Path(image_dir)
            rel = []
            for n in out:
                try:
                    rel.append(Path(n).relative_to(root).as_posix())
                except ValueError:
                    raise InputError(f"image {n} is not inside the image folder {root}") from None
            out = rel
        else:
            out = [Path(n).as_posix() for n in out]
    else:
        raise InputError("the features have no image_names: pass names= (hloc's names, relative to the image folder)")
    if len(out) < n_ids:
        raise InputError(f"{len(out)} image name(s) but the image ids go up to {n_ids - 1} (one name per id needed)")
    if not out:
        raise InputError("no images to write")
    for n in out:
        _check_name(n)
    if len(set(out)) != len(out):
        raise InputError("two images have the same name; hloc needs one group per image")
    return out


def _image_size_of(path: str) -> np.ndarray | None:
    """(width, height) of an image file as hloc reads it (EXIF orientation ignored), or None."""
    if not Path(path).is_file():
        return None
    import cv2

    img = cv2.imread(path, cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        return None
    return np.array([img.shape[1], img.shape[0]], np.int64)


def write_h5_features(path: PathLike, feature_set: FeatureSet, names: Sequence[str] | None = None, *,
                      image_dir: PathLike | None = None, image_sizes: ArrayLike | None = None,
                      scores: ArrayLike | None = None,
                      overwrite: bool = False, with_descriptors: bool = True) -> Path:
    """Write a FEATURES set as an hloc local-features file; returns the path.

    One group per image (names with '/' become nested groups), holding
    ``keypoints`` (N, 2) float32 x, y (unchanged: both use pixel centres at
    integer coordinates), ``descriptors`` (D, N) float32, ``scores`` (N,)
    float32 (``scores``, one per feature, default 1.0) and ``image_size``
    (width, height). Keypoint sizes and angles are written as hloc's ``scales``
    and ``oris`` when any is set (size != 0 or angle != -1), as hloc's DoG
    extractor does. Every image id 0..m-1 gets a group, even without features.

    Names: ``names`` (one per image id) if given, else the set's
    ``image_names`` made relative to ``image_dir`` (as hloc names images),
    else ``image_names`` as they are (they must then be relative paths).

    ``image_sizes``: (m, 2) width, height per image id; by default each size is
    read from the image file (``image_names``) when it exists, and otherwise
    left out. hloc's matchers (``match_features``) need ``image_size``.

    ``with_descriptors=False`` leaves ``descriptors`` out (the features' own are then
    ignored): enough for hloc's reconstruction and triangulation, which read keypoints only,
    when the clusters came without descriptors (a distributed job's CLUSTERS file).

    An existing ``path`` is refused unless ``overwrite``; the file is written
    to a temporary name and renamed, so a failed write leaves no partial file.
    """
    h5py = require_h5py()
    path = Path(path)
    if path.exists() and not overwrite:
        raise InputError(f"{path} exists; pass overwrite=True to replace it")
    if path.is_dir():
        raise InputError(f"{path} is a directory")
    fs = feature_set.validate("feature_set")
    if fs.keypoints is None:
        raise InputError("the features have no keypoints; an hloc features file needs them")
    desc = np.asarray(fs.descriptors)
    ids = np.asarray(fs.image_ids, np.int64)
    if len(ids) and ids.min() < 0:
        raise InputError(f"image ids must be >= 0, got {ids.min()}")
    n_ids = int(ids.max()) + 1 if len(ids) else 0
    image_names = _names_for_writing(fs, names, image_dir, n_ids)
    m = len(image_names)
    kp = np.asarray(fs.keypoints, np.float32)
    sizes = kp[:, 2] if kp.shape[1] > 2 else np.full(len(kp), DEFAULT_SIZE, np.float32)
    angles = kp[:, 3] if kp.shape[1] > 3 else np.full(len(kp), DEFAULT_ANGLE, np.float32)
    write_scales = bool((sizes != DEFAULT_SIZE).any())
    write_oris = bool((angles != DEFAULT_ANGLE).any())
    if scores is None:
        sc = np.ones(len(desc), np.float32)
    else:
        sc = np.asarray(scores, np.float32)
        if sc.shape != (len(desc),):
            raise InputError(f"scores must have one value per feature ({len(desc)}), got shape {sc.shape}")
    wh: dict[int, np.ndarray] = {}
    if image_sizes is not None:
        arr = np.asarray(image_sizes)
        if arr.shape != (m, 2) or not np.issubdtype(arr.dtype, np.number):
            raise InputError(f"image_sizes must be (m, 2) width, height for the {m} image(s), got shape {arr.shape}")
        wh = {k: arr[k].astype(np.int64) for k in range(m)}
    elif fs.image_names is not None and len(fs.image_names) >= m:
        for k in range(m):
            size = _image_size_of(str(fs.image_names[k]))
            if size is not None:
                wh[k] = size
    order = np.argsort(ids, kind="stable")
    bounds = np.searchsorted(ids[order], np.arange(m + 1))
    with atomic_output(path) as tmp, h5py.File(tmp, "w") as fd:
        for k, name in enumerate(image_names):
            rows = order[bounds[k]:bounds[k + 1]]
            try:
                grp = fd.create_group(name)
            except ValueError as exc:
                raise InputError(f"image name {name!r} clashes with another image's group ({exc})") from None
            grp.create_dataset("keypoints", data=np.ascontiguousarray(kp[rows, :2]))
            if with_descriptors:
                grp.create_dataset("descriptors", data=np.ascontiguousarray(desc[rows].T, dtype=np.float32))
            grp.create_dataset("scores", data=sc[rows])
            if write_scales:
                grp.create_dataset("scales", data=sizes[rows])
            if write_oris:
                grp.create_dataset("oris", data=angles[rows])
            if k in wh:
                grp.create_dataset("image_size", data=wh[k])
    return path


def names_to_pair(name0: str, name1: str) -> str:
    """hloc's group of an image pair in a matches file: both names with '/' made '-', joined by '/'.

    As ``hloc/utils/parsers.py`` ``names_to_pair`` (the current format; hloc's readers also
    try the reversed pair and an older '_' separator).
    """
    return name0.replace("/", "-") + "/" + name1.replace("/", "-")


def check_pair_names(names: Sequence[str]) -> list[str]:
    """The names, checked for hloc's matches and pairs files; InputError naming the first problem.

    Each must be a relative '/'-separated path (an hloc group name), hold no white space
    (``pairs.txt`` is split on it) and stay distinct once '/' becomes '-' (:func:`names_to_pair`).
    """
    out = [_check_name(str(n)) for n in names]
    for n in out:
        if any(ch.isspace() for ch in n):
            raise InputError(f"image name {n!r} holds white space, which hloc's pairs file cannot carry "
                             "(rename the image)")
    flat: dict[str, str] = {}
    for n in out:
        other = flat.setdefault(n.replace("/", "-"), n)
        if other != n:
            raise InputError(f"images {other!r} and {n!r} get one hloc pair name ({n.replace('/', '-')!r}: "
                             "'/' becomes '-'); rename one")
    return out


@dataclass
class MatchesSummary:
    """What :func:`write_h5_matches` wrote: the image pairs (hloc names, in file order) and the match count."""

    path: Path
    pairs: list[tuple[str, str]]
    n_matches: int


def write_h5_matches(path: PathLike, labels: ArrayLike, image_ids: ArrayLike, names: Sequence[str], *,
                     overwrite: bool = False, matches: str = DEFAULT_CLUSTER_MATCHES) -> MatchesSummary:
    """Write the matches that clusters imply as an hloc matches file (``match_features`` layout).

    ``matches``: which members of a cluster, in two different images, are a match
    (:func:`dqm.vision.colmap.cluster_pairs`: ``auto``, the default, every two but log-spaced members in a
    track through a run of frames; ``all``, every two; ``log``, log-spaced ones everywhere). One group per image
    pair with at least one match, named ``names_to_pair(names[a], names[b])`` with image ``a``
    before ``b`` in image-id order, holding ``matches0`` (int32, one entry per feature of image
    ``a`` in row order: the index of its match among image ``b``'s features, -1 for none) and
    ``matching_scores0`` (float16: 1 where matched, 0 elsewhere). hloc itself stores ``matches0``
    as int16; int32 keeps images with more than 32,767 features right, and hloc's readers take any
    integer type. ``names``: hloc's name of every image id (relative to the image folder,
    :func:`check_pair_names`). An existing ``path`` is refused unless ``overwrite``; the file is
    written to a temporary name and renamed.
    """
    h5py = require_h5py()
    path = Path(path)
    if path.exists() and not overwrite:
        raise InputError(f"{path} exists; pass overwrite=True to replace it")
    labels = np.asarray(labels, np.int64)
    ids = np.asarray(image_ids, np.int64)
    if labels.shape != ids.shape or labels.ndim != 1:
        raise InputError(f"labels {labels.shape} and image_ids {ids.shape} must be 1-D arrays of one length")
    names = check_pair_names(names)
    if len(ids) and (ids.min() < 0 or ids.max() >= len(names)):
        raise InputError(f"image ids must index the {len(names)} image names (0..{len(names) - 1})")
    pairs = cluster_pairs(labels, ids, matches)
    local = local_indices(ids)
    counts = np.bincount(ids, minlength=len(names))
    written: list[tuple[str, str]] = []
    n_matches = 0
    with atomic_output(path) as tmp, h5py.File(tmp, "w") as fd:
        for (a, b), m in sorted(pairs.items()):
            matches0 = np.full(counts[a], -1, np.int32)
            scores0 = np.zeros(counts[a], np.float16)
            matches0[local[m[:, 0]]] = local[m[:, 1]]
            scores0[local[m[:, 0]]] = 1.0
            grp = fd.create_group(names_to_pair(names[a], names[b]))
            grp.create_dataset("matches0", data=matches0)
            grp.create_dataset("matching_scores0", data=scores0)
            written.append((names[a], names[b]))
            n_matches += len(m)
    return MatchesSummary(path, written, n_matches)


def write_pairs(path: PathLike, pairs: Sequence[tuple[str, str]], *, overwrite: bool = False) -> Path:
    """Write an hloc pairs file: one ``name0 name1`` line per pair (``pairs_from_*`` layout); returns the path.

    Refuses an existing ``path`` unless ``overwrite``; written to a temporary name and renamed.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise InputError(f"{path} exists; pass overwrite=True to replace it")
    with atomic_output(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        fh.writelines(f"{a} {b}\n" for a, b in pairs)
    return path


def read_h5_matches(path: PathLike, name0: str, name1: str) -> np.ndarray:
    """The matches of one image pair in an hloc matches file: (k, 2) int64 keypoint indices, column 0 in ``name0``.

    Finds the pair's group in either order (as hloc's ``find_pair``; the older '_' separator is
    not read) and keeps the entries of ``matches0`` that are not -1. InputError if the pair is absent.
    """
    h5py = require_h5py()
    path = _check_h5_file(h5py, Path(path))
    with h5py.File(str(path), "r") as fd:
        for key, flip in ((names_to_pair(name0, name1), False), (names_to_pair(name1, name0), True)):  # noqa: B007 - read after the break
            if key in fd and isinstance(fd[key], h5py.Group) and "matches0" in fd[key]:
                m0 = np.asarray(fd[key]["matches0"][()], np.int64)
                break
        else:
            raise InputError(f"{path}: no matches for the image pair {name0!r}, {name1!r}")
    idx = np.flatnonzero(m0 != -1)
    out = np.stack([idx, m0[idx]], axis=1)
    return out[:, ::-1].copy() if flip else out
