"""Messages between dqm processes: msgpack, versioned, validated on receipt.

Every message is a msgpack map with the header ``v`` (schema version), ``kind``,
``job`` (job id string: keeps concurrent jobs apart), ``src`` (sender: agent
index >= 0, or -1 for the coordinator), ``epoch`` (the coordinator's count of
reassignments: messages of an older epoch are refused) and ``seq`` (the
message's number on its (src, dst) link within the epoch; receivers drop a
number they have seen, so a replayed message is never processed twice; an
``ack`` carries the number it acknowledges, ``progress`` always 0). numpy arrays travel as
``{"dtype", "shape", "data"[, "enc"]}`` maps of little-endian bytes (``enc``: delta, roots and
byte-plane layouts, dqm.distributed.wire), and the fields of a message (all but the header), once they take
256 bytes or more, as one zstd frame in the field ``z`` when that is shorter: all lossless, so every
value arrives bit for bit.

:func:`decode` checks everything a receiver relies on -- size, msgpack
validity, version, kind, job, the fields of that kind with their types,
array dtypes/shapes/consistent lengths, agent indices -- and raises
:class:`MessageError` (never anything else) on a bad message, so a receiver can
count and drop it and go on.

The in-process simulator meters traffic with :func:`encode` too, so its byte
counts are those the runtime sends.

Streaming (``dqm stream``, :mod:`dqm.runtime.stream`) has two kinds of its own:
``image`` (a camera node -> the stream: one image's features; :func:`image_message`)
and ``changes`` (the stream -> subscribers: what one add or remove changed, as
flat arrays; :func:`changes_message`, :func:`changes_events`).
"""
from __future__ import annotations

import time
from typing import Any, Dict, Optional

import msgpack
import numpy as np

from ..core.events import EVENT_KINDS, ClusterEvent
from . import wire

#: the schema version (8: square roots of integers as those integers, wire's roots; 7: copies offered, then
#: pulled by windows: offer / grant / ghost; 6: takeover / taken / resume, and ready / taken / refuse not
#: numbered; 5: compact encodings). Processes of different
#: versions refuse each other's messages, naming the version
VERSION = 8
#: default maximum encoded message size (bytes); larger messages are rejected
MAX_MESSAGE_BYTES = 64 << 20
#: most entries of a map: an agent's ``stats`` hold two per (destination, kind) it sent to, so 1,024
#: (the earlier limit) rejected the statistics of every agent of a job of 43 or more agents and the
#: coordinator waited for them until its timeout; the message size limit bounds the memory anyway
MAX_MAP_ENTRIES = 1 << 20

_ALLOWED_DTYPES = {"|u1", "|i1", "<i4", "<i8", "<f4", "<f8", "<u8"}


class MessageError(ValueError):
    """A message that cannot be accepted; the text says why."""


def _pack_array(a: np.ndarray) -> Dict[str, Any]:
    a = np.ascontiguousarray(a)
    dt = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
    a = a.astype(dt, copy=False)
    enc, data = wire.encode_array(a)
    out = {"dtype": a.dtype.str, "shape": list(a.shape), "data": data}
    if enc:
        out["enc"] = enc
    return out


def _unpack_array(obj: Any, name: str) -> np.ndarray:
    if not isinstance(obj, dict) or not {"dtype", "shape", "data"} <= set(obj) <= {"dtype", "shape", "data", "enc"}:
        raise MessageError(f"field {name!r} is not an array")
    dt, shape, data = obj["dtype"], obj["shape"], obj["data"]
    if dt not in _ALLOWED_DTYPES:
        raise MessageError(f"field {name!r} has disallowed dtype {dt!r}")
    if not isinstance(shape, list) or not all(isinstance(s, int) and 0 <= s < 2 ** 40 for s in shape) or len(shape) > 3:
        raise MessageError(f"field {name!r} has a bad shape {shape!r}")
    if not isinstance(data, (bytes, bytearray)):
        raise MessageError(f"field {name!r} has no byte data")
    dtype = np.dtype(dt)
    count = int(np.prod(shape)) if shape else 1
    enc = obj.get("enc", "")
    if count * wire.encoded_itemsize(dtype, str(enc)) != len(data):
        raise MessageError(f"field {name!r}: {len(data)} bytes do not fit shape {shape} of {dt}")
    try:
        return wire.decode_array(data, dtype, tuple(shape), enc)
    except wire.WireError as exc:
        raise MessageError(f"field {name!r}: {exc}") from None


# the envelope of every data message of a round: per-link sequence number (acknowledged,
# resent, duplicates dropped) and the part index among the message's parts
ENVELOPE = {"part": "int", "parts": "int"}
#: kinds that are not numbered on their link (never deduplicated): acknowledgements, progress reports, probes,
#: and what a process (not one of its agents) tells the coordinator: ``ready``, ``taken``, ``refuse``. So an
#: agent's own messages to the coordinator are numbered alike wherever it runs (a takeover replays them)
UNNUMBERED = ("ack", "progress", "probe", "ready", "taken", "refuse")

# kind -> {field: type spec}; "array:<dtypes>:<ndim>", "int", "float", "str" or "dict"
SCHEMAS: Dict[str, Dict[str, str]] = {
    # coordinator -> every agent process: start (or restart, at a new epoch) the job: the seed integer,
    # the process hosting each agent's cell and images (owners), and the parameters that change the result
    # (params: "name=value;..." and its sha256, checked by every agent before it takes part)
    "start": {"seed": "int", "agents": "int", "owners": "array:<i8:1", "params": "str", "params_hash": "str",
              "catalog": "int"},
    # agent process -> coordinator: ready for this epoch (inboxes of its hosted agents declared)
    "ready": {"dim": "int", "dtype": "str", "hosted": "array:<i8:1", "features": "int"},
    # agent process -> coordinator: refuses the job (param: the differing parameter, or "")
    "refuse": {"reason": "str", "param": "str"},
    # coordinator -> agent processes: every process is ready, run the protocol of this epoch; mode: in a
    # --mode auto job, the mode the coordinator picked (the processes make its drivers now); "" otherwise
    "go": {"mode": "str", "engine": "str"},
    # coordinator -> every live agent process, after a process was lost while the job ran: the process now
    # hosting each agent (the lost process's agents moved to the next live one), takeover number ``round``
    # (1, 2, ... within the epoch); each process answers ``taken`` once it addresses them there
    "takeover": {"owners": "array:<i8:1", "round": "int"},
    # coordinator -> every live agent process: these agents' process exited after they had delivered everything:
    # stop waiting for their acknowledgements (nothing needs them any more)
    "gone": {"agents": "array:<i8:1"},
    # agent process -> coordinator: it follows takeover ``round`` (hosted: the agents it now hosts)
    "taken": {"round": "int", "hosted": "array:<i8:1"},
    # coordinator -> every live agent process: every process follows takeover ``round``: the new hosts run
    # the moved agents again from their start, every other process sends them again what it had sent them
    "resume": {"round": "int"},
    # agent -> coordinator: entered a phase (for the operator's progress display; not numbered)
    "progress": {"state": "str", "features": "int", "bytes": "int"},
    # agent -> leader: sample of own descriptors (seeds, cell weights, sketch basis; may be empty)
    # and the number of own features alone in their image (their sigma needs everyone's)
    "sample": {"descriptors": "array:|u1,<f4:2", "lonely": "int"},
    # leader -> agents: seeds (empty: derive them from the integer), power weights, int8 sketch
    # basis (k x dim, k may be 0), final (1: weights need no refinement), fill (1: send sigmas)
    "seeds": {"seeds": "array:<f8:2", "weights": "array:<f8:1", "basis": "array:|i1:2", "final": "int",
              "fill": "int"},
    # agent -> leader: every finite sigma of own features (only when some image has one feature)
    "sigmas": {**ENVELOPE, "values": "array:<f8:1"},
    # leader -> agents: sigma of features alone in their image (median of all finite sigmas)
    "fill": {"value": "float"},
    # agent -> leader: own features per cell under the current weights
    "counts": {"counts": "array:<i8:1"},
    # leader -> agents: refined weights (final = 1: route with these)
    "weights": {"weights": "array:<f8:1", "final": "int"},
    # agent -> agent: features (routing or lean hand-down); unit: hand-down unit of every row (empty: routing)
    "features": {"phase": "str", "ids": "array:<i8:1", "image_ids": "array:<i8:1",
                 "descriptors": "array:|u1,<f4:2", "sigma": "array:<f8:1", "unit": "array:<i8:1"},
    # agent -> agent: end of a phase from this sender to this receiver (count of feature messages);
    # moved: flattened (cell, target) pairs of the sender's hand-downs (2 x K, row-major)
    "phase_end": {"phase": "str", "dst": "int", "messages": "int", "features": "int", "moved": "array:<i8:1"},
    # lean/paper: agent -> all agents: exchanged minima per other agent
    "minima": {"values": "array:<f8:1"},
    # balanced rounds (dqm.distributed.balanced), all with the envelope
    "bounds": {**ENVELOPE, "minima": "array:<f8:1", "slack": "array:<f8:1"},
    "sketch": {**ENVELOPE, "codes": "array:|i1:2", "residual": "array:|u1:1", "reach": "array:<f4:1",
               "scale": "array:<f8:1", "bounds": "array:<f8:1", "pending": "int"},
    "request": {**ENVELOPE, "want": "int"},
    "sketch_rest": {**ENVELOPE, "codes": "array:|i1:2", "residual": "array:|u1:1", "reach": "array:<f4:1",
                    "scale": "array:<f8:1", "bounds": "array:<f8:1", "pending": "int"},
    # balanced: a sender offers a cell ``count`` copies; the cell pulls them by windows (``grant``: ``count`` copies
    # from ``offset`` on), each answered by one ``ghost`` message (possibly in parts) with those copies
    "offer": {**ENVELOPE, "count": "int"},
    "grant": {**ENVELOPE, "offset": "int", "count": "int"},
    "ghost": {**ENVELOPE, "offset": "int", "ids": "array:<i8:1", "image_ids": "array:<i8:1",
              "descriptors": "array:|u1,<f4:2", "sigma": "array:<f8:1"},
    "sums": {**ENVELOPE, "units": "array:<i8:1", "high": "array:<i8:1"},
    "density": {**ENVELOPE, "density": "array:<f8:1"},
    "proposal": {**ENVELOPE, "index": "array:<i8:1", "parent": "array:<i8:1", "distance": "array:<f8:1"},
    "notify": {**ENVELOPE, "child": "array:<i8:1", "parent": "array:<i8:1"},
    "fragments": {**ENVELOPE, "child_key": "array:<i8:1", "child_agent": "array:<i8:1",
                  "parent_key": "array:<i8:1"},
    "assign": {**ENVELOPE, "key": "array:<i8:1", "target": "array:<i8:1"},
    "component": {**ENVELOPE, "ids": "array:<i8:1", "image_ids": "array:<i8:1", "sigma": "array:<f8:1",
                  "parent": "array:<i8:1", "distance": "array:<f8:1"},
    # agent -> coordinator: final clusters of the features the agent decided
    "result": {"ids": "array:<i8:1", "labels": "array:<i8:1"},
    # agent -> coordinator, when start asked for it (catalog = 1): what the CLUSTERS file needs of the
    # agent's own features (dqm.distributed.sources): ids, image (index into the image table), keypoints
    # (rows of x, y[, size, angle], or none) and point_ids (or none); the image table: file index and local
    # image id per entry, names NUL-separated as UTF-8 (or none). Never descriptors
    "catalog": {**ENVELOPE, "ids": "array:<i8:1", "image": "array:<i4:1", "keypoints": "array:<f4:2",
                "point_ids": "array:<i8:1", "image_file": "array:<i8:1", "image_local": "array:<i8:1",
                "names": "array:|u1:1"},
    # receiver -> sender: acknowledgement of the sequence number in the header
    "ack": {"dst": "int"},
    # gather (dqm.runtime.gather): a source -> the gathering host, its features in parts (the centralized
    # baseline of the distributed modes)
    "gather": {**ENVELOPE, "ids": "array:<i8:1", "image_ids": "array:<i8:1", "descriptors": "array:|u1,<f4:2"},
    # agent -> coordinator: per-phase timings and local statistics (numbers only)
    "stats": {"values": "dict"},
    # link measurement (--mode auto): the coordinator -> a process, ``data`` bytes of filler, and the
    # process -> the coordinator, its answer with the same ``token`` and ``reply`` bytes of filler
    # (``reply``: what the coordinator asks for; 0 in an answer). Not numbered
    "probe": {"token": "int", "reply": "int", "data": "array:|u1:1"},
    # coordinator -> agents: abort the job (reason)
    "abort": {"reason": "str"},
    # coordinator -> agents: all results are in, exit
    "finish": {"clusters": "int"},
    # streaming (dqm stream). camera node -> stream: one image's features (src: the camera, >= 0; seq: its
    # frame number); keypoints: (n, 2..4) x, y[, size, angle] or empty (0 rows); time: the sender's clock
    # (seconds since the epoch) at the put, echoed in the change sets so that a listener can measure latency;
    # name: the image's name (a path or file name; optional, see OPTIONAL_FIELDS: "" = none)
    "image": {"image_id": "int", "time": "float", "descriptors": "array:|u1,<f4:2", "keypoints": "array:<f4:2",
              "name": "str"},
    # stream -> subscribers: what one add or remove (dqm.core.events.ChangeSet) changed. op: "add" or "remove";
    # image_id and time: the image added or removed (time: of the image message that caused the change);
    # one row per event: event_kind (index into dqm.core.events.EVENT_KINDS), cluster, source (-1: none),
    # new (0/1), size (its feature count); keys and images: every event's features (key, image id)
    # concatenated in event order (size of them per event); added / removed: feature keys that arrived /
    # left; the counts after the change and the stream's rejected messages so far; stats: of the update;
    # name: the name the image added or removed came with (optional, see OPTIONAL_FIELDS: "" = none)
    "changes": {"op": "str", "image_id": "int", "name": "str", "time": "float", "event_kind": "array:|u1:1",
                "cluster": "array:<i8:1", "source": "array:<i8:1", "new": "array:|u1:1", "size": "array:<i8:1",
                "keys": "array:<i8:1", "images": "array:<i8:1", "added": "array:<i8:1", "removed": "array:<i8:1",
                "n_images": "int", "n_features": "int", "n_clusters": "int", "rejected": "int", "stats": "dict"},
}

#: the coordinator's kinds (sender -1); it also sends ``ack``
CONTROL = ("start", "go", "takeover", "resume", "gone", "abort", "finish")
#: ``changes.op`` values
CHANGE_OPS = ("add", "remove")
#: fields a message of the kind may lack (sent by an older sender of the same schema version): their value
#: when absent. An older receiver ignores them (decode keeps only the fields it knows), so adding one
#: keeps the version
OPTIONAL_FIELDS: Dict[str, Dict[str, Any]] = {"image": {"name": ""}, "changes": {"name": ""},
                                              "go": {"mode": "", "engine": ""}, "start": {"catalog": 0}}
#: longest ``image.name`` / ``changes.name`` (characters); control characters are refused
MAX_NAME_CHARS = 4096

#: fields of one row per feature (split across parts; equal lengths within a message)
ROW_FIELDS: Dict[str, tuple] = {
    "sigmas": ("values",),
    "sketch": ("codes", "residual", "reach"),
    "sketch_rest": ("codes", "residual", "reach"),
    "ghost": ("ids", "image_ids", "descriptors", "sigma"),
    "sums": ("units",),
    "density": ("density",),
    "proposal": ("index", "parent", "distance"),
    "notify": ("child", "parent"),
    "fragments": ("child_key", "child_agent", "parent_key"),
    "assign": ("key", "target"),
    "component": ("ids", "image_ids", "sigma", "parent", "distance"),
    "changes": ("event_kind", "cluster", "source", "new", "size"),
    "catalog": ("ids", "image"),
    "gather": ("ids", "image_ids", "descriptors"),
}
#: row fields that may also be empty (sums.high: only when a partial sum is too large for one int64)
OPTIONAL_ROW_FIELDS: Dict[str, tuple] = {"sums": ("high",), "catalog": ("keypoints", "point_ids")}


def row_fields(kind: str, fields: Dict[str, Any]) -> tuple:
    """The fields of one row per feature in this message: the kind's, and its optional ones present."""
    return ROW_FIELDS.get(kind, ()) + tuple(f for f in OPTIONAL_ROW_FIELDS.get(kind, ()) if len(fields[f]))


def encode(kind: str, job: str, src: int, *, seq: int = 0, epoch: int = 0, **fields: Any) -> bytes:
    """Encode a message (header: ``seq`` on its link, ``epoch``); arrays become typed byte maps."""
    if kind not in SCHEMAS:
        raise MessageError(f"unknown message kind {kind!r}")
    body: Dict[str, Any] = {"v": VERSION, "kind": kind, "job": job, "src": int(src), "epoch": int(epoch),
                            "seq": int(seq)}
    for k, v in fields.items():
        body[k] = _pack_array(v) if isinstance(v, np.ndarray) else v
    return pack_body(body)


#: the header of every message (outside the compressed fields; see :func:`pack_body`)
HEADER = ("v", "kind", "job", "src", "epoch", "seq")
#: the header field that carries the other fields as one zstd frame (dqm.distributed.wire)
FRAME_FIELD = "z"


def pack_body(body: Dict[str, Any]) -> bytes:
    """The payload of a message body (a map of plain values and packed arrays): msgpack, with every
    field but the header compressed into one zstd frame (dqm.distributed.wire) when that is shorter, so
    that the size of a message does not depend on its header."""
    head = {k: v for k, v in body.items() if k in HEADER}
    rest = {k: v for k, v in body.items() if k not in HEADER}
    packed = msgpack.packb(rest, use_bin_type=True)
    frame = wire.compress(packed)
    if frame is packed:
        return msgpack.packb(body, use_bin_type=True)
    return msgpack.packb({**head, FRAME_FIELD: frame}, use_bin_type=True)


def _unpackb(raw: bytes, max_bytes: int) -> Any:
    try:
        return msgpack.unpackb(raw, raw=False, strict_map_key=True, max_bin_len=max_bytes, max_str_len=1 << 16,
                               max_array_len=1 << 16, max_map_len=MAX_MAP_ENTRIES)
    except Exception as exc:  # noqa: BLE001 - any malformed input
        raise MessageError(f"not valid msgpack ({type(exc).__name__})") from None


def unpack_body(payload: bytes, max_bytes: int = MAX_MESSAGE_BYTES) -> Any:
    """The msgpack value of a payload with its compressed fields restored, not validated further (also
    for tools that alter messages: :func:`pack_body` packs it again); raises MessageError."""
    body = _unpackb(bytes(payload), max_bytes)
    if not isinstance(body, dict) or FRAME_FIELD not in body:
        return body
    frame = body.pop(FRAME_FIELD)
    if not isinstance(frame, (bytes, bytearray)):
        raise MessageError("compressed fields are not bytes")
    try:
        rest = _unpackb(wire.decompress(frame, max_bytes), max_bytes)
    except wire.WireError as exc:
        raise MessageError(str(exc)) from None
    if not isinstance(rest, dict) or set(rest) & (set(body) | {FRAME_FIELD}):
        raise MessageError("compressed fields are not a map of fields apart from the header")
    body.update(rest)
    return body


def decode(payload: bytes, job: Optional[str] = None, agents: Optional[int] = None,  # noqa: C901 - a check per field, in wire order
           max_bytes: int = MAX_MESSAGE_BYTES, dim: Optional[int] = None, sender: Optional[int] = None,
           owners: Optional[np.ndarray] = None) -> Dict[str, Any]:
    """Decode and validate a message; raise MessageError naming the problem.

    ``sender``: the process its key names as the sender (-1: the coordinator; see
    :mod:`dqm.distributed.keys`), checked against the message's ``src`` with :func:`check_sender`
    and ``owners`` (the process hosting each agent in the receiver's epoch).
    """
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise MessageError("payload is not bytes")
    if len(payload) > max_bytes:
        raise MessageError(f"message of {len(payload)} bytes exceeds the maximum {max_bytes}")
    body = unpack_body(payload, max_bytes)
    if not isinstance(body, dict):
        raise MessageError("message is not a map")
    if body.get("v") != VERSION:
        raise MessageError(f"schema version {body.get('v')!r} is not {VERSION}")
    kind = body.get("kind")
    if not isinstance(kind, str) or kind not in SCHEMAS:
        raise MessageError(f"unknown message kind {str(kind)[:40]!r}")
    if not isinstance(body.get("job"), str):
        raise MessageError("missing job id")
    if job is not None and body["job"] != job:
        raise MessageError(f"message for job {body['job']!r}, not this job {job!r}")
    src = body.get("src")
    if not isinstance(src, int) or src < -1 or (agents is not None and src >= agents):
        raise MessageError(f"bad sender {src!r}")
    for field in ("epoch", "seq"):
        val = body.get(field)
        if not isinstance(val, int) or isinstance(val, bool) or not 0 <= val < 1 << 62:
            raise MessageError(f"bad {field} {val!r}")
    out: Dict[str, Any] = {"v": VERSION, "kind": kind, "job": body["job"], "src": src, "epoch": body["epoch"],
                           "seq": body["seq"]}
    for field, spec in SCHEMAS[kind].items():
        if field not in body:
            if field in OPTIONAL_FIELDS.get(kind, {}):
                out[field] = OPTIONAL_FIELDS[kind][field]
                continue
            raise MessageError(f"{kind} message lacks field {field!r}")
        val = body[field]
        if spec == "int":
            if not isinstance(val, int) or isinstance(val, bool):
                raise MessageError(f"{kind}.{field} must be an integer")
        elif spec == "str":
            if not isinstance(val, str):
                raise MessageError(f"{kind}.{field} must be a string")
        elif spec == "float":
            if isinstance(val, bool) or not isinstance(val, (int, float)) or not np.isfinite(val):
                raise MessageError(f"{kind}.{field} must be a finite number")
            val = float(val)
        elif spec == "dict":
            if not isinstance(val, dict) or not all(
                    isinstance(k, str) and isinstance(x, (int, float)) for k, x in val.items()):
                raise MessageError(f"{kind}.{field} must be a map of numbers")
        else:
            _, dts, nd = spec.split(":")
            arr = _unpack_array(val, f"{kind}.{field}")
            if arr.dtype.str not in dts.split(","):
                raise MessageError(f"{kind}.{field} has dtype {arr.dtype.str}, expected {dts}")
            if arr.ndim != int(nd):
                raise MessageError(f"{kind}.{field} must be {nd}-D, got shape {arr.shape}")
            val = arr
        out[field] = val
    _check_content(kind, out, agents, dim)
    if sender is not None:
        check_sender(out, sender, owners)
    return out


def check_sender(msg: Dict[str, Any], sender: int, owners: Optional[np.ndarray] = None) -> None:
    """Refuse a message whose key names another sender than the message: the coordinator's key carries
    only the coordinator's messages (``src`` -1), and agent process ``sender``'s key only messages of
    the agents it hosts (``owners[a]``: agent a's process in this epoch; None: agent p on process p).
    Under a router's access control (``dqm router --acl``) only the key's identity may put on it, so
    no admitted process can speak for another."""
    src, kind = msg["src"], msg["kind"]
    if sender < 0:
        if src != -1:
            raise MessageError(f"{kind} message of agent {src} on the coordinator's key")
        return
    if src < 0:
        raise MessageError(f"{kind} message of the coordinator on the key of process {sender}")
    host = src if owners is None else (int(owners[src]) if src < len(owners) else None)
    if host != sender:
        raise MessageError(f"{kind} message of agent {src} on the key of process {sender}, which does not host it")


def _nonneg(arr: np.ndarray, what: str, allow_inf: bool = False) -> None:
    ok = (arr >= 0) & (np.isfinite(arr) | (allow_inf & (arr == np.inf)))
    if len(arr) and not ok.all():
        raise MessageError(f"{what} must be {'non-negative' if allow_inf else 'finite and non-negative'}")


def _check_content(kind: str, out: Dict[str, Any], agents: Optional[int], dim: Optional[int]) -> None:  # noqa: C901 - one rule per kind, the wire contract in one place
    """Checks beyond types: lengths, ranges, finiteness, agent indices, dimensions."""
    if "parts" in out and not 0 <= out["part"] < out["parts"] <= 1 << 20:
        raise MessageError(f"{kind} message has a bad part {out['part']} of {out['parts']}")
    if (kind in CONTROL) != (out["src"] == -1) and kind not in ("ack", "probe"):  # the coordinator acknowledges
        # catalogs; probes go both ways
        raise MessageError(f"{kind} message from the wrong sender {out['src']}")
    rows = row_fields(kind, out)
    if rows:
        n = len(out[rows[0]])
        for f in rows[1:]:
            if len(out[f]) != n:
                raise MessageError(f"{kind}.{f} has {len(out[f])} rows, {rows[0]} has {n}")
    if "descriptors" in out and kind in ("features", "ghost", "sample", "image", "gather"):
        d = out["descriptors"]
        if kind == "image" and d.shape[1] == 0:
            raise MessageError(f"{kind}.descriptors have no dimensions (shape {tuple(d.shape)})")
        if dim is not None and len(d) and d.shape[1] != dim:
            raise MessageError(f"descriptor dimension {d.shape[1]} is not the job's {dim}")
        if d.dtype == np.float32 and len(d) and not np.isfinite(d).all():
            raise MessageError("non-finite descriptor values")
    for f in ("ids", "child", "child_key", "parent_key", "key", "index", "units", "high"):
        if f in out and isinstance(out[f], np.ndarray) and len(out[f]) and (out[f] < 0).any():
            raise MessageError("negative feature id" if f == "ids" else f"negative {kind}.{f}")
    if "sigma" in out and kind != "features":
        _nonneg(out["sigma"], f"{kind}.sigma")
    if kind == "features" and len(out["ids"]) and (out["sigma"] < 0).any():
        raise MessageError("negative sigma")
    if kind == "features":
        n = len(out["ids"])
        for f in ("image_ids", "sigma", "unit"):
            if len(out[f]) != n and not (f == "unit" and len(out[f]) == 0):
                raise MessageError(f"features.{f} has {len(out[f])} rows, ids has {n}")
        if out["descriptors"].shape[0] != n:
            raise MessageError(f"features.descriptors has {out['descriptors'].shape[0]} rows, ids has {n}")
        if n and not np.isfinite(out["sigma"]).all():
            raise MessageError("non-finite sigma")
    if kind in ("component", "proposal"):
        low = 0 if kind == "proposal" else -1  # a proposal names a feature; a component member may have none
        if len(out["parent"]) and (out["parent"] < low).any():
            raise MessageError(f"{kind}.parent below {low}")
        _nonneg(out["distance"], f"{kind}.distance", allow_inf=True)
    if kind == "notify" and len(out["parent"]) and (out["parent"] < 0).any():
        raise MessageError("negative notify.parent")
    if kind == "density" and len(out["density"]) and not np.isfinite(out["density"]).all():
        raise MessageError("non-finite density")
    if kind == "sigmas":
        _nonneg(out["values"], "sigmas.values")
    for f in ("count", "offset"):
        if kind in ("offer", "grant", "ghost") and f in out and out[f] < 0:
            raise MessageError(f"negative {kind}.{f}")
    if kind in ("sketch", "sketch_rest"):
        if out["pending"] < 0:
            raise MessageError(f"negative {kind}.pending")
        k = out["codes"].shape[1]
        if len(out["scale"]) != k or len(out["bounds"]) != 4:
            raise MessageError(f"sketch has {len(out['scale'])} scales and {len(out['bounds'])} bounds for {k} dims")
        if not (np.isfinite(out["scale"]).all() and (out["scale"] > 0).all() and np.isfinite(out["bounds"]).all()):
            raise MessageError("sketch scales and bounds must be finite (scales > 0)")
        _nonneg(out["reach"].astype(np.float64), "sketch.reach")
    if kind in ("bounds",):
        for f in ("minima", "slack"):
            if np.isnan(out[f]).any():
                raise MessageError(f"bounds.{f} holds NaN")
    if kind == "start" and (out["agents"] < 1 or len(out["owners"]) != out["agents"]
                            or (len(out["owners"]) and ((out["owners"] < 0) | (out["owners"] >= out["agents"])).any())):
        raise MessageError(f"start names {len(out['owners'])} owners for {out['agents']} agents")
    if kind == "ready" and (out["dim"] < 1 or out["features"] < 0 or out["dtype"] not in ("|u1", "<f4")):
        raise MessageError("ready has a bad dimension, feature count or dtype")
    if kind == "probe" and not (0 <= out["token"] < 1 << 62 and 0 <= out["reply"] <= MAX_MESSAGE_BYTES // 2):
        raise MessageError("probe has a bad token or reply size")
    if kind == "progress" and (out["features"] < 0 or out["bytes"] < 0):
        raise MessageError("negative progress counts")
    if kind == "catalog":
        if len(out["image_file"]) != len(out["image_local"]):
            raise MessageError("catalog.image_file and image_local differ in length")
        if len(out["image"]) and ((out["image"] < 0) | (out["image"] >= len(out["image_local"]))).any():
            raise MessageError("catalog.image names an entry outside the image table")
        kp = out["keypoints"]
        if len(kp) and (not 2 <= kp.shape[1] <= 4 or not np.isfinite(kp).all()):
            raise MessageError("catalog.keypoints must be finite rows of 2..4 numbers")
    if kind == "result" and len(out["ids"]) != len(out["labels"]):
        raise MessageError("result ids and labels differ in length")
    if kind in ("image", "changes"):
        _check_stream(kind, out)
    if agents is None:
        return
    if kind in ("ready", "taken") and len(out["hosted"]) and ((out["hosted"] < 0) | (out["hosted"] >= agents)).any():
        raise MessageError(f"{kind} names an agent outside the job")
    if kind == "gone" and len(out["agents"]) and ((out["agents"] < 0) | (out["agents"] >= agents)).any():
        raise MessageError("gone names an agent outside the job")
    if kind == "takeover" and (len(out["owners"]) != agents or out["round"] < 1
                               or ((out["owners"] < 0) | (out["owners"] >= agents)).any()):
        raise MessageError(f"takeover names {len(out['owners'])} owners for {agents} agents, or a bad round")
    if kind in ("phase_end", "ack") and not 0 <= out["dst"] < agents:
        raise MessageError(f"bad destination agent {out['dst']}")
    for f in ("child_agent", "target"):
        if f in out and len(out[f]) and ((out[f] < 0) | (out[f] >= agents)).any():
            raise MessageError(f"{kind}.{f} names an agent outside 0..{agents - 1}")
    if kind in ("minima", "counts", "weights") or kind == "bounds":
        fields = {"minima": ("values",), "counts": ("counts",), "weights": ("weights",),
                  "bounds": ("minima", "slack")}[kind]
        for f in fields:
            if len(out[f]) != agents:
                raise MessageError(f"{kind}.{f} has {len(out[f])} values for {agents} agents")
    if kind == "seeds":
        if out["seeds"].shape[0] not in (0, agents) or len(out["weights"]) != agents:
            raise MessageError(f"{out['seeds'].shape[0]} seeds and {len(out['weights'])} weights for {agents} agents")
        if not (np.isfinite(out["seeds"]).all() and np.isfinite(out["weights"]).all()):
            raise MessageError("non-finite seeds or weights")
        if dim is not None and (out["seeds"].shape[0] and out["seeds"].shape[1] != dim
                                or len(out["basis"]) and out["basis"].shape[1] != dim):
            raise MessageError(f"seeds or sketch basis do not have the job's dimension {dim}")
    if kind == "weights" and not np.isfinite(out["weights"]).all():
        raise MessageError("non-finite weights")


def _check_stream(kind: str, out: Dict[str, Any]) -> None:
    """Content of the streaming kinds (types and row counts are checked already)."""
    if out["image_id"] < 0:
        raise MessageError(f"negative image id {out['image_id']}")
    if out["time"] < 0:
        raise MessageError(f"{kind}.time is negative")
    name = out["name"]
    if len(name) > MAX_NAME_CHARS or any(ord(ch) < 32 or ord(ch) == 127 for ch in name):
        raise MessageError(f"{kind}.name must be at most {MAX_NAME_CHARS} characters without control characters")
    if kind == "image":
        n = len(out["descriptors"])
        kp = out["keypoints"]
        if len(kp):
            if len(kp) != n:
                raise MessageError(f"image.keypoints has {len(kp)} rows, descriptors has {n}")
            if not 2 <= kp.shape[1] <= 4:
                raise MessageError(f"image.keypoints must have 2 to 4 columns (x, y, size, angle), got {kp.shape[1]}")
            if not np.isfinite(kp).all():
                raise MessageError("non-finite keypoint values")
        return
    if out["op"] not in CHANGE_OPS:
        raise MessageError(f"changes.op {out['op'][:20]!r} is not one of {', '.join(CHANGE_OPS)}")
    for f in ("n_images", "n_features", "n_clusters", "rejected"):
        if out[f] < 0:
            raise MessageError(f"negative changes.{f}")
    if len(out["event_kind"]) and out["event_kind"].max() >= len(EVENT_KINDS):
        raise MessageError(f"changes.event_kind names an unknown kind {int(out['event_kind'].max())}")
    if len(out["new"]) and out["new"].max() > 1:
        raise MessageError("changes.new must be 0 or 1")
    for f, low in (("cluster", 0), ("source", -1), ("size", 0), ("keys", 0), ("images", 0), ("added", 0),
                   ("removed", 0)):
        if len(out[f]) and out[f].min() < low:
            raise MessageError(f"changes.{f} below {low}")
    total = int(out["size"].sum()) if len(out["size"]) else 0
    for f in ("keys", "images"):
        if len(out[f]) != total:
            raise MessageError(f"changes.{f} has {len(out[f])} rows, the events' sizes add up to {total}")


def image_message(job: str, camera: int, image_id: int, descriptors, keypoints=None, *, seq: int = 0,
                  sent: Optional[float] = None, name: str = "") -> bytes:
    """An ``image`` message: one image's descriptors (uint8 stays uint8, others become float32) and
    keypoints (optional), from camera node ``camera``; ``sent``: the sender's clock (default now);
    ``name``: the image's name ("" = none)."""
    d = np.asarray(descriptors)
    d = d if d.dtype == np.uint8 else np.ascontiguousarray(d, dtype=np.float32)
    kp = np.zeros((0, 4), np.float32) if keypoints is None else np.ascontiguousarray(keypoints, dtype=np.float32)
    return encode("image", job, camera, seq=seq, image_id=int(image_id),
                  time=float(time.time() if sent is None else sent), descriptors=d, keypoints=kp, name=str(name))


def changes_message(job: str, changeset, op: str, image_id: int, *, sent: float, n_images: int,
                    n_features: int, n_clusters: int, rejected: int, seq: int = 0, src: int = 0,
                    name: str = "") -> bytes:
    """A ``changes`` message from a :class:`dqm.core.events.ChangeSet` (see :data:`SCHEMAS`); ``name``: the
    image's name ("" = none)."""
    ev = list(changeset.events)

    def cat(parts: list) -> np.ndarray:
        return np.concatenate(parts).astype(np.int64) if parts else np.zeros(0, np.int64)

    return encode(
        "changes", job, src, seq=seq, op=op, image_id=int(image_id), name=str(name), time=float(sent),
        event_kind=np.array([EVENT_KINDS.index(e.kind) for e in ev], np.uint8),
        cluster=np.array([e.cluster for e in ev], np.int64), source=np.array([e.source for e in ev], np.int64),
        new=np.array([bool(e.new) for e in ev], np.uint8), size=np.array([len(e.features) for e in ev], np.int64),
        keys=cat([np.asarray(e.features) for e in ev]), images=cat([np.asarray(e.images) for e in ev]),
        added=np.asarray(changeset.added, np.int64), removed=np.asarray(changeset.removed, np.int64),
        n_images=int(n_images), n_features=int(n_features), n_clusters=int(n_clusters), rejected=int(rejected),
        stats={str(k): float(v) for k, v in dict(changeset.stats).items()})


def changes_events(msg: Dict[str, Any]) -> list:
    """The :class:`dqm.core.events.ClusterEvent` list of a decoded ``changes`` message, in order."""
    bounds = np.concatenate([[0], np.cumsum(msg["size"])]).astype(np.int64)
    return [ClusterEvent(EVENT_KINDS[int(k)], int(c), msg["keys"][a:b].astype(np.int64),
                         msg["images"][a:b].astype(np.int64), int(s), bool(n))
            for k, c, s, n, a, b in zip(msg["event_kind"], msg["cluster"], msg["source"], msg["new"],
                                        bounds[:-1], bounds[1:])]
