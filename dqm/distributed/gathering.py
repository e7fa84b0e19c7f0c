"""Gather, sans I/O: every source's features go to one host, which runs centralized QuickMatch.

* :func:`gather_payload`: one source's ``gather`` payload (sent in parts of at most 1 MiB by
  :func:`dqm.distributed.protocol.data_messages`, merged by :func:`dqm.distributed.protocol.merge_parts`);
* :class:`GatheredParts`: the parts received per source, their completeness, the features by id;
* :func:`match_gathered`: :func:`dqm.quickmatch` on the gathered features in feature-id order, labels
  numbered canonically (as :func:`dqm.distributed.sources.assemble_labels` numbers a distributed job's):
  with the quadratic kernel the balanced mode's labels exactly;
* :class:`GatherDriver`: one agent of a ``gather`` job, the same calls as
  :class:`~dqm.distributed.driver.AgentDriver`: agent 0 gathers every other agent's features, keeps its
  own and sends the coordinator the labels; the others send it their features.

The agents of a ``dqm run`` job in ``--mode gather`` (:mod:`dqm.distributed.hosting`) and the stand-alone
gathering of :mod:`dqm.runtime.gather` use them.
"""
from __future__ import annotations

import time
from typing import Callable, Dict, Iterable, Optional, Tuple

import numpy as np

from ..core.params import FINITE_KERNEL, QuickMatchParams
from ..validation import has_repeats
from . import messages, protocol
from .config import DQMConfig
from .driver import JobAborted
from .ledger import COORDINATOR
from .sources import AgentFeatures, assemble_labels


def gather_payload(ids, image_ids, descriptors) -> Dict[str, np.ndarray]:
    """One source's features as the payload of its ``gather`` message (descriptors as they travel: uint8,
    or float32), split into parts by :func:`dqm.distributed.protocol.data_messages` like every round
    message (:func:`dqm.distributed.protocol.part_count` parts)."""
    return {"ids": np.asarray(ids, np.int64), "image_ids": np.asarray(image_ids, np.int64),
            "descriptors": protocol.wire_descriptors(descriptors)}


class GatheredParts:
    """The ``gather`` parts received, per source: complete when every expected source's parts are in."""

    def __init__(self, sources: Iterable[int]):
        self.sources = sorted(set(int(s) for s in sources))
        self.parts: Dict[int, Dict[int, dict]] = {}
        self.expected: Dict[int, int] = {}

    def take(self, msg: dict) -> None:
        """Keep one decoded ``gather`` message of an expected source (a repeated part replaces itself)."""
        src = int(msg["src"])
        if src not in self.sources:
            raise ValueError(f"a gather message of source {src}, which is not among {self.sources}")
        self.expected[src] = msg["parts"]
        self.parts.setdefault(src, {})[msg["part"]] = msg

    def done(self, src: int) -> bool:
        """Whether every part of source ``src`` is in."""
        return src in self.expected and len(self.parts[src]) == self.expected[src]

    def complete(self) -> bool:
        return all(self.done(s) for s in self.sources)

    def progress(self) -> Dict[int, str]:
        """Parts in per source, ``got/expected`` (``?``: none yet), for a message."""
        return {s: f"{len(self.parts.get(s, {}))}/{self.expected.get(s, '?')}" for s in self.sources}

    def features(self, own=None) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids, image_ids, descriptors) of every source (and ``own``: an object with ``ids``, ``image_ids``
        and ``descriptors``, the gathering host's own features), ordered by feature id."""
        blocks = [] if own is None else [(own.ids, own.image_ids, protocol.wire_descriptors(own.descriptors))]
        for s in sorted(self.parts):
            m = protocol.merge_parts("gather", list(self.parts[s].values()))
            blocks.append((m["ids"], m["image_ids"], m["descriptors"]))
        if not blocks:
            raise ValueError("nothing was gathered")
        dtypes = {b[2].dtype for b in blocks if len(b[2])}
        if len(dtypes) > 1:
            raise ValueError(f"the sources sent descriptors of different types {sorted(map(str, dtypes))}")
        ids, image_ids, X = (np.concatenate([b[i] for b in blocks]) for i in range(3))
        order = np.argsort(ids, kind="stable")
        return ids[order], image_ids[order], X[order]


def match_gathered(ids: np.ndarray, image_ids: np.ndarray, descriptors: np.ndarray,
                   params: Optional[QuickMatchParams] = None, approximate: bool = False,
                   n_threads: Optional[int] = None, engine: str = "exact") -> Tuple[np.ndarray, np.ndarray]:
    """:func:`dqm.quickmatch` of the gathered features (in feature-id order, as :meth:`GatheredParts.features`
    gives them) with ``params`` (default: the quadratic kernel, the rest QuickMatch's defaults; a distributed
    job's :attr:`~dqm.distributed.config.DQMConfig.params`) with ``engine`` (a job's ``--engine``) on ``n_threads``
    threads (None: the default): ``(ids, labels)``, labels numbered canonically. Feature ids must be unique."""
    import dqm

    if has_repeats(ids):
        raise ValueError("two sources sent the same feature id (feature ids must be unique across the job: give "
                         "each FEATURES file its own feature_ids, or none)")
    r = dqm.quickmatch(descriptors, image_ids, params=params or QuickMatchParams(kernel=FINITE_KERNEL),
                       approximate=approximate, n_threads=n_threads, engine=engine)
    return assemble_labels([(ids, r.labels)])


#: the agent that gathers in a ``gather`` job of the runtime: it keeps its own features (they do not cross a link)
GATHERER = 0


class GatherDriver:
    """One hosted agent of a ``gather`` job (``--mode gather``, or ``auto`` when the coordinator picked it),
    the same calls as :class:`~dqm.distributed.driver.AgentDriver` (``begin``, ``handle``, ``settle``,
    ``check_timeout``).

    Agent :data:`GATHERER` (0) gathers, as the stand-alone baseline's source 0 does: on ``go`` every other
    agent sends it its features as ``gather`` messages (:func:`gather_payload` in parts, numbered on the
    link and acknowledged), and it keeps its own; once every part is in it runs :func:`match_gathered` on
    all of them and sends the coordinator the ``result`` (every feature's id and label). Every agent sends
    its catalog to the coordinator when the job asked for it, then its statistics once everything it sent
    is acknowledged, and waits for ``finish``. A takeover needs nothing more: the process that takes over
    agent 0 gets every part again from the senders' logs, one that takes over a sender runs it from its
    start (its repeated parts are dropped as duplicates)."""

    def __init__(self, me: int, cfg: DQMConfig, transport, features: AgentFeatures, epoch: int,
                 home: int, catalog: bool, phase_timeout_s: float = 120.0, match_threads: Optional[int] = None,
                 on_state: Optional[Callable[[int, str], None]] = None):
        self.me, self.cfg, self.bus, self.features = me, cfg, transport, features
        self.match_threads = match_threads
        self.on_state = on_state  # called on entering every state (a test's fault injection)
        self.epoch, self.home, self.catalog = epoch, home, catalog
        self.phase_timeout_s = phase_timeout_s
        self.gathers = me == GATHERER
        self.gathered = GatheredParts(a for a in range(cfg.agents) if a != me) if self.gathers else None
        self.states = ("wait_start", "gather", "match", "wait_acks", "wait_finish") if self.gathers else \
            ("wait_start", "gather", "wait_acks", "wait_finish")
        self.state = "wait_start"
        self.phase_started = time.monotonic()
        self.cpu0 = time.process_time()
        self.times: Dict[str, float] = {}
        self.core_stats: Dict[str, float] = {}

    @property
    def step_index(self) -> int:
        return self.states.index(self.state)

    def _enter(self, state: str) -> None:
        now = time.monotonic()
        self.times[f"time_{self.state}"] = self.times.get(f"time_{self.state}", 0.0) + now - self.phase_started
        self.state, self.phase_started = state, now
        self.bus.send(self.me, COORDINATOR, "progress", messages.encode(
            "progress", self.cfg.job, self.me, epoch=self.epoch, state=state, features=len(self.features),
            bytes=int(self.bus.meter.sent_by(self.me))))
        if self.on_state is not None:
            self.on_state(self.me, state)

    def _send_parts(self, kind: str, dst: int, payload: Dict[str, np.ndarray]) -> None:
        n = protocol.part_count(kind, payload)
        seq0 = self.bus.next_seq(self.me, dst, n)
        for j, msg in enumerate(protocol.data_messages(kind, self.cfg.job, self.me, payload, seq0=seq0,
                                                       epoch=self.epoch)):
            self.bus.send(self.me, dst, kind, msg, seq=seq0 + j)

    def begin(self, seed: int) -> None:
        """``go``: the catalog (when asked) to the coordinator; a sender's features to the gathering agent."""
        self._enter("gather")
        if self.catalog:
            self._send_parts("catalog", COORDINATOR, self.features.catalog)
        if not self.gathers:
            f = self.features
            self._send_parts("gather", GATHERER, gather_payload(f.ids, f.image_ids, f.descriptors))
            self._enter("wait_acks")
        else:
            self._match_when_complete()

    def handle(self, msg: dict) -> None:
        """The gathering agent keeps each ``gather`` part of another agent (a repeated part replaces itself), also
        before its own ``go``; once it has matched, parts sent again (a sender run again after a takeover) are
        dropped."""
        if msg["kind"] != "gather" or self.gathered is None:
            return
        self.gathered.take(msg)  # ValueError for a source that is not one of the others
        if self.state == "gather":
            self._match_when_complete()

    def _match_when_complete(self) -> None:
        if not self.gathered.complete():
            return
        self._enter("match")
        t = time.monotonic()
        try:
            ids, labels = match_gathered(*self.gathered.features(own=self.features), self.cfg.params,
                                         n_threads=self.match_threads, engine=self.cfg.engine)
        except ValueError as exc:  # InputError included: duplicate ids, mixed types, over the memory budget
            reason = f"the gathered features cannot be matched: {exc}"
            self.bus.send_single(self.me, COORDINATOR, "refuse", reason=reason[:1000], param="")
            raise JobAborted(reason) from None
        self.core_stats = {"match_s": time.monotonic() - t, "gathered": float(len(ids)),
                           "fast_engine": float(self.cfg.fast)}  # which engine matched, for the report
        self.gathered = None  # the parts are no longer needed
        self.bus.send_single(self.me, COORDINATOR, "result", ids=ids, labels=labels)
        self._enter("wait_acks")

    def settle(self) -> None:
        """Once every part is acknowledged: the statistics, then wait for ``finish``."""
        if self.state == "wait_acks" and self.bus.unacknowledged(self.me) == 0:
            self._enter("wait_finish")
            stats = dict(self.times)
            stats.update(self.core_stats)
            stats["cpu_s"] = time.process_time() - self.cpu0
            stats["host"] = float(self.home)
            stats["features"] = float(len(self.features))
            if self.me == self.home:  # the process's counters, reported once
                stats.update(self.bus.meter.counter_stats())
            stats.update(self.bus.meter.as_stats(src=self.me))
            self.bus.send_single(self.me, COORDINATOR, "stats", values=stats)

    def check_timeout(self) -> None:
        """Waiting longer than the phase timeout for acknowledgements (a sender) or for the other agents'
        features (the gathering agent) ends the process (TimeoutError)."""
        if self.state not in ("gather", "wait_acks") or time.monotonic() - self.phase_started <= self.phase_timeout_s:
            return
        if self.state == "gather":
            waiting = [s for s in self.gathered.sources if not self.gathered.done(s)]
            raise TimeoutError(f"agent {self.me} waited more than {self.phase_timeout_s:.0f} s for the features of "
                               f"agents {waiting} (parts in: {self.gathered.progress()})")
        raise TimeoutError(f"agent {self.me} waited more than {self.phase_timeout_s:.0f} s for its messages to "
                           "be acknowledged")
