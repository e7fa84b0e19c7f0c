"""The Distributed QuickMatch wire protocol: which messages carry what, built once.

Both the in-process simulator (to meter) and the runtime agents (to send) build
their messages with these functions, so the bytes the simulator counts are the
bytes the runtime sends.

Set-up (every mode; ``src -> dst``):

=============  ===========================  ==========================================
phase          message kind                 content
=============  ===========================  ==========================================
start          coordinator -> every agent   ``start``: the partition seed integer
sample         agent a -> agent 0           ``sample``: a deterministic descriptor sample
                                            (may be empty) and the count of own
                                            features alone in their image
seeds          agent 0 -> every agent       ``seeds``: seeds (empty when they follow
                                            from the integer), power weights, int8
                                            sketch basis, ``final``, ``fill``
fill           (only if ``fill``)           ``sigmas`` to agent 0; ``fill`` (the median)
balance        (until ``final``)            ``counts`` to agent 0; ``weights`` back
route          agent a -> agent b           ``features`` chunks (seq 0..k-1), then
                                            ``phase_end`` with k (also when k = 0)
=============  ===========================  ==========================================

Lean / paper (cascade): ``minima`` all-to-all, then ``features`` hand-downs with
``phase_end`` (and the (cell, target) moves) from agent m-1 down to 0.

Balanced: the rounds of dqm.distributed.balanced.ROUNDS, one message kind each
(``bounds``, ``sketch``, ``request``, ``sketch_rest``, ``offer``, ``sums``, ``density``,
``proposal``, ``notify``, ``fragments``, ``assign``, ``component``), but the copies: a
receiver pulls the copies offered to it by windows, ``grant`` (offset, count) answered by one
``ghost`` message of those copies (flow control: it holds its own features and at most two
windows). Each is a payload of arrays split into
parts of at most :data:`PART_BYTES` (every part carries ``seq``, ``part`` and
``parts``; the receiver has a sender's round when it holds all parts).

Every agent then sends ``result`` (ids, labels) and ``stats`` to the coordinator.
Every ``features`` chunk and every data part (:data:`ACKED`) is acknowledged
(``ack``) and resent until it is. Every message but ``ack`` and ``progress`` is
numbered on its link (``seq``), so a receiver processes each number once.

Start and restart (the coordinator's side, docs/runtime.md): ``start`` (epoch,
seed, owners, parameters) to every live agent process, ``ready`` (or ``refuse``)
back, then ``go``; a lost process makes the coordinator give its agents to a
survivor and start again at the next epoch.
"""
from __future__ import annotations

from typing import Dict, List, Optional, Sequence

import numpy as np

from . import messages

#: feature rows per features message (keeps messages well under the size limit)
CHUNK_ROWS = 4096
#: largest row payload of one part of a round message
PART_BYTES = 1 << 20


def chunk_count(n_rows: int) -> int:
    """Number of ``features`` chunks for ``n_rows`` features."""
    return (int(n_rows) + CHUNK_ROWS - 1) // CHUNK_ROWS


def wire_descriptors(descriptors: np.ndarray) -> np.ndarray:
    """Descriptors as they travel: uint8 stays uint8, anything else becomes float32."""
    d = np.asarray(descriptors)
    return d if d.dtype == np.uint8 else np.ascontiguousarray(d, dtype=np.float32)


def feature_messages(job: str, src: int, phase: str, ids, image_ids, descriptors, sigma, unit=None,
                     seq0: int = 0, epoch: int = 0) -> List[bytes]:
    """The ``features`` chunks of one (src, dst, phase), numbered ``seq0, seq0 + 1, ...``.

    Sequence numbers are per directed link and never reused within a job, so
    an ack names one chunk and a duplicate is recognised. ``unit`` (the lean
    hand-down's units) is left out (an empty array) when None, as in routing.
    """
    n = len(ids)
    desc = wire_descriptors(descriptors)
    out = []
    for k, s in enumerate(range(0, n, CHUNK_ROWS)):
        sl = slice(s, s + CHUNK_ROWS)
        out.append(messages.encode(
            "features", job, src, phase=phase, seq=seq0 + k, epoch=epoch, ids=np.asarray(ids[sl], np.int64),
            image_ids=np.asarray(image_ids[sl], np.int64), descriptors=np.ascontiguousarray(desc[sl]),
            sigma=np.asarray(sigma[sl], np.float64),
            unit=np.zeros(0, np.int64) if unit is None else np.asarray(unit[sl], np.int64)))
    return out


def phase_end(job: str, src: int, dst: int, phase: str, n_messages: int, n_features: int,
              moved: np.ndarray | None = None, seq: int = 0, epoch: int = 0) -> bytes:
    mv = np.zeros(0, np.int64) if moved is None else np.asarray(moved, np.int64).reshape(-1)
    return messages.encode("phase_end", job, src, seq=seq, epoch=epoch, phase=phase, dst=dst, messages=int(n_messages),
                           features=int(n_features), moved=mv)


def moved_pairs(cells: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Unique (cell, target) pairs of handed-down features, flattened row-major (2 x K)."""
    if len(cells) == 0:
        return np.zeros(0, np.int64)
    return np.unique(np.stack([np.asarray(cells, np.int64), np.asarray(targets, np.int64)]), axis=1).reshape(-1)


def unpack_moved(flat: np.ndarray) -> np.ndarray:
    """Inverse of :func:`moved_pairs`: (2, K) array of cells and targets."""
    flat = np.asarray(flat, np.int64)
    if len(flat) % 2:
        raise messages.MessageError("moved pairs must have an even length")
    return flat.reshape(2, -1)


#: kinds that are acknowledged by the receiver and resent until they are (bulk payloads)
ACKED = ("features", "sigmas", "bounds", "sketch", "request", "sketch_rest", "offer", "grant", "ghost", "sums",
         "density", "proposal", "notify", "fragments", "assign", "component", "catalog", "gather")


def ack(job: str, src: int, dst: int, seq: int, epoch: int = 0) -> bytes:
    return messages.encode("ack", job, src, seq=int(seq), epoch=epoch, dst=int(dst))


class Retransmit:
    """When an unacknowledged message is due again: an adaptive timeout with exponential backoff.

    The timeout of a link starts at ``base_s`` and follows its measured acknowledgement
    round trips (``factor`` times their smoothed mean, as TCP does, first tries only: a resent
    message's ack cannot be matched to one send), never below ``base_s``; every resend of the
    same message doubles it, up to ``max_s``. On a saturated thin link a message's ack can take
    seconds behind megabytes queued before it: a fixed 2-s timeout then resent every part again
    and again, which filled the link further (lean moved 3.9x the raw bytes at 10 Mbit/s instead
    of 2.2x). A lost receiver is not the retransmitter's business: the coordinator notices it.
    """

    def __init__(self, base_s: float = 2.0, max_s: float = 60.0, factor: float = 3.0):
        self.base_s = float(base_s)
        self.max_s = float(max_s)
        self.factor = float(factor)
        self.srtt: Dict[int, float] = {}

    def timeout(self, peer: int, tries: int) -> float:
        """Seconds to wait for the ack of a message to ``peer`` sent ``tries`` times so far."""
        base = max(self.base_s, self.factor * self.srtt.get(peer, 0.0))
        return min(self.max_s, base * 2.0 ** max(0, tries - 1))

    def acknowledged(self, peer: int, rtt_s: float, tries: int) -> None:
        """An ack from ``peer`` came ``rtt_s`` after the message's last send."""
        if tries != 1 or not rtt_s >= 0:
            return
        old = self.srtt.get(peer)
        self.srtt[peer] = rtt_s if old is None else 0.875 * old + 0.125 * rtt_s


def part_count(kind: str, payload: Dict[str, np.ndarray]) -> int:
    """Number of parts the payload of a round message is split into (at least 1)."""
    rows = messages.row_fields(kind, payload)
    if not rows:
        return 1
    n = len(payload[rows[0]])
    row_bytes = sum(np.asarray(payload[f]).itemsize * int(np.prod(np.shape(payload[f])[1:])) for f in rows)
    per = max(1, PART_BYTES // max(1, row_bytes))
    return max(1, (n + per - 1) // per)


def data_messages(kind: str, job: str, src: int, payload: Dict[str, np.ndarray], seq0: int = 0,
                  epoch: int = 0) -> List[bytes]:
    """The parts of one round message from ``src``, numbered ``seq0, seq0 + 1, ...``.

    Row fields (one row per feature) are split across the parts; other fields
    (a sketch's scales, say) are repeated in every part.
    """
    rows = messages.row_fields(kind, payload)
    k = part_count(kind, payload)
    n = len(payload[rows[0]]) if rows else 0
    per = (n + k - 1) // k if n else 0
    out = []
    for p in range(k):
        fields = {}
        for f, v in payload.items():
            if f in rows:
                v = np.ascontiguousarray(np.asarray(v)[p * per:(p + 1) * per])
            fields[f] = v
        out.append(messages.encode(kind, job, src, seq=seq0 + p, epoch=epoch, part=p, parts=k, **fields))
    return out


def _part_signature(value, row: bool):
    """What every part of a message must share for a field: the row shape and dtype, or the value."""
    if row:
        return np.shape(value)[1:], value.dtype.str
    if isinstance(value, np.ndarray):
        return value.shape, value.dtype.str, value.tobytes()
    return repr(value)


def merge_parts(kind: str, parts: Sequence[dict]) -> Dict[str, np.ndarray]:
    """One payload from all decoded parts of a round message (any arrival order)."""
    parts = sorted(parts, key=lambda msg: msg["part"])
    fields = [f for f in messages.SCHEMAS[kind] if f not in messages.ENVELOPE]
    if len(parts) == 1:
        return {f: parts[0][f] for f in fields}
    if [p["part"] for p in parts] != list(range(parts[0]["parts"])) or len({p["parts"] for p in parts}) != 1:
        raise messages.MessageError(f"{kind} parts do not make one message")
    rows = messages.row_fields(kind, parts[0])
    for f in fields:
        if len({_part_signature(p[f], f in rows) for p in parts}) != 1:
            raise messages.MessageError(f"{kind} parts disagree on {f}")
    return {f: (np.concatenate([p[f] for p in parts]) if f in rows else parts[0][f]) for f in fields}


def traffic_table(report: dict, max_links: Optional[int] = None) -> str:
    """Markdown tables of a traffic report (``links``: src, dst, bytes, messages; ``kinds``;
    ``total_bytes``), the shape both the coordinator and the simulator produce. ``max_links``: show
    only that many links, the busiest (M agents make M(M+1) links), and one row for the rest."""
    links = report["links"]
    shown = links if max_links is None or len(links) <= max_links else \
        sorted(links, key=lambda e: -e["bytes"])[:max_links]
    lines = ["| link | bytes | messages |", "|---|---|---|"]
    for e in shown:
        lines.append(f"| {e['src']} -> {e['dst']} | {e['bytes']} | {e['messages']} |")
    if len(shown) < len(links):
        rest = [e for e in links if e not in shown]
        lines.append(f"| {len(rest)} other links | {sum(e['bytes'] for e in rest)} | "
                     f"{sum(e['messages'] for e in rest)} |")
    lines.append(f"| total | {report['total_bytes']} | {sum(e['messages'] for e in report['links'])} |")
    lines += ["", "| kind | bytes | messages |", "|---|---|---|"]
    for k, v in report["kinds"].items():
        lines.append(f"| {k} | {v['bytes']} | {v['messages']} |")
    return "\n".join(lines)
