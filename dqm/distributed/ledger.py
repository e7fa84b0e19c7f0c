"""The one traffic ledger: bytes and messages per directed link and message kind.

The simulator's in-memory bus, the runtime's zenoh bus and the coordinator's
report all count with :class:`TrafficLedger`, so their numbers are made the
same way. A message is metered as its payload plus the key it is put on.

An agent reports what it sent inside its ``stats`` message as flat numeric
fields (``sent:<dst>:<kind>:bytes`` / ``:messages``); :meth:`TrafficLedger.as_stats`
writes them and :meth:`TrafficLedger.add_stats` reads them back, here and
nowhere else.
"""
from __future__ import annotations

import re
import threading
from collections import defaultdict
from typing import Dict, List, Mapping, Optional, Tuple

#: the index of the coordinator in (src, dst) pairs
COORDINATOR = -1

Link = Tuple[int, int]
Entry = Tuple[int, int, str]


def endpoint_name(i: int) -> str:
    """``coordinator`` or ``agent<i>``: how reports name a link's ends."""
    return "coordinator" if i == COORDINATOR else f"agent{i}"


class TrafficLedger:
    """Bytes and messages per ``(src, dst, kind)``, safe to update from several threads."""

    _SENT = "sent:"

    def __init__(self):
        self.bytes: Dict[Entry, int] = defaultdict(int)
        self.count: Dict[Entry, int] = defaultdict(int)
        self._by_src: Dict[int, int] = defaultdict(int)  # bytes per sender: every state change reports its own
        self.lock = threading.Lock()

    # ------------------------------------------------------------------ counting
    def add(self, src: int, dst: int, kind: str, nbytes: int, messages: int = 1) -> None:
        with self.lock:
            self.bytes[(src, dst, kind)] += int(nbytes)
            self.count[(src, dst, kind)] += int(messages)
            self._by_src[src] += int(nbytes)

    def entries(self) -> Dict[Entry, Tuple[int, int]]:
        """``(src, dst, kind) -> (bytes, messages)``, copied under the lock."""
        with self.lock:
            return {k: (v, self.count[k]) for k, v in self.bytes.items()}

    def as_stats(self, src: Optional[int] = None) -> Dict[str, float]:
        """What ``src`` sent (everything when None) as the flat fields of a ``stats`` message."""
        out: Dict[str, float] = {}
        for (s, d, k), (b, c) in self.entries().items():
            if src is None or s == src:
                out[f"{self._SENT}{d}:{k}:bytes"] = float(b)
                out[f"{self._SENT}{d}:{k}:messages"] = float(c)
        return out

    def add_stats(self, src: int, values: Mapping[str, float]) -> None:
        """Count what an agent's ``stats`` message says ``src`` sent (the inverse of :meth:`as_stats`)."""
        for key, v in values.items():
            if key.startswith(self._SENT):
                dst, kind, what = key[len(self._SENT):].rsplit(":", 2)
                with self.lock:
                    (self.bytes if what == "bytes" else self.count)[(src, int(dst), kind)] += int(v)
                    if what == "bytes":
                        self._by_src[src] += int(v)

    @classmethod
    def strip_stats(cls, values: Mapping[str, float]) -> Dict[str, float]:
        """A ``stats`` message's fields without the traffic ones."""
        return {k: v for k, v in values.items() if not k.startswith(cls._SENT)}

    # ------------------------------------------------------------------ reading
    def total(self, kind: Optional[str] = None) -> int:
        return sum(b for (_, _, k), (b, _) in self.entries().items() if kind is None or k == kind)

    def messages(self, kind: Optional[str] = None) -> int:
        return sum(c for (_, _, k), (_, c) in self.entries().items() if kind is None or k == kind)

    def sent_by(self, src: int) -> int:
        """Bytes sent by ``src`` so far."""
        with self.lock:
            return self._by_src.get(src, 0)

    def per_link(self) -> Dict[Link, int]:
        out: Dict[Link, int] = defaultdict(int)
        for (s, d, _), (b, _) in self.entries().items():
            out[(s, d)] += b
        return dict(out)

    def per_kind(self) -> Dict[str, Tuple[int, int]]:
        out: Dict[str, List[int]] = defaultdict(lambda: [0, 0])
        for (_, _, k), (b, c) in self.entries().items():
            out[k][0] += b
            out[k][1] += c
        return {k: (v[0], v[1]) for k, v in out.items()}

    def as_json(self) -> dict:
        """Every (src, dst, kind) entry."""
        entries = self.entries()
        return {
            "links": [{"src": endpoint_name(s), "dst": endpoint_name(d), "kind": k, "bytes": b, "messages": c}
                      for (s, d, k), (b, c) in sorted(entries.items())],
            "total_bytes": sum(b for b, _ in entries.values()),
            "total_messages": sum(c for _, c in entries.values()),
        }

    def report(self) -> dict:
        """Per-link and per-kind totals (``links``, ``kinds``, ``total_bytes``): the shape of the runtime's
        report and of :func:`dqm.distributed.protocol.traffic_table`."""
        links: Dict[Link, List[int]] = defaultdict(lambda: [0, 0])
        for (s, d, _), (b, c) in self.entries().items():
            links[(s, d)][0] += b
            links[(s, d)][1] += c
        return {
            "links": [{"src": endpoint_name(s), "dst": endpoint_name(d), "bytes": b, "messages": c}
                      for (s, d), (b, c) in sorted(links.items())],
            "kinds": {k: {"bytes": b, "messages": c} for k, (b, c) in sorted(self.per_kind().items())},
            "total_bytes": sum(b for b, _ in links.values()),
        }

    def table(self) -> str:
        from .protocol import traffic_table

        return traffic_table(self.report())


class Meter(TrafficLedger):
    """A process's ledger plus what it refused on receipt: rejected messages per reason, duplicates
    dropped, and messages resent for want of an acknowledgement."""

    def __init__(self):
        super().__init__()
        self.rejected: Dict[str, int] = defaultdict(int)
        self.duplicates = 0
        self.resent = 0

    def reject(self, reason: str) -> None:
        """Count a refused message under its reason (numbers in it replaced by N, so that reasons group)."""
        reason = re.sub(r"\d+", "N", reason)[:80]
        with self.lock:
            self.rejected[reason] += 1

    def duplicate(self) -> None:
        with self.lock:
            self.duplicates += 1

    def resend(self) -> None:
        with self.lock:
            self.resent += 1

    def counters(self) -> Tuple[Dict[str, int], int, int]:
        """``(rejected per reason, duplicates, resent)`` copied under the lock."""
        with self.lock:
            return dict(self.rejected), self.duplicates, self.resent

    def counter_stats(self) -> Dict[str, float]:
        """The counters as an agent's ``stats`` entries: ``rejected:<reason>``, ``duplicates``, ``resent``
        (a process reports them once, with its home agent's statistics)."""
        rejected, duplicates, resent = self.counters()
        out = {f"rejected:{reason}": float(count) for reason, count in rejected.items()}
        out.update(duplicates=float(duplicates), resent=float(resent))
        return out
