"""The simulator's network: one endpoint per process, a virtual clock and a fault plan.

Every process of a simulated job (each agent process, and the coordinator as process -1) has a
:class:`MemoryBus`: the same calls as the zenoh bus (:class:`dqm.runtime.bus.Bus`) and the same
delivery layer (:class:`dqm.distributed.delivery.Delivery`: sequence numbers, acks, resends with
the adaptive timeout, duplicates, epochs). A message is encoded by its sender, metered as the
runtime meters it (payload plus key; each ack when it is sent), decoded again (so the codec is on
the path) and queued for the receiving process in :class:`MemoryNetwork`, which delivers in order of
arrival time, then of sending. Time is virtual: it moves only when nothing can arrive now, to the
next delayed message or the next resend that falls due, so a lost ack costs no wall time and
every run is deterministic.

A :class:`FaultPlan` changes what the network does with chosen messages: :class:`Drop` (the
message, or an ``ack``, never arrives: its sender resends it), :class:`Duplicate` (it arrives
twice: the receiver acknowledges both and uses one), :class:`Delay` (it arrives ``seconds``
later, after what was sent after it; past the resend timeout a resent copy arrives first), and
:class:`LoseProcess` (the process dies when its own agent enters a state; what it had sent is still
delivered, what is sent to it is lost, and the coordinator is told that its token vanished).
Only acknowledged kinds (:data:`dqm.distributed.protocol.ACKED`) and acks may be dropped or
delayed: the others rely on the transport's order and reliability, as zenoh's are.
"""
from __future__ import annotations

import heapq
from collections import defaultdict
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from ..validation import InputError
from . import keys, messages, protocol
from .delivery import Delivery
from .ledger import COORDINATOR, Meter

#: the kind of the notice the coordinator gets when a process's liveliness token vanishes (not a message)
LOST = "lost"


@dataclass(frozen=True)
class _Match:
    """The ``nth`` message (1-based, first sends and resends counted alike) of ``kind`` from agent ``src``
    to agent ``dst`` (None: any; -1: the coordinator)."""

    kind: str
    src: Optional[int] = None
    dst: Optional[int] = None
    nth: int = 1

    def matches(self, kind: str, src: int, dst: int) -> bool:
        return kind == self.kind and self.src in (None, src) and self.dst in (None, dst)


@dataclass(frozen=True)
class Drop(_Match):
    """The matching message never arrives."""


@dataclass(frozen=True)
class Duplicate(_Match):
    """The matching message arrives twice."""


@dataclass(frozen=True)
class Delay(_Match):
    """The matching message arrives ``seconds`` (virtual) later."""

    seconds: float = 5.0


@dataclass(frozen=True)
class LoseProcess:
    """Agent process ``process`` dies when its own agent enters ``state`` in epoch ``epoch``."""

    process: int
    state: str
    epoch: int = 0


Fault = Union[Drop, Duplicate, Delay, LoseProcess]


class FaultPlan:
    """The faults of one simulated run (see the module's text); each message fault applies once."""

    def __init__(self, faults: Sequence[Fault] = ()):
        self.faults = list(faults)
        for f in self.faults:
            if isinstance(f, (Drop, Delay)) and f.kind not in protocol.ACKED + ("ack",):
                raise InputError(f"a {type(f).__name__.lower()} of a {f.kind!r} message: only acknowledged kinds "
                                 f"({', '.join(protocol.ACKED)}) and acks are resent, so only they may be dropped or "
                                 "delayed")
            if isinstance(f, _Match) and f.nth < 1:
                raise InputError(f"nth must be at least 1, got {f.nth}")
        self._seen: Dict[int, int] = defaultdict(int)
        #: what happened, for a test to check that each fault struck: (fault, kind, src, dst)
        self.struck: List[Tuple[Fault, str, int, int]] = []

    def losses(self) -> Dict[int, LoseProcess]:
        """Process -> when it is lost."""
        return {f.process: f for f in self.faults if isinstance(f, LoseProcess)}

    def arrivals(self, kind: str, src: int, dst: int) -> List[float]:
        """The delays after which copies of this message arrive ([] dropped, [0] as usual)."""
        out = [0.0]
        for i, f in enumerate(self.faults):
            if not isinstance(f, _Match) or not f.matches(kind, src, dst):
                continue
            self._seen[i] += 1
            if self._seen[i] != f.nth:
                continue
            self.struck.append((f, kind, src, dst))
            if isinstance(f, Drop):
                return []
            if isinstance(f, Duplicate):
                out = out + [out[-1]]
            elif isinstance(f, Delay):
                out = [t + f.seconds for t in out]
        return out


class MemoryNetwork:
    """The processes' endpoints, the queue of messages in flight, the virtual clock and the one meter.
    ``unmetered`` kinds (the agents' progress reports and final statistics, which are not the
    algorithm's traffic) travel but are not counted."""

    def __init__(self, job: str, m: int, dim: int, plan: Optional[FaultPlan] = None,
                 unmetered: Sequence[str] = ("progress", "stats")):
        self.job = job
        self.m = m
        self.dim = dim
        self.plan = plan or FaultPlan()
        self.unmetered = tuple(unmetered)
        self.meter = Meter()
        self.clock = 0.0
        self._heap: List[tuple] = []
        self._order = 0
        self.endpoints: Dict[int, "MemoryBus"] = {}
        self.dead: set = set()
        #: features carried per phase (``route``, ``handdown``), first sends only
        self.features_moved: Dict[str, int] = defaultdict(int)

    def endpoint(self, home: int) -> "MemoryBus":
        """Process ``home``'s bus (-1: the coordinator's), made on first use."""
        if home not in self.endpoints:
            self.endpoints[home] = MemoryBus(self, home)
        return self.endpoints[home]

    def lose(self, process: int) -> None:
        """Process ``process`` dies: nothing more reaches it, it sends and resends nothing more, and the
        coordinator hears that its liveliness token vanished (a ``lost`` notice, after what the process had
        sent, as the runtime's coordinator waits for a refusal sent just before an exit)."""
        self.dead.add(process)
        self.endpoints.pop(process, None)
        heapq.heappush(self._heap, (self.clock, self._order, COORDINATOR, COORDINATOR,
                                    {"kind": LOST, "src": process}))
        self._order += 1

    def put(self, to_process: int, dst: int, msg: dict) -> None:
        """Queue a decoded message for agent ``dst`` at ``to_process``, as the fault plan has it."""
        for delay in self.plan.arrivals(msg["kind"], msg["src"], dst):
            heapq.heappush(self._heap, (self.clock + delay, self._order, to_process, dst, msg))
            self._order += 1

    def peek_now(self, clock: float) -> bool:
        """Whether a message arrives at virtual time ``clock`` (no clock move needed)."""
        return bool(self._heap) and self._heap[0][0] <= clock

    def _next_resend(self) -> Optional[float]:
        due = [t for e in self.endpoints.values() for t in [e.delivery.next_due()] if t is not None]
        return min(due) if due else None

    def next(self) -> Optional[Tuple[int, int, dict]]:
        """The next message to deliver as ``(process, agent, message)``, advancing the virtual clock (and
        resending what falls due) when nothing arrives now; None when nothing is in flight or pending."""
        while True:
            arrive = self._heap[0][0] if self._heap else None
            resend = self._next_resend()
            if arrive is not None and (resend is None or arrive <= resend):
                t, _, to_process, dst, msg = heapq.heappop(self._heap)
                self.clock = max(self.clock, t)
                if to_process in self.dead:
                    continue
                return to_process, dst, dict(msg)
            if resend is None:
                return None
            self.clock = max(self.clock, resend)
            for e in list(self.endpoints.values()):
                e.resend_due()


class MemoryBus:
    """One process's endpoint on a :class:`MemoryNetwork` (``home``: its index, -1 the coordinator): the
    transport of its drivers, with the delivery layer of the zenoh bus."""

    def __init__(self, net: MemoryNetwork, home: int):
        self.net = net
        self.job = net.job
        self.home = home
        self.dim: Optional[int] = net.dim
        self.delivery = Delivery(net.job, net.meter)
        self.owners = np.arange(net.m, dtype=np.int64)
        self.hosted = frozenset([home]) if home >= 0 else frozenset()
        self._keys: Dict[Tuple[int, int], str] = {}  # (process, agent) -> message key

    @property
    def meter(self) -> Meter:
        return self.net.meter

    @property
    def epoch(self) -> int:
        return self.delivery.epoch

    # ------------------------------------------------------------------ the job's epochs and hosts
    def set_epoch(self, epoch: int) -> None:
        self.delivery.set_epoch(epoch)

    def set_owners(self, owners) -> None:
        self.owners = np.asarray(owners, dtype=np.int64).copy()
        self._keys.clear()

    def host(self, agents) -> None:
        self.hosted = frozenset(int(a) for a in agents) | ({self.home} if self.home >= 0 else set())

    def _process(self, agent: int) -> int:
        return COORDINATOR if agent < 0 else int(self.owners[agent])

    # ------------------------------------------------------------------ sending
    def next_seq(self, src: int, dst: int, count: int = 1) -> int:
        return self.delivery.next_seq(src, dst, count)

    def _put(self, src: int, dst: int, kind: str, payload: bytes) -> dict:
        process = self._process(dst)
        key = self._keys.get((process, dst))
        if key is None:
            key = self._keys[(process, dst)] = keys.message_key(self.job, self.home, process, dst)
        if kind not in self.net.unmetered:
            self.meter.add(src, dst, kind, len(payload) + len(key))
        msg = messages.decode(payload, job=self.job, agents=self.net.m, dim=self.dim, sender=src)
        msg["_bytes"] = len(payload)
        msg["_key"] = key
        self.net.put(process, dst, msg)
        return msg

    def send(self, src: int, dst: int, kind: str, payload: bytes, seq: Optional[int] = None) -> None:
        """Send from hosted agent ``src`` to agent ``dst`` (-1: the coordinator); acknowledged kinds are kept
        until acknowledged and resent when due (virtual time)."""
        kept = self.delivery.sending(src, dst, kind, payload, seq, self.net.clock)
        msg = self._put(src, dst, kind, payload)
        if kept:
            self.delivery.put_returned(src, dst, seq, self.net.clock)
        if kind == "features":
            self.net.features_moved[msg["phase"]] += len(msg["ids"])

    def send_single(self, src: int, dst: int, kind: str, **fields) -> None:
        seq = 0 if kind in messages.UNNUMBERED else self.next_seq(src, dst)
        self.send(src, dst, kind, messages.encode(kind, self.job, src, seq=seq, epoch=self.delivery.epoch, **fields))

    def unacknowledged(self, src: Optional[int] = None) -> int:
        return self.delivery.unacknowledged(src)

    def resend_due(self) -> None:
        for r in self.delivery.due(self.net.clock):
            self._put(r.src, r.dst, r.kind, r.payload)
            self.delivery.put_returned(r.src, r.dst, r.seq, self.net.clock)

    def forget(self, agents) -> None:
        """Stop waiting for the acks of these finished agents (:meth:`Delivery.forget`)."""
        self.delivery.forget(agents)

    def replay(self, agents) -> None:
        """Send these agents again everything this process sent them in this epoch (:meth:`Delivery.replay`)."""
        for r in self.delivery.replay(agents, self.net.clock):
            self._put(r.src, r.dst, r.kind, r.payload)

    # ------------------------------------------------------------------ receiving
    def accept(self, dst: int, msg: dict) -> bool:
        """Judge an arriving message for agent ``dst`` here (the delivery layer; its ack goes back at once):
        whether to hand it over."""
        if self.home >= 0 and dst not in self.hosted:
            self.meter.reject("message for an agent this process does not host")
            return False
        verdict = self.delivery.receive(msg, dst, self.net.clock)
        if verdict.ack is not None:
            self._put(dst, msg["src"], "ack", verdict.ack)
        return verdict.deliver
