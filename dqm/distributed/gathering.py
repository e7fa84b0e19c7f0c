"""Gather, sans I/O: every source's features go to one host, which runs centralized QuickMatch.

* :func:`gather_payload`: one source's ``gather`` payload (sent in parts of at most 1 MiB by
  :func:`dqm.distributed.protocol.data_messages`, merged by :func:`dqm.distributed.protocol.merge_parts`);
* :class:`GatheredParts`: the parts received per source, their completeness, the features by id;
* :func:`match_gathered`: :func:`dqm.quickmatch` on the gathered features in feature-id order, labels
  numbered canonically (as :func:`dqm.distributed.sources.assemble_labels` numbers a distributed job's):
  with the quadratic kernel the balanced mode's labels exactly;
* :class:`GatherDriver`: one agent of a ``gather`` job, the same calls as
  :class:`~dqm.distributed.driver.AgentDriver`: it sends its features (and its catalog) to the
  coordinator, then its statistics.

The coordinator of a ``dqm run`` job in ``--mode gather`` (:mod:`dqm.distributed.coordination`) and the
stand-alone gathering of :mod:`dqm.runtime.gather` use them.
"""
from __future__ import annotations

import time
from typing import Dict, Iterable, Optional, Tuple

import numpy as np

from ..core.params import FINITE_KERNEL, QuickMatchParams
from . import messages, protocol
from .config import DQMConfig
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
                   params: Optional[QuickMatchParams] = None, approximate: bool = False
                   ) -> Tuple[np.ndarray, np.ndarray]:
    """:func:`dqm.quickmatch` of the gathered features (in feature-id order, as :meth:`GatheredParts.features`
    gives them) with ``params`` (default: the quadratic kernel, the rest QuickMatch's defaults; a distributed
    job's :attr:`~dqm.distributed.config.DQMConfig.params`): ``(ids, labels)``, labels numbered canonically.
    Feature ids must be unique."""
    import dqm

    if len(np.unique(ids)) != len(ids):
        raise ValueError("two sources sent the same feature id (feature ids must be unique across the job: give "
                         "each FEATURES file its own feature_ids, or none)")
    r = dqm.quickmatch(descriptors, image_ids, params=params or QuickMatchParams(kernel=FINITE_KERNEL),
                       approximate=approximate)
    return assemble_labels([(ids, r.labels)])


class GatherDriver:
    """One hosted agent of a ``gather`` job (``--mode gather``, or ``auto`` when the coordinator picked it):
    on ``go`` it sends its features to the coordinator as ``gather`` messages (:func:`gather_payload` in
    parts, numbered on its link and acknowledged) and its catalog when the job asked for it, then its
    statistics once every part is acknowledged, and waits for ``finish``. The same calls as
    :class:`~dqm.distributed.driver.AgentDriver` (``begin``, ``handle``, ``settle``, ``check_timeout``)."""

    def __init__(self, me: int, cfg: DQMConfig, transport, features: AgentFeatures, epoch: int,
                 home: int, catalog: bool, phase_timeout_s: float = 120.0):
        self.me, self.cfg, self.bus, self.features = me, cfg, transport, features
        self.epoch, self.home, self.catalog = epoch, home, catalog
        self.phase_timeout_s = phase_timeout_s
        self.states = ("wait_start", "gather", "wait_acks", "wait_finish")
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

    def _send_parts(self, kind: str, payload: Dict[str, np.ndarray]) -> None:
        n = protocol.part_count(kind, payload)
        seq0 = self.bus.next_seq(self.me, COORDINATOR, n)
        for j, msg in enumerate(protocol.data_messages(kind, self.cfg.job, self.me, payload, seq0=seq0,
                                                       epoch=self.epoch)):
            self.bus.send(self.me, COORDINATOR, kind, msg, seq=seq0 + j)

    def begin(self, seed: int) -> None:
        """``go``: send the features (and the catalog) to the coordinator."""
        self._enter("gather")
        f = self.features
        self._send_parts("gather", gather_payload(f.ids, f.image_ids, f.descriptors))
        if self.catalog:
            self._send_parts("catalog", self.features.catalog)
        self._enter("wait_acks")

    def handle(self, msg: dict) -> None:
        """Nothing comes to a gathering source from other agents."""

    def settle(self) -> None:
        """Once every part is acknowledged: the statistics, then wait for ``finish``."""
        if self.state == "wait_acks" and self.bus.unacknowledged(self.me) == 0:
            self._enter("wait_finish")
            stats = dict(self.times)
            stats["cpu_s"] = time.process_time() - self.cpu0
            stats["host"] = float(self.home)
            stats["features"] = float(len(self.features))
            if self.me == self.home:  # the process's counters, reported once
                stats.update(self.bus.meter.counter_stats())
            stats.update(self.bus.meter.as_stats(src=self.me))
            self.bus.send_single(self.me, COORDINATOR, "stats", values=stats)

    def check_timeout(self) -> None:
        """Parts unacknowledged for longer than the phase timeout end the process (TimeoutError)."""
        if self.state == "wait_acks" and time.monotonic() - self.phase_started > self.phase_timeout_s:
            raise TimeoutError(f"agent {self.me} waited more than {self.phase_timeout_s:.0f} s for the coordinator "
                               "to acknowledge its features")
