"""Stable cluster ids across an online update, and the events that lead from the old ids to the new.

After an ``add`` or ``remove``, online QuickMatch replays merges in a region
(whole components of the merge forest) and gets fresh local labels there.
:func:`reconcile` names them: each local cluster inherits the id of the old
cluster it overlaps most (ties: lower old id, then lower local label; an old
id goes to one local cluster at most), the rest get new ids; then it lists the
:class:`~dqm.core.events.ClusterEvent` s, in the order :mod:`dqm.core.events`
documents (shrunk / removed, split / merged, created / grown), so that
replaying them over the old assignment gives the new one.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Set, Tuple

import numpy as np

from .events import ClusterEvent


@dataclass
class Reconciled:
    """What :func:`reconcile` decided: ``ids`` (stable id per region feature), ``events``, and the
    next unused cluster id."""

    ids: np.ndarray
    events: List[ClusterEvent]
    next_cid: int


def reconcile(keys: np.ndarray, images: np.ndarray, local: np.ndarray, old_cid: Dict[int, int],
              gone_keys: Set[int], gone_images: Dict[int, int], added_keys: Set[int], next_cid: int) -> Reconciled:
    """Stable ids for the region's new clusters, and the events that lead from the old ids to them.

    ``keys``, ``images``, ``local``: key, image and local label of every feature now in the region;
    ``old_cid``: key -> old cluster id of every feature the region held before (removed ones
    included); ``gone_keys`` / ``gone_images``: keys that left and their images; ``added_keys``:
    keys that arrived; ``next_cid``: the first unused cluster id.
    """
    rkeys = keys.tolist()
    key_image = dict(zip(rkeys, images.tolist()))
    events = _leaving_events(old_cid, gone_keys, gone_images)
    inherit, taken = _inheritance(rkeys, local.tolist(), old_cid, gone_keys)
    ids, born, next_cid = _assign_ids(local, inherit, next_cid)
    moves, announced = _move_events(rkeys, ids.tolist(), old_cid, taken, born, key_image)
    events += moves
    events += _arrival_events(rkeys, ids.tolist(), added_keys, born, announced, key_image)
    return Reconciled(ids, events, next_cid)


def _leaving_events(old_cid: Dict[int, int], gone_keys: Set[int], gone_images: Dict[int, int]
                    ) -> List[ClusterEvent]:
    """``removed`` (a cluster's last features left) or ``shrunk``, per old cluster, by id."""
    size: Dict[int, int] = {}
    for c in old_cid.values():
        size[c] = size.get(c, 0) + 1
    gone_by: Dict[int, List[int]] = {}
    for k in sorted(gone_keys):
        if k in old_cid:
            gone_by.setdefault(old_cid[k], []).append(k)
    events = []
    for c in sorted(gone_by):
        ks = gone_by[c]
        kind = "removed" if len(ks) == size[c] else "shrunk"
        events.append(ClusterEvent(kind, c, np.array(ks, np.int64),
                                   np.array([gone_images.get(k, -1) for k in ks], np.int64)))
    return events


def _inheritance(keys: List[int], local: List[int], old_cid: Dict[int, int], gone_keys: Set[int]
                 ) -> Tuple[Dict[int, int], Set[int]]:
    """Local label -> the old id it keeps (largest overlap first), and the set of old ids kept."""
    overlap: Dict[Tuple[int, int], int] = {}
    for k, lab in zip(keys, local):
        c = old_cid.get(k)
        if c is not None and k not in gone_keys:
            overlap[(c, lab)] = overlap.get((c, lab), 0) + 1
    inherit: Dict[int, int] = {}
    taken: Set[int] = set()
    for (c, lab), _ in sorted(overlap.items(), key=lambda kv: (-kv[1], kv[0][0], kv[0][1])):
        if lab in inherit or c in taken:
            continue
        inherit[lab] = c
        taken.add(c)
    return inherit, taken


def _assign_ids(local: np.ndarray, inherit: Dict[int, int], next_cid: int) -> Tuple[np.ndarray, Set[int], int]:
    """Id of every region feature: its label's inherited id, or a new one (by label order)."""
    born: Set[int] = set()
    ids_of_label: Dict[int, int] = {}
    for lab in sorted(set(local.tolist())):
        if lab in inherit:
            ids_of_label[lab] = inherit[lab]
        else:
            ids_of_label[lab] = next_cid
            born.add(next_cid)
            next_cid += 1
    ids = np.array([ids_of_label[lab] for lab in local.tolist()], np.int64)
    return ids, born, next_cid


def _move_events(keys: List[int], ids: List[int], old_cid: Dict[int, int], taken: Set[int], born: Set[int],
                 key_image: Dict[int, int]) -> Tuple[List[ClusterEvent], Set[int]]:
    """``split`` / ``merged`` per (old id, new id) that surviving features moved between, and the new
    clusters these events announced."""
    moves: Dict[Tuple[int, int], List[int]] = {}
    for k, t in zip(keys, ids):
        c = old_cid.get(k)
        if c is not None and c != t:
            moves.setdefault((c, t), []).append(k)
    last_part: Dict[int, Tuple[int, int]] = {}  # an old id nobody kept: its last move is the merge
    for (c, t) in sorted(moves):
        if c not in taken:
            last_part[c] = (c, t)
    events = []
    announced: Set[int] = set()
    for (c, t) in sorted(moves):
        ks = moves[(c, t)]
        kind = "merged" if last_part.get(c) == (c, t) else "split"
        is_new = t in born and t not in announced
        announced.add(t)
        events.append(ClusterEvent(kind, t, np.array(ks, np.int64), np.array([key_image[k] for k in ks]),
                                   source=c, new=is_new))
    return events, announced


def _arrival_events(keys: List[int], ids: List[int], added_keys: Set[int], born: Set[int], announced: Set[int],
                    key_image: Dict[int, int]) -> List[ClusterEvent]:
    """``created`` (a new cluster no move announced) or ``grown``, per cluster that new features joined."""
    arrivals: Dict[int, List[int]] = {}
    for k, t in zip(keys, ids):
        if k in added_keys:
            arrivals.setdefault(t, []).append(k)
    events = []
    for t in sorted(arrivals):
        ks = arrivals[t]
        kind = "created" if t in born and t not in announced else "grown"
        events.append(ClusterEvent(kind, t, np.array(ks, np.int64), np.array([key_image[k] for k in ks]),
                                   new=t in born))
    return events
