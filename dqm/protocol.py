"""The Distributed QuickMatch wire protocol: which messages carry what, built once.

Both the in-process simulator (to meter) and the runtime agents (to send) build
their messages with these functions, so the bytes the simulator counts are the
bytes the runtime sends.

Phases and messages (``src -> dst``):

=============  ===========================  ==========================================
phase          message kind                 content
=============  ===========================  ==========================================
start          coordinator -> every agent   ``start``: the partition seed integer
seeds          agent a -> agent 0           ``sample``: a deterministic sample (kmeans)
               agent 0 -> every agent       ``seeds``: the m seeds (kmeans)
route          agent a -> agent b           ``features`` chunks (seq 0..k-1), then
                                            ``phase_end`` with k (also when k = 0)
minima         agent a -> every agent       ``minima``: e[a, .]
handdown       agent a -> agent b < a       ``features`` chunks, then ``phase_end``
                                            with k and the (cell, target) moves
result         agent a -> coordinator       ``result`` (ids, labels), ``stats``
any            receiver -> sender           ``ack`` of every ``features`` chunk
=============  ===========================  ==========================================
"""
from __future__ import annotations

from typing import List

import numpy as np

from . import messages

#: feature rows per features message (keeps messages well under the size limit)
CHUNK_ROWS = 4096


def chunk_count(n_rows: int) -> int:
    """Number of ``features`` chunks for ``n_rows`` features."""
    return (int(n_rows) + CHUNK_ROWS - 1) // CHUNK_ROWS


def wire_descriptors(descriptors: np.ndarray) -> np.ndarray:
    """Descriptors as they travel: uint8 stays uint8, anything else becomes float32."""
    d = np.asarray(descriptors)
    return d if d.dtype == np.uint8 else np.ascontiguousarray(d, dtype=np.float32)


def feature_messages(job: str, src: int, phase: str, ids, image_ids, descriptors, sigma, unit,
                     seq0: int = 0) -> List[bytes]:
    """The ``features`` chunks of one (src, dst, phase), numbered ``seq0, seq0 + 1, ...``.

    Sequence numbers are per directed link and never reused within a job, so
    an ack names one chunk and a duplicate is recognised.
    """
    n = len(ids)
    desc = wire_descriptors(descriptors)
    out = []
    for k, s in enumerate(range(0, n, CHUNK_ROWS)):
        sl = slice(s, s + CHUNK_ROWS)
        out.append(messages.encode(
            "features", job, src, phase=phase, seq=seq0 + k, ids=np.asarray(ids[sl], np.int64),
            image_ids=np.asarray(image_ids[sl], np.int64), descriptors=np.ascontiguousarray(desc[sl]),
            sigma=np.asarray(sigma[sl], np.float64), unit=np.asarray(unit[sl], np.int64)))
    return out


def phase_end(job: str, src: int, dst: int, phase: str, n_messages: int, n_features: int,
              moved: np.ndarray | None = None) -> bytes:
    mv = np.zeros(0, np.int64) if moved is None else np.asarray(moved, np.int64).reshape(-1)
    return messages.encode("phase_end", job, src, phase=phase, dst=dst, messages=int(n_messages),
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


def ack(job: str, src: int, dst: int, seq: int) -> bytes:
    return messages.encode("ack", job, src, seq=int(seq), dst=int(dst))


def traffic_table(report: dict) -> str:
    """Markdown tables of a traffic report (``links``: src, dst, bytes, messages; ``kinds``;
    ``total_bytes``), the shape both the coordinator and the simulator produce."""
    lines = ["| link | bytes | messages |", "|---|---|---|"]
    for e in report["links"]:
        lines.append(f"| {e['src']} -> {e['dst']} | {e['bytes']} | {e['messages']} |")
    lines.append(f"| total | {report['total_bytes']} | {sum(e['messages'] for e in report['links'])} |")
    lines += ["", "| kind | bytes | messages |", "|---|---|---|"]
    for k, v in report["kinds"].items():
        lines.append(f"| {k} | {v['bytes']} | {v['messages']} |")
    return "\n".join(lines)
