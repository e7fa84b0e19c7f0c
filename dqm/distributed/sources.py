"""Where a distributed job's features start and where its clusters end up.

* **Ownership.** An agent holds whole images (a camera, a robot). :func:`image_owners` is the rule
  the simulator and ``dqm run`` use to deal one set of images out (image k, in sorted order of the
  ids, to agent k mod M); :func:`split_features` cuts a FEATURES set that way (or by lists of
  images), keeping keypoints, image names and global feature ids (``dqm split``).
* **Image identity.** Every FEATURES file numbers its own images: two robots that each ran
  ``dqm extract`` both hold an image 0. On the wire an image is therefore named by its source:
  :class:`AgentFeatures` gives each distinct (file, image id) of an agent the wire id
  ``(agent << 32) + k``, so images of different agents (or files) never meet as one image in a
  sigma, a C2 check or a merge. Only equality of image ids matters to the algorithm, so when no two
  sources share an id the clusters are exactly those of the same images numbered globally.
* **The catalog.** With the result, each agent reports to the coordinator what the CLUSTERS file
  needs of its own features and nothing more (``catalog`` message: feature ids, image, keypoints,
  ground truth; the image table with the local ids and names; never descriptors).
  :func:`assemble_clusters` turns the catalogs and the labels into the CLUSTERS arrays, with the
  images numbered by :func:`dqm.io.combine_images` (kept when no two sources share an id,
  numbered afresh otherwise).
* **Labels.** :func:`assemble_labels` puts the agents' per-cell labels together (offsets, order by
  feature id, canonical numbering): the one assembly the simulator and the coordinator share.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from .. import io
from ..core.tree import canonical_labels
from ..validation import InputError, check_magnitude
from . import protocol

#: wire image id = (agent << IMAGE_BITS) + index of the (file, image) in the agent's image table
IMAGE_BITS = 32
#: separator of the image names in a catalog (cannot occur in a path)
NAME_SEPARATOR = b"\0"


def image_owners(image_ids: np.ndarray, m: int) -> np.ndarray:
    """Source agent of every feature: image k (in sorted order of ids) belongs to agent k mod m."""
    _, inv = np.unique(image_ids, return_inverse=True)
    return (inv.ravel() % m).astype(np.int64)


def split_features(fs: io.FeatureSet, m: Optional[int] = None,
                   image_lists: Optional[Sequence[Sequence[int]]] = None) -> List[io.FeatureSet]:
    """One FEATURES set per agent: by :func:`image_owners` (``m`` agents) or by ``image_lists`` (the
    image ids of each agent; every image of ``fs`` in exactly one list).

    Each part keeps its rows' keypoints and ground truth, the whole ``image_names`` array (so that
    its image ids keep meaning the same images) and global ``feature_ids``: the file's own, or
    its row numbers.
    """
    ids = np.asarray(fs.image_ids, np.int64)
    if image_lists is None:
        if m is None or m < 1:
            raise InputError(f"the number of agents must be at least 1, got {m}")
        owner = image_owners(ids, m)
    else:
        m = len(image_lists)
        owner = np.full(len(ids), -1, np.int64)
        present = set(np.unique(ids).tolist())
        seen: Dict[int, int] = {}
        for a, lst in enumerate(image_lists):
            for img in lst:
                if int(img) in seen:
                    raise InputError(f"image {img} is in the lists of agents {seen[int(img)]} and {a}; "
                                     "an image belongs to one agent")
                if int(img) not in present:
                    raise InputError(f"the list of agent {a} names image {img}, which has no features")
                seen[int(img)] = a
                owner[ids == int(img)] = a
        left = sorted(present - set(seen))
        if left:
            raise InputError(f"image(s) {', '.join(map(str, left[:5]))}{' ...' if len(left) > 5 else ''} are in "
                             "no agent's list; every image must belong to one agent")
    fid = fs.global_ids()
    desc = protocol.wire_descriptors(fs.descriptors)
    parts = []
    for a in range(m):
        sel = np.flatnonzero(owner == a)
        parts.append(io.FeatureSet(
            descriptors=desc[sel], image_ids=ids[sel],
            keypoints=None if fs.keypoints is None else np.asarray(fs.keypoints)[sel],
            image_names=fs.image_names,
            point_ids=None if fs.point_ids is None else np.asarray(fs.point_ids)[sel],
            feature_ids=fid[sel]))
    return parts


@dataclass
class AgentFeatures:
    """An agent's own features as the protocol sees them, and the catalog it reports.

    ``ids``: global feature ids; ``image_ids``: wire image ids (``(agent << 32) + k``, k indexing
    the agent's image table); ``descriptors``: as they travel (uint8 or float32); ``catalog``: the
    payload of the ``catalog`` message (see :func:`catalog_payload`).
    """

    ids: np.ndarray
    image_ids: np.ndarray
    descriptors: np.ndarray
    catalog: Dict[str, np.ndarray]

    def __len__(self) -> int:
        return len(self.ids)


def agent_features(sets: Sequence[io.FeatureSet], agent: int, sources: Optional[Sequence[str]] = None
                   ) -> AgentFeatures:
    """An agent's features from its FEATURES sets (one per file, in the order given).

    Feature ids: each file's ``feature_ids``, else ``(agent << 32) + row`` counted over the files.
    Images: every distinct (file, image id) gets the next index of the agent's image table.
    Refused, naming the file: no files, files of different dimensions, magnitudes outside the safe
    range, and feature ids that repeat.
    """
    if not sets:
        raise InputError("no features files given")
    names = list(sources) if sources is not None else [f"file {k}" for k in range(len(sets))]
    dims = {fs.descriptors.shape[1] for fs in sets}
    if len(dims) > 1:
        raise InputError("the agent's FEATURES files have descriptors of different dimensions ("
                         + ", ".join(f"{n}: {fs.descriptors.shape[1]}" for n, fs in zip(names, sets)) + ")")
    images, descs, keypoints, points = [], [], [], []
    table_file, table_local, table_names = [], [], []
    for f, (fs, src) in enumerate(zip(sets, names)):
        check_magnitude(np.asarray(fs.descriptors), f"{src}: descriptors")
        local, inverse = np.unique(np.asarray(fs.image_ids, np.int64), return_inverse=True)
        images.append(len(table_local) + inverse.ravel())
        table_file += [f] * len(local)
        table_local += local.tolist()
        table_names += [str(fs.image_names[k]) if fs.image_names is not None else "" for k in local.tolist()]
        descs.append(protocol.wire_descriptors(fs.descriptors))
        keypoints.append(None if fs.keypoints is None else np.asarray(fs.keypoints, np.float32))
        points.append(None if fs.point_ids is None else np.asarray(fs.point_ids, np.int64))
    all_ids = feature_ids(sets, agent)
    io.check_feature_ids(all_ids, len(all_ids), "this agent's FEATURES files")
    image = np.concatenate(images).astype(np.int64)
    kp = (np.concatenate(keypoints) if all(k is not None for k in keypoints)
          and len({k.shape[1] for k in keypoints}) == 1 else np.zeros((0, 4), np.float32))
    pid = (np.concatenate([p if p is not None else np.full(len(fs), -1, np.int64) for p, fs in zip(points, sets)])
           if any(p is not None for p in points) else np.zeros(0, np.int64))
    named = any(table_names)
    catalog = {
        "ids": all_ids, "image": image.astype(np.int32), "keypoints": kp, "point_ids": pid,
        "image_file": np.asarray(table_file, np.int64), "image_local": np.asarray(table_local, np.int64),
        "names": np.frombuffer(NAME_SEPARATOR.join(n.encode() for n in table_names), np.uint8).copy()
        if named else np.zeros(0, np.uint8),
    }
    wire = (np.int64(agent) << np.int64(IMAGE_BITS)) + image
    return AgentFeatures(all_ids, wire, np.concatenate(descs), catalog)


def feature_ids(sets: Sequence[io.FeatureSet], agent: int) -> np.ndarray:
    """The global ids of an agent's features, its FEATURES sets in the order given: each set's ``feature_ids``,
    else ``(agent << 32) + row``, the rows counted over the sets (int64; not checked for repeats)."""
    ids, offset = [], 0
    for fs in sets:
        if fs.feature_ids is not None:
            ids.append(np.asarray(fs.feature_ids, np.int64))
        else:
            ids.append((np.int64(agent) << np.int64(IMAGE_BITS)) + offset + np.arange(len(fs), dtype=np.int64))
        offset += len(fs)
    return np.concatenate(ids) if ids else np.zeros(0, np.int64)


def agent_files(spec: str, option: str) -> Tuple[int, List[str]]:
    """``"2=/data/a2.npz,/data/a2b.npz"`` -> ``(2, [...])``: an agent and the FEATURES files it holds, as a
    command line gives them (``option`` names the option in the one-line error)."""
    agent, sep, paths = spec.partition("=")
    if not sep or not agent.strip().isdigit() or not paths:
        raise InputError(f"{option} must look like AGENT=FILE[,FILE...], got {spec!r}")
    return int(agent), [p for p in paths.split(",") if p]


def load_agent_features(paths: Sequence, agent: int) -> AgentFeatures:
    """An agent's own features from FEATURES files (each read once): global ids from ``feature_ids`` or
    (agent << 32) + row, images named by their source (:func:`agent_features`)."""
    return agent_features([io.load_features(p) for p in paths], agent, [str(p) for p in paths])


def catalog_names(catalog: Dict[str, np.ndarray]) -> List[str]:
    """The image names of a catalog's image table ("" for every image when it has none)."""
    n = len(catalog["image_local"])
    raw = np.asarray(catalog["names"], np.uint8).tobytes()
    if not raw:
        return [""] * n
    names = [part.decode("utf-8", errors="replace") for part in raw.split(NAME_SEPARATOR)]
    return names if len(names) == n else [""] * n


def assemble_labels(results: Sequence[Tuple[np.ndarray, np.ndarray]]) -> Tuple[np.ndarray, np.ndarray]:
    """Feature ids (ascending) and canonical labels from every agent's ``(ids, labels)`` result.

    Each agent numbers its clusters from 0; they are offset so that no two agents' clusters share
    a number, then ordered by feature id and numbered canonically (first appearance)."""
    ids_l, lab_l, offset = [], [], 0
    for ids, labels in results:
        labels = np.asarray(labels, np.int64)
        ids_l.append(np.asarray(ids, np.int64))
        lab_l.append(labels + offset)
        offset += int(labels.max()) + 1 if len(labels) else 0
    ids = np.concatenate(ids_l) if ids_l else np.zeros(0, np.int64)
    labels = np.concatenate(lab_l) if lab_l else np.zeros(0, np.int64)
    order = np.argsort(ids, kind="stable")
    return ids[order], canonical_labels(labels[order])


@dataclass
class AssembledClusters:
    """The CLUSTERS arrays of a distributed job (``features.descriptors`` is None) and a note on how
    the images were numbered ("" when every source's image ids stayed)."""

    features: io.FeatureSet
    labels: np.ndarray
    note: str


def assemble_clusters(ids: np.ndarray, labels: np.ndarray, catalogs: Dict[int, Dict[str, np.ndarray]]
                      ) -> AssembledClusters:
    """The CLUSTERS arrays from the assembled labels (ids ascending, as :func:`assemble_labels`
    gives them) and every agent's catalog; raises ValueError if they do not describe the same features.

    Images: each (agent, file) is a source numbering its own images; :func:`dqm.io.combine_images`
    keeps their ids when no two sources share one and numbers them afresh otherwise.
    """
    agents = sorted(catalogs)
    sources, local_ids = [], []  # one source per (agent, file): its rows of the agent's image table
    for a in agents:
        files = np.asarray(catalogs[a]["image_file"], np.int64)
        local = np.asarray(catalogs[a]["image_local"], np.int64)
        for f in np.unique(files).tolist():
            rows = np.flatnonzero(files == f)
            sources.append((a, rows))
            local_ids.append(local[rows])
    new_ids, renumbered = io.combine_images(local_ids)
    # output image id of every (agent, table index); combine_images gives each source's ids in sorted order
    out_of = {a: np.zeros(len(catalogs[a]["image_local"]), np.int64) for a in agents}
    for (a, rows), lids, out in zip(sources, local_ids, new_ids):
        out_of[a][rows] = out[np.searchsorted(np.unique(lids), lids)]
    names: Dict[int, str] = {}
    for a in agents:
        for k, name in enumerate(catalog_names(catalogs[a])):
            names.setdefault(int(out_of[a][k]), name)
    cat_ids = np.concatenate([np.asarray(catalogs[a]["ids"], np.int64) for a in agents])
    order = np.argsort(cat_ids, kind="stable")
    if not np.array_equal(cat_ids[order], ids):
        raise ValueError(f"the agents' catalogs list {len(cat_ids)} features, their results {len(ids)} "
                         "(not the same feature ids)")
    image = np.concatenate([out_of[a][np.asarray(catalogs[a]["image"], np.int64)] for a in agents])[order]
    fs = io.FeatureSet(descriptors=None, image_ids=image, feature_ids=ids)
    if all(len(catalogs[a]["keypoints"]) == len(catalogs[a]["ids"]) for a in agents) and \
            len({catalogs[a]["keypoints"].shape[1] for a in agents}) == 1:
        fs.keypoints = np.concatenate([catalogs[a]["keypoints"] for a in agents])[order]
    if any(len(catalogs[a]["point_ids"]) for a in agents):
        fs.point_ids = np.concatenate([catalogs[a]["point_ids"] if len(catalogs[a]["point_ids"])
                                       else np.full(len(catalogs[a]["ids"]), -1, np.int64) for a in agents])[order]
    if any(names.values()):
        top = max(names) + 1 if names else 0
        fs.image_names = np.array([names.get(k, "") for k in range(top)])
    note = ""
    if renumbered:
        shared = io.shared_image_ids(local_ids)
        holders = sorted({a for (a, _), lids in zip(sources, local_ids) if np.isin(lids, shared).any()})
        note = (f"image id(s) {', '.join(map(str, shared[:5].tolist()))}{' ...' if len(shared) > 5 else ''} are used "
                f"by more than one FEATURES file (agents {', '.join(map(str, holders))}) for different images (every "
                f"file numbers its own images): the CLUSTERS file numbers the {sum(len(x) for x in local_ids)} "
                "images 0.. agent after agent; image_names say which is which")
    return AssembledClusters(fs, labels, note)
