"""Change events of online QuickMatch: what happened to which cluster after an ``add`` or ``remove``.

Clusters carry **stable ids** (integers, never reused) for as long as they
survive, so a tracking user reads "cluster 17 gained a feature in image 42"
rather than diffing label vectors. Features are named by their **key**: the
number :class:`dqm.core.online.OnlineQuickMatch` gave them on arrival (0, 1,
2, ... over the whole stream, never reused).

Event kinds (``ClusterEvent.kind``), in the order a change set lists them:

* ``"shrunk"``: ``features`` left ``cluster`` because their image was removed;
  the cluster lives on.
* ``"removed"``: the cluster's last ``features`` were removed; it is gone.
* ``"split"``: ``features`` left cluster ``source`` (which lives on) for
  ``cluster``: a new cluster when ``new`` is true, otherwise an existing one.
* ``"merged"``: every remaining feature of ``source`` joined ``cluster``;
  ``source`` is gone.
* ``"created"``: ``features``, all newly added, form the new ``cluster``.
* ``"grown"``: newly added ``features`` joined the existing (or just split
  off) ``cluster``.

Replaying a change set's events in order over the previous assignment
(feature key -> cluster id) gives the new assignment exactly:
:func:`replay` does that, and the tests check it after every call.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, MutableMapping

import numpy as np

EVENT_KINDS = ("shrunk", "removed", "split", "merged", "created", "grown")
#: kinds after which the features no longer belong to any cluster
LEAVING = ("shrunk", "removed")


@dataclass(frozen=True)
class ClusterEvent:
    """One change to one cluster (see the module docstring for the kinds).

    ``features``: keys of the features concerned; ``images``: their image ids
    (same order); ``source``: the cluster they came from (``split``, ``merged``;
    -1 otherwise); ``new``: whether ``cluster`` was born in this change set.
    """

    kind: str
    cluster: int
    features: np.ndarray
    images: np.ndarray
    source: int = -1
    new: bool = False

    def __str__(self) -> str:
        n = len(self.features)
        imgs = ", ".join(str(int(i)) for i in np.unique(self.images)[:6])
        more = ", ..." if len(np.unique(self.images)) > 6 else ""
        what = f"{n} feature{'s' if n != 1 else ''} (images {imgs}{more})"
        if self.kind == "created":
            return f"cluster {self.cluster} created with {what}"
        if self.kind == "grown":
            return f"cluster {self.cluster} gained {what}"
        if self.kind == "merged":
            return f"cluster {self.source} merged into cluster {self.cluster} ({what})"
        if self.kind == "split":
            into = "new cluster" if self.new else "cluster"
            return f"cluster {self.source} split: {what} moved to {into} {self.cluster}"
        if self.kind == "shrunk":
            return f"cluster {self.cluster} lost {what} (removed)"
        return f"cluster {self.cluster} removed with its last {what}"

    def to_dict(self) -> Dict[str, Any]:
        """Plain types (ints and lists), for JSON or msgpack."""
        return {"kind": self.kind, "cluster": int(self.cluster), "source": int(self.source), "new": bool(self.new),
                "features": [int(k) for k in self.features], "images": [int(i) for i in self.images]}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "ClusterEvent":
        """Inverse of :meth:`to_dict` (no validation: check untrusted input first)."""
        return cls(str(d["kind"]), int(d["cluster"]), np.asarray(d["features"], np.int64),
                   np.asarray(d["images"], np.int64), int(d.get("source", -1)), bool(d.get("new", False)))


@dataclass(frozen=True)
class ChangeSet:
    """What one ``add`` or ``remove`` changed.

    ``events``: the :class:`ClusterEvent` list, replayable in order;
    ``added`` / ``removed``: keys of the features that arrived or left;
    ``stats``: counts and times of the update (features whose density or
    parent changed, features whose merges were replayed, seconds).
    """

    events: List[ClusterEvent]
    added: np.ndarray
    removed: np.ndarray
    stats: Dict[str, float] = field(default_factory=dict)

    def counts(self) -> Dict[str, int]:
        """Number of events of every kind."""
        out = {k: 0 for k in EVENT_KINDS}
        for e in self.events:
            out[e.kind] += 1
        return out

    def summary(self) -> str:
        """One line: features in and out, events per kind, features touched."""
        c = self.counts()
        kinds = ", ".join(f"{v} {k}" for k, v in c.items() if v) or "no cluster changes"
        touched = self.stats.get("replayed")
        tt = f"; merges replayed over {touched:.0f} features" if touched is not None else ""
        return f"+{len(self.added)} / -{len(self.removed)} features: {kinds}{tt}"

    def to_dict(self) -> Dict[str, Any]:
        return {"events": [e.to_dict() for e in self.events], "added": [int(k) for k in self.added],
                "removed": [int(k) for k in self.removed],
                "stats": {k: float(v) for k, v in self.stats.items()}}


def replay(assignment: MutableMapping[int, int], events: List[ClusterEvent]) -> MutableMapping[int, int]:
    """Apply ``events`` in order to ``assignment`` (feature key -> cluster id), in place; returns it."""
    for e in events:
        keys = [int(k) for k in e.features]
        if e.kind in LEAVING:
            for k in keys:
                del assignment[k]
        else:
            for k in keys:
                assignment[k] = int(e.cluster)
    return assignment
