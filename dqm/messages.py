"""Messages between dqm processes: msgpack, versioned, validated on receipt.

Every message is a msgpack map with at least ``v`` (schema version), ``kind``,
``job`` (job id string: keeps concurrent jobs apart) and ``src`` (sender: agent
index >= 0, or -1 for the coordinator). numpy arrays travel as
``{"dtype", "shape", "data"}`` maps of raw little-endian bytes.

:func:`decode` checks everything a receiver relies on -- size, msgpack
validity, version, kind, job, the fields of that kind with their types,
array dtypes/shapes/consistent lengths, agent indices -- and raises
:class:`MessageError` (never anything else) on a bad message, so a receiver can
count and drop it and go on.

The in-process simulator meters traffic with :func:`encode` too, so its byte
counts are those the runtime sends.
"""
from __future__ import annotations

from typing import Any, Dict, Optional

import msgpack
import numpy as np

VERSION = 1
#: default maximum encoded message size (bytes); larger messages are rejected
MAX_MESSAGE_BYTES = 64 << 20

_ALLOWED_DTYPES = {"|u1", "<i4", "<i8", "<f4", "<f8", "<u8"}


class MessageError(ValueError):
    """A message that cannot be accepted; the text says why."""


def _pack_array(a: np.ndarray) -> Dict[str, Any]:
    a = np.ascontiguousarray(a)
    dt = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
    a = a.astype(dt, copy=False)
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


def _unpack_array(obj: Any, name: str) -> np.ndarray:
    if not isinstance(obj, dict) or set(obj) != {"dtype", "shape", "data"}:
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
    if count * dtype.itemsize != len(data):
        raise MessageError(f"field {name!r}: {len(data)} bytes do not fit shape {shape} of {dt}")
    return np.frombuffer(data, dtype=dtype).reshape(shape)


# kind -> {field: type spec}; "array:<dtypes>:<ndim>" or a python type
SCHEMAS: Dict[str, Dict[str, str]] = {
    # coordinator -> agents: start a job (the only thing the coordinator decides)
    "start": {"seed": "int", "agents": "int", "mode": "str"},
    # agent -> leader: sample of own descriptors for k-means seeds
    "sample": {"descriptors": "array:|u1,<f4:2"},
    # leader -> agents: the partition seeds
    "seeds": {"seeds": "array:<f8:2"},
    # agent -> agent: features (routing or hand-down); unit: hand-down unit of every row
    "features": {"phase": "str", "seq": "int", "ids": "array:<i8:1", "image_ids": "array:<i8:1",
                 "descriptors": "array:|u1,<f4:2", "sigma": "array:<f8:1", "unit": "array:<i8:1"},
    # agent -> agent: end of a phase from this sender to this receiver (count of feature messages);
    # moved: flattened (cell, target) pairs of the sender's hand-downs (2 x K, row-major)
    "phase_end": {"phase": "str", "dst": "int", "messages": "int", "features": "int", "moved": "array:<i8:1"},
    # agent -> all agents: exchanged minima / reach maxima per other agent
    "minima": {"values": "array:<f8:1"},
    # agent -> coordinator: final clusters of the features the agent holds
    "result": {"ids": "array:<i8:1", "labels": "array:<i8:1"},
    # receiver -> sender: acknowledgement of a sequence number
    "ack": {"seq": "int", "dst": "int"},
    # agent -> coordinator: per-phase timings and local statistics (numbers only)
    "stats": {"values": "dict"},
    # coordinator -> agents: abort the job (reason)
    "abort": {"reason": "str"},
    # coordinator -> agents: all results are in, exit
    "finish": {"clusters": "int"},
}


def encode(kind: str, job: str, src: int, **fields: Any) -> bytes:
    """Encode a message; arrays become typed byte maps."""
    if kind not in SCHEMAS:
        raise MessageError(f"unknown message kind {kind!r}")
    body: Dict[str, Any] = {"v": VERSION, "kind": kind, "job": job, "src": int(src)}
    for k, v in fields.items():
        body[k] = _pack_array(v) if isinstance(v, np.ndarray) else v
    return msgpack.packb(body, use_bin_type=True)


def decode(payload: bytes, job: Optional[str] = None, n_agents: Optional[int] = None,
           max_bytes: int = MAX_MESSAGE_BYTES, dim: Optional[int] = None) -> Dict[str, Any]:
    """Decode and validate a message; raise MessageError naming the problem."""
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise MessageError("payload is not bytes")
    if len(payload) > max_bytes:
        raise MessageError(f"message of {len(payload)} bytes exceeds the maximum {max_bytes}")
    try:
        body = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=True,
                               max_bin_len=max_bytes, max_str_len=1 << 16, max_array_len=1 << 16,
                               max_map_len=1 << 10)
    except Exception as exc:  # noqa: BLE001 - any malformed input
        raise MessageError(f"not valid msgpack ({type(exc).__name__})") from None
    if not isinstance(body, dict):
        raise MessageError("message is not a map")
    if body.get("v") != VERSION:
        raise MessageError(f"schema version {body.get('v')!r} is not {VERSION}")
    kind = body.get("kind")
    if kind not in SCHEMAS:
        raise MessageError(f"unknown message kind {kind!r}")
    if not isinstance(body.get("job"), str):
        raise MessageError("missing job id")
    if job is not None and body["job"] != job:
        raise MessageError(f"message for job {body['job']!r}, not this job {job!r}")
    src = body.get("src")
    if not isinstance(src, int) or src < -1 or (n_agents is not None and src >= n_agents):
        raise MessageError(f"bad sender {src!r}")
    out: Dict[str, Any] = {"v": VERSION, "kind": kind, "job": body["job"], "src": src}
    for field, spec in SCHEMAS[kind].items():
        if field not in body:
            raise MessageError(f"{kind} message lacks field {field!r}")
        val = body[field]
        if spec == "int":
            if not isinstance(val, int) or isinstance(val, bool):
                raise MessageError(f"{kind}.{field} must be an integer")
        elif spec == "str":
            if not isinstance(val, str):
                raise MessageError(f"{kind}.{field} must be a string")
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
    if kind == "features":
        n = len(out["ids"])
        for f in ("image_ids", "sigma", "unit"):
            if len(out[f]) != n:
                raise MessageError(f"features.{f} has {len(out[f])} rows, ids has {n}")
        if out["descriptors"].shape[0] != n:
            raise MessageError(f"features.descriptors has {out['descriptors'].shape[0]} rows, ids has {n}")
        if dim is not None and n and out["descriptors"].shape[1] != dim:
            raise MessageError(f"descriptor dimension {out['descriptors'].shape[1]} is not the job's {dim}")
        if n and (out["ids"] < 0).any():
            raise MessageError("negative feature id")
        if n and not np.isfinite(out["sigma"]).all():
            raise MessageError("non-finite sigma")
        if out["descriptors"].dtype == np.float32 and n and not np.isfinite(out["descriptors"]).all():
            raise MessageError("non-finite descriptor values")
    if kind == "result" and len(out["ids"]) != len(out["labels"]):
        raise MessageError("result ids and labels differ in length")
    if kind in ("phase_end", "ack") and n_agents is not None and not 0 <= out["dst"] < n_agents:
        raise MessageError(f"bad destination agent {out['dst']}")
    if kind == "minima" and n_agents is not None and len(out["values"]) != n_agents:
        raise MessageError(f"minima has {len(out['values'])} values for {n_agents} agents")
    if kind == "seeds" and n_agents is not None and out["seeds"].shape[0] != n_agents:
        raise MessageError(f"{out['seeds'].shape[0]} seeds for {n_agents} agents")
    return out
