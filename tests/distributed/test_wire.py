"""The compact wire encodings (dqm.distributed.wire): exact round trips, shorter messages, clean refusals."""
import msgpack
import numpy as np
import pytest
import zstandard

from dqm.distributed import messages, wire

JOB = "wire-test"


def _edge_arrays():
    rng = np.random.default_rng(5)
    i8 = np.iinfo(np.int64)
    yield "sorted ids", np.sort(rng.integers(0, 10 ** 9, 500)).astype(np.int64)
    yield "runs of image ids", np.repeat(np.arange(7, dtype=np.int64), 90)
    yield "int64 extremes, sorted", np.array([i8.min, i8.min + 1, -1, 0, 0, 1, i8.max - 1, i8.max] * 2, np.int64)
    yield "int64 extremes, unsorted", np.array([i8.max, i8.min, 0, -5, i8.max, 3, i8.min, 1, 2], np.int64)
    yield "int32 wrap", np.array([np.iinfo(np.int32).min] * 3 + [0] * 3 + [np.iinfo(np.int32).max] * 3, np.int32)
    yield "uint64", np.sort(rng.integers(0, 2 ** 63, 64, dtype=np.uint64)) * np.uint64(2)
    yield "sigma float64", rng.gamma(2.0, 40.0, 300)
    yield "floats with specials", np.array([0.0, -0.0, np.inf, -np.inf, 1e-310, np.finfo(np.float64).max,
                                            np.nextafter(1.0, 2.0), np.nan, -7.25])
    roots = np.sqrt(rng.integers(0, 200_000, 300).astype(np.float64))
    yield "roots of integers (sigmas of uint8 descriptors)", roots
    yield "roots with +inf and the largest integer", np.concatenate([roots[:20], [np.inf, 0.0],
                                                                     np.sqrt([float(wire.ROOT_INF - 1)])])
    yield "roots but one a step off", np.concatenate([roots[:20], [np.nextafter(roots[3], 0.0)]])
    yield "roots but one -0.0", np.concatenate([roots[:20], [-0.0]])
    yield "roots but one negative", np.concatenate([roots[:20], [-roots[5]]])
    yield "roots but one NaN, late", np.concatenate([roots, [np.nan]])
    yield "roots but one too large", np.concatenate([roots[:20], [np.sqrt(float(wire.ROOT_INF))]])
    yield "float32", rng.standard_normal(100).astype(np.float32)
    yield "short", np.array([3, 1, 2], np.int64)
    yield "empty", np.zeros(0, np.int64)
    yield "uint8 descriptors", rng.integers(0, 256, (40, 128)).astype(np.uint8)
    yield "2-D float", rng.standard_normal((9, 4))


@pytest.mark.parametrize("name,a", list(_edge_arrays()), ids=[n for n, _ in _edge_arrays()])
def test_arrays_round_trip_bit_for_bit(name, a):
    enc, data = wire.encode_array(np.ascontiguousarray(a))
    assert len(data) == a.size * wire.encoded_itemsize(a.dtype, enc)
    assert (enc == "rs") == (name.startswith("roots with") or name.startswith("roots of integers"))
    back = wire.decode_array(data, a.dtype, a.shape, enc)
    assert back.dtype == a.dtype and back.shape == a.shape
    assert back.tobytes() == a.tobytes()  # bit for bit: -0.0, infinities and wrap-around included


def test_layouts_are_chosen_by_content():
    assert wire.encode_array(np.arange(20, dtype=np.int64))[0] == "ds"
    assert wire.encode_array(np.arange(20, dtype=np.int64)[::-1].copy())[0] == "s"
    assert wire.encode_array(np.arange(20, dtype=np.float64) + 0.5)[0] == "s"
    assert wire.encode_array(np.arange(20, dtype=np.float64))[0] == "rs"  # integers are roots of their squares
    assert wire.encode_array(np.arange(20, dtype=np.uint8))[0] == ""
    assert wire.encode_array(np.arange(5, dtype=np.int64))[0] == ""
    assert wire.encode_array(np.sqrt(np.arange(20, dtype=np.float64)))[0] == "rs"
    assert wire.encode_array(np.sqrt(np.arange(20, dtype=np.float64)) + 0.5)[0] == "s"
    assert wire.encode_array(np.sqrt(np.arange(20, dtype=np.float32)))[0] == "s"  # float64 only


def test_sigmas_of_integer_descriptors_travel_as_integers():
    """The sigmas and distances of uint8 descriptors are square roots of integers: they travel in about a
    third of their float64 bytes, and arrive bit for bit."""
    from dqm import quickmatch, synthetic
    ds = synthetic.sized(3000)
    r = quickmatch(ds.descriptors, ds.image_ids)
    for name, v in (("sigma", r.sigma), ("parent_distance", r.parent_distance)):
        assert np.isinf(v).any() or name == "sigma"
        as_roots = messages.encode("component", JOB, 1, part=0, parts=1, ids=np.arange(len(v), dtype=np.int64),
                                   image_ids=ds.image_ids.astype(np.int64), sigma=r.sigma,
                                   parent=np.zeros(len(v), np.int64), distance=v)
        out = messages.decode(as_roots, job=JOB)
        assert out["sigma"].tobytes() == r.sigma.tobytes() and out["distance"].tobytes() == v.tobytes()
        enc, data = wire.encode_array(v)
        assert enc == "rs", name
        _, plain = wire.encode_array(v + 0.25)  # the same values, no longer roots: byte planes
        assert len(wire.compress(data)) < 0.5 * len(wire.compress(plain)), name


def _outer(payload: bytes) -> dict:
    return msgpack.unpackb(payload, raw=False)


def test_routing_message_is_smaller_and_exact():
    """A routing message of SIFT-like descriptors: compressed well below its raw size, decoded exactly."""
    rng = np.random.default_rng(1)
    n = 2000
    d = np.minimum(rng.exponential(25.0, (n, 128)), 255).astype(np.uint8)
    ids = np.sort(rng.choice(10 ** 6, n, replace=False)).astype(np.int64)
    img = np.repeat(np.arange(4, dtype=np.int64), n // 4)
    sigma = rng.gamma(3.0, 30.0, n)
    fields = dict(phase="route", ids=ids, image_ids=img, descriptors=d, sigma=sigma, unit=np.zeros(0, np.int64))
    payload = messages.encode("features", JOB, 2, seq=4, **fields)
    plain = msgpack.packb({"v": messages.VERSION, "kind": "features", "job": JOB, "src": 2, "epoch": 0, "seq": 4,
                           **{k: ({"dtype": v.dtype.str, "shape": list(v.shape), "data": v.tobytes()}
                                  if isinstance(v, np.ndarray) else v) for k, v in fields.items()}},
                          use_bin_type=True)
    assert set(_outer(payload)) == set(messages.HEADER) | {messages.FRAME_FIELD}
    assert len(payload) < 0.8 * len(plain)
    out = messages.decode(payload, job=JOB)
    for k in ("ids", "image_ids", "descriptors", "sigma"):
        assert out[k].dtype == fields[k].dtype and np.array_equal(out[k], fields[k])
    assert messages.decode(plain, job=JOB)["ids"].tolist() == ids.tolist()  # plain bodies still read
    # the size does not depend on the header: the simulator and the runtime number links alike, but not
    # every test harness does
    assert len(messages.encode("features", JOB, 2, seq=100000, epoch=3, **fields)) - len(payload) == \
        len(msgpack.packb(100000)) - len(msgpack.packb(4)) + len(msgpack.packb(3)) - len(msgpack.packb(0))


def test_small_messages_stay_plain():
    payload = messages.encode("go", JOB, -1)
    assert messages.FRAME_FIELD not in _outer(payload)
    assert messages.decode(payload, job=JOB)["kind"] == "go"


def _frame(body: bytes, **kw) -> bytes:
    return zstandard.ZstdCompressor(level=1, **kw).compress(body)


def _with_frame(frame, **extra) -> bytes:
    head = {"v": messages.VERSION, "kind": "gather", "job": JOB, "src": 1, "epoch": 0, "seq": 0}
    return msgpack.packb({**head, messages.FRAME_FIELD: frame, **extra}, use_bin_type=True)


def test_malformed_compressed_messages_are_refused_cleanly():
    good = messages.encode("gather", JOB, 1, part=0, parts=1, ids=np.arange(100, dtype=np.int64),
                           image_ids=np.zeros(100, np.int64), descriptors=np.ones((100, 16), np.uint8))
    frame = _outer(good)[messages.FRAME_FIELD]
    assert wire.is_frame(frame)
    fields = wire.decompress(frame, 1 << 20)
    cases = {
        "truncated frame": _with_frame(frame[:len(frame) // 2]),
        "magic only": _with_frame(wire.ZSTD_MAGIC),
        "not a frame": _with_frame(b"\x00" * 40),
        "not bytes": _with_frame("text"),
        "corrupted": _with_frame(frame[:12] + bytes(b ^ 0x5A for b in frame[12:30]) + frame[30:]),
        "no declared size": _with_frame(_frame(fields, write_content_size=False)),
        "bomb": _with_frame(_frame(b"\x00" * (5 << 20))),
        "garbage inside": _with_frame(_frame(b"\xc1" * 400)),
        "not a map inside": _with_frame(_frame(msgpack.packb(list(range(300))))),
        "header inside": _with_frame(_frame(msgpack.packb({"src": 0, "pad": b"x" * 300}))),
        "field twice": _with_frame(frame, part=0),
    }
    for name, payload in cases.items():
        with pytest.raises(messages.MessageError) as err:
            messages.decode(payload, job=JOB, max_bytes=1 << 20)
        text = str(err.value)
        assert "\n" not in text and ("compress" in text or "zstd" in text or "msgpack" in text), (name, text)
    with pytest.raises(messages.MessageError, match="exceeds the maximum"):
        messages.decode(cases["bomb"], job=JOB, max_bytes=1 << 20)
    assert messages.decode(_with_frame(frame), job=JOB)["ids"].tolist() == list(range(100))


@pytest.mark.parametrize("enc,shape,dtype,match", [
    ("zz", (10,), np.int64, "unknown array encoding"),
    ("d", (10,), np.float64, "does not apply"),
    ("s", (10,), np.uint8, "does not apply"),
    ("s", (3,), np.int64, "does not apply"),
    ("s", (4, 3), np.int64, "does not apply"),
    ("rs", (10,), np.int64, "does not apply"),
    ("rs", (10,), np.float64, "do not fit"),  # float64's 8 bytes an item where roots carry 4
])
def test_malformed_array_encodings_are_refused(enc, shape, dtype, match):
    a = np.zeros(shape, dtype)
    body = messages.unpack_body(messages.encode("gather", JOB, 1, part=0, parts=1, ids=np.arange(3, dtype=np.int64),
                                                image_ids=np.zeros(3, np.int64),
                                                descriptors=np.zeros((3, 4), np.uint8)))
    body["ids"] = {"dtype": a.dtype.str, "shape": list(shape), "data": a.tobytes(), "enc": enc}
    with pytest.raises(messages.MessageError, match=match):
        messages.decode(messages.pack_body(body), job=JOB)
    body["ids"] = {"dtype": "<i8", "shape": [3], "data": np.zeros(3, np.int64).tobytes(), "extra": 1}
    with pytest.raises(messages.MessageError, match="is not an array"):
        messages.decode(messages.pack_body(body), job=JOB)

