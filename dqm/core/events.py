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

from collections.abc import Mapping, MutableMapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

EVENT_KINDS = ("shrunk", "removed", "split", "merged", "created", "grown")
#: kinds after which the features no longer belong to any cluster
LEAVING = ("shrunk", "removed")
#: events a change set's ``str`` / ``repr`` spell out (the rest are counted), so that printing a change
#: set stays short whatever its size
SHOWN_EVENTS = 3
#: feature keys / image ids an event's ``repr`` spells out
SHOWN_KEYS = 6


def _few(values: np.ndarray, limit: int = SHOWN_KEYS) -> str:
    """``[1, 2, 3, ...]`` (the first ``limit`` values, with their count when there are more)."""
    vals = [str(int(v)) for v in np.asarray(values).ravel()[:limit]]
    more = f", ... ({len(values)} in all)" if len(values) > limit else ""
    return "[" + ", ".join(vals) + more + "]"


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

    def __repr__(self) -> str:
        """Bounded: at most :data:`SHOWN_KEYS` feature keys and image ids, then their count."""
        return (f"ClusterEvent(kind={self.kind!r}, cluster={self.cluster}, features={_few(self.features)}, "
                f"images={_few(self.images)}, source={self.source}, new={self.new})")

    def to_dict(self) -> dict[str, Any]:
        """Plain types (ints and lists), for JSON or msgpack."""
        return {"kind": self.kind, "cluster": int(self.cluster), "source": int(self.source), "new": bool(self.new),
                "features": [int(k) for k in self.features], "images": [int(i) for i in self.images]}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ClusterEvent:
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

    events: list[ClusterEvent]
    added: np.ndarray
    removed: np.ndarray
    stats: dict[str, float] = field(default_factory=dict)

    def counts(self) -> dict[str, int]:
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

    def _first_events(self) -> list[str]:
        shown = [str(e) for e in self.events[:SHOWN_EVENTS]]
        if len(self.events) > SHOWN_EVENTS:
            shown.append(f"... {len(self.events) - SHOWN_EVENTS} more event(s)")
        return shown

    def __str__(self) -> str:
        """The :meth:`summary` line, then the first :data:`SHOWN_EVENTS` events, one per line (bounded)."""
        return "\n".join([self.summary()] + ["  " + line for line in self._first_events()])

    def __repr__(self) -> str:
        """One bounded line: the summary and the first events (``events`` holds them all)."""
        events = "; ".join(self._first_events()) or "none"
        return f"ChangeSet({self.summary()}; {len(self.events)} event(s): {events})"

    def to_dict(self) -> dict[str, Any]:
        """Plain types (ints, floats and lists), for JSON or msgpack."""
        return {"events": [e.to_dict() for e in self.events], "added": [int(k) for k in self.added],
                "removed": [int(k) for k in self.removed],
                "stats": {k: float(v) for k, v in self.stats.items()}}


def replay(assignment: MutableMapping[int, int], events: list[ClusterEvent]) -> MutableMapping[int, int]:
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
