"""Reliable delivery, sans I/O: one process's sequence numbers, acknowledgements, resends,
duplicates and epochs.

Both buses keep one :class:`Delivery` per process and call it around their own puts: the zenoh
bus (:mod:`dqm.runtime.bus`) with the wall clock, the simulator's memory network
(:mod:`dqm.distributed.network`) with its virtual clock. It never sends and never reads a clock:

* :meth:`Delivery.next_seq` numbers the messages of a link (``src -> dst`` agents; -1 is the
  coordinator) in the current epoch;
* :meth:`Delivery.sending` keeps a message of an acknowledged kind (:data:`protocol.ACKED`)
  until its ack comes back; :meth:`Delivery.put_returned` starts its timer once the put
  returned (a put blocked behind a full link is not yet waiting for its ack);
* :meth:`Delivery.due` names the messages whose ack is overdue by the adaptive timeout
  (:class:`dqm.distributed.protocol.Retransmit`) and counts them resent;
* :meth:`Delivery.replay` gives every message sent to an agent in this epoch again (a takeover:
  the agent's new host runs it from its start); :meth:`Delivery.forget` stops waiting for the acks of
  agents that finished before their process was lost;
* :meth:`Delivery.receive` judges a decoded incoming message: of an earlier epoch, or of a
  later one that is not its ``start``: refused and counted; an ack: its message is done; an
  acknowledged kind: the ack to send back (every copy is acknowledged, the first ack may have
  been lost); a numbered message seen before: a duplicate, counted and dropped.

:meth:`Delivery.set_epoch` starts numbering, pending acknowledgements and duplicate detection
afresh. The counters (resends, duplicates, refusals per reason) go to the process's
:class:`~dqm.distributed.ledger.Meter`. A lock makes it safe to call from the zenoh bus's
receiver thread and its main thread at once.
"""
from __future__ import annotations

import threading
from collections import defaultdict
from dataclasses import dataclass
from typing import Dict, List, NamedTuple, Optional, Tuple

from . import messages, protocol
from .ledger import Meter

#: a pending message: (sending agent, receiving agent, sequence number)
Link = Tuple[int, int, int]


#: the slowest link rate (bytes/s) a first resend timeout assumes: a message waits for its ack at least as
#: long as everything this process had put and not yet seen acknowledged, itself included, takes at this rate
#: (1 Mbit/s). On a thin, saturated link an ack comes only after the megabytes queued before the message: a
#: timeout from the round trips of small messages alone resent parts that were still queued (docs/runtime.md)
FLOOR_BYTES_S = 125_000.0


@dataclass
class Pending:
    """A message kept until acknowledged: when its last send's put returned, how often it was sent, and
    the least it waits for its ack (the bytes ahead of it at :data:`FLOOR_BYTES_S`)."""

    sent_at: float
    tries: int
    payload: bytes
    kind: str
    floor_s: float = 0.0


class Resend(NamedTuple):
    """A message to put again: its link, kind and encoded bytes."""

    src: int
    dst: int
    seq: int
    kind: str
    payload: bytes


class Verdict(NamedTuple):
    """What to do with a received message: hand it over (``deliver``), and the ack to send back."""

    deliver: bool
    ack: Optional[bytes] = None


class Delivery:
    """One process's delivery state (see the module's text). ``job``: the job id acks carry."""

    def __init__(self, job: str, meter: Meter, retransmit: Optional[protocol.Retransmit] = None,
                 keep_log: bool = True):
        self.job = job
        #: every numbered message sent to each agent in this epoch, in order (:meth:`replay`)
        self.keep_log = keep_log
        self._log: Dict[int, List[Resend]] = defaultdict(list)
        #: agents that finished and whose process is gone: nothing sent to them waits for an ack
        self._gone: set = set()
        self.meter = meter
        self.retransmit = retransmit or protocol.Retransmit()
        self.epoch = 0
        self._pending: Dict[Link, Pending] = {}
        self._pending_bytes = 0  # the payload bytes of what is pending (each send's first timeout counts them)
        self._due: Optional[float] = None  # next_due's answer while nothing pending changed (None: recompute)
        self._seen: set = set()
        self._next: Dict[Tuple[int, int], int] = defaultdict(int)
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ epochs and numbering
    def set_epoch(self, epoch: int) -> None:
        """Enter ``epoch``: numbering, pending acknowledgements and duplicate detection start afresh."""
        with self._lock:
            self.epoch = int(epoch)
            self._pending.clear()
            self._pending_bytes, self._due = 0, None
            self._seen = {k for k in self._seen if k[0] >= self.epoch}  # the start of this epoch stays seen
            self._next.clear()
            self._log.clear()
            self._gone.clear()

    def next_seq(self, src: int, dst: int, count: int = 1) -> int:
        """The first of ``count`` sequence numbers on the link ``src -> dst`` in this epoch."""
        with self._lock:
            s = self._next[(src, dst)]
            self._next[(src, dst)] = s + count
            return s

    # ------------------------------------------------------------------ sending
    def sending(self, src: int, dst: int, kind: str, payload: bytes, seq: Optional[int], now: float) -> bool:
        """Before a put: keep the message until acknowledged if its kind is acknowledged (and it has its
        ``seq``); returns whether it is kept. Every numbered message to an agent is logged for :meth:`replay`."""
        if self.keep_log and dst >= 0 and kind not in messages.UNNUMBERED:
            with self._lock:
                self._log[dst].append(Resend(src, dst, -1 if seq is None else seq, kind, payload))
        if seq is None or kind not in protocol.ACKED or dst in self._gone:
            return False
        with self._lock:  # before the put: the ack may come back at once
            self._keep(Resend(src, dst, seq, kind, payload), now)
        return True

    def _keep(self, r: Resend, now: float) -> None:
        """Keep ``r`` until acknowledged, its first resend no sooner than the bytes ahead of it, itself
        included, take at :data:`FLOOR_BYTES_S` (caller holds the lock)."""
        ahead = self._pending_bytes + len(r.payload)
        self._drop((r.src, r.dst, r.seq))  # a replay keeps again what may still be pending
        self._pending[(r.src, r.dst, r.seq)] = Pending(now, 1, r.payload, r.kind, ahead / FLOOR_BYTES_S)
        self._pending_bytes += len(r.payload)
        self._due = None

    def _drop(self, link: Link) -> Optional[Pending]:
        """Stop waiting for the ack of ``link`` (caller holds the lock); returns what was pending."""
        entry = self._pending.pop(link, None)
        if entry is not None:
            self._pending_bytes -= len(entry.payload)
            self._due = None
        return entry

    def put_returned(self, src: int, dst: int, seq: int, now: float) -> None:
        """The put of a kept message returned: its ack timer starts now."""
        with self._lock:
            entry = self._pending.get((src, dst, seq))
            if entry is not None:
                entry.sent_at = now
                self._due = None

    def unacknowledged(self, src: Optional[int] = None) -> int:
        """Messages (of agent ``src``, or of every agent here) still waiting for their ack."""
        with self._lock:
            return sum(1 for k in self._pending if src is None or k[0] == src)

    def _timeout(self, dst: int, p: Pending) -> float:
        """How long a pending message waits for its ack: the adaptive timeout, at least its floor."""
        return max(self.retransmit.timeout(dst, p.tries), min(self.retransmit.max_s, p.floor_s))

    def next_due(self) -> Optional[float]:
        """When the earliest pending message is due again (None: nothing pending). Computed again only after
        something pending changed (the simulator asks every process after every message)."""
        with self._lock:
            if self._due is None and self._pending:
                self._due = min(p.sent_at + self._timeout(k[1], p) for k, p in self._pending.items())
            return self._due

    def due(self, now: float) -> List[Resend]:
        """The messages whose ack is overdue at ``now``, counted as resent (put them again, then call
        :meth:`put_returned`). A lost receiver is not this layer's business: the coordinator starts a new
        epoch, which drops what is pending."""
        out = []
        with self._lock:
            for (src, dst, seq), p in self._pending.items():
                if now - p.sent_at >= self._timeout(dst, p):
                    p.sent_at, p.tries = now, p.tries + 1
                    out.append(Resend(src, dst, seq, p.kind, p.payload))
                    self._due = None
        for _ in out:
            self.meter.resend()
        return out

    def forget(self, agents) -> None:
        """These agents finished and their process is gone: nothing sent to them waits for an ack any more (a
        takeover's replay may send them again what they already had). The log of what they were sent stays: a
        later takeover may run them again (:meth:`replay` then counts on their acks again)."""
        with self._lock:
            self._gone |= {int(a) for a in agents}
            for k in [k for k in self._pending if k[1] in self._gone]:
                self._drop(k)

    def replay(self, agents, now: float) -> List[Resend]:
        """Everything sent to these agents in this epoch, in the order it was sent, to put again: after a
        takeover their new host runs them from the start and needs every message they had received. The
        acknowledged ones are kept until acknowledged again (at once, when the new host has them)."""
        out = []
        with self._lock:
            self._gone -= {int(a) for a in agents}
            for a in sorted(int(x) for x in agents):
                for r in self._log.get(a, []):
                    if r.kind in protocol.ACKED and r.seq >= 0:  # a replay is put all at once: the same floor
                        self._keep(r, now)
                    out.append(r)
        return out

    # ------------------------------------------------------------------ receiving
    def receive(self, msg: dict, dst: int, now: float) -> Verdict:
        """Judge the decoded message ``msg`` for hosted agent ``dst`` (see the module's text)."""
        kind, src, seq = msg["kind"], msg["src"], msg["seq"]
        with self._lock:
            epoch = self.epoch
        if msg["epoch"] < epoch:
            self.meter.reject("message of an earlier epoch")
            return Verdict(False)
        if msg["epoch"] > epoch and kind != "start":
            self.meter.reject("message of a later epoch")
            return Verdict(False)
        if kind == "ack":
            if msg["dst"] != dst:
                self.meter.reject("ack for another agent")
                return Verdict(False)
            with self._lock:
                entry = self._drop((dst, src, seq))
                if entry is not None:  # the link's round trip changes every pending timeout to src
                    self.retransmit.acknowledged(src, now - entry.sent_at, entry.tries)
            return Verdict(False)
        if kind in messages.UNNUMBERED:
            return Verdict(True)
        # acknowledge every copy (the first ack may have been lost), hand over once
        ack = protocol.ack(self.job, dst, src, seq, epoch=msg["epoch"]) if kind in protocol.ACKED else None
        key = (msg["epoch"], dst, src, seq)
        with self._lock:
            dup = key in self._seen
            self._seen.add(key)
        if dup:
            self.meter.duplicate()
        return Verdict(not dup, ack)
