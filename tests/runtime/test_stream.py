"""dqm stream: the image / changes messages, and the stream over a router on loopback (bad messages counted)."""
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
from runtime_helpers import start_dqm

import dqm
from dqm import io
from dqm.core.events import replay
from dqm.core.online import OnlineQuickMatch
from dqm.core.tree import canonical_labels
from dqm.distributed import keys, messages
from dqm.synthetic import sift_like

JOB = "stream-test"
DIM = 128


@pytest.fixture(scope="module")
def data():
    ds = sift_like(n_images=5, n_points=120, clutter_per_image=40, noise=0.3, seed=11)
    return ds.descriptors, ds.image_ids


def _image(i=3, n=5, dim=DIM, dtype=np.uint8, kp_rows=None, **kw):
    d = np.random.default_rng(i).integers(0, 255, size=(n, dim)).astype(dtype)
    kp = None if kp_rows is None else np.ones((kp_rows, 4), np.float32)
    return messages.image_message(JOB, 0, i, d, kp, **kw)


def _mutate(payload: bytes, **changes) -> bytes:
    body = messages.unpack_body(payload)
    body.update(changes)
    return msgpack.packb(body, use_bin_type=True)


def _array(a: np.ndarray) -> dict:
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


def _nan_image():
    d = np.ones((4, DIM), np.float32)
    d[2, 5] = np.nan
    return messages.image_message(JOB, 0, 1, d)


def _inf_keypoints():
    kp = np.ones((5, 4), np.float32)
    kp[0, 0] = np.inf
    return _mutate(_image(), keypoints=_array(kp))


BAD_IMAGES = [
    (lambda: b"\x00garbage\xff", "not valid msgpack"),
    (lambda: b"", "not valid msgpack"),
    (lambda: msgpack.packb([1, 2, 3]), "not a map"),
    (lambda: _mutate(_image(), v=messages.VERSION + 1), "schema version"),
    (lambda: _mutate(_image(), kind="picture"), "unknown message kind"),
    (lambda: messages.image_message("other-job", 0, 1, np.zeros((2, DIM), np.uint8)), "not this job"),
    (lambda: _nan_image(), "non-finite descriptor values"),
    (lambda: _mutate(_image(), descriptors=_array(np.full((2, DIM), np.inf, np.float32))),
     "non-finite descriptor values"),
    (lambda: _mutate(_image(), descriptors=_array(np.zeros((2, DIM), np.int32))), "expected |u1,<f4"),
    (lambda: _mutate(_image(), descriptors=_array(np.zeros((2, DIM), np.float64))), "expected |u1,<f4"),
    (lambda: _mutate(_image(), descriptors=_array(np.zeros((2, 4, 4), np.uint8))), "must be 2-D"),
    (lambda: _mutate(_image(), descriptors=_array(np.zeros((2, 0), np.uint8))), "no dimensions"),
    (lambda: _mutate(_image(), descriptors={"dtype": "|u1", "shape": [5, DIM], "data": b"\x00" * 7}),
     "do not fit shape"),
    (lambda: _mutate(_image(), descriptors={"dtype": "|u1", "shape": [1 << 41, DIM], "data": b""}),
     "bad shape"),
    (lambda: _image(kp_rows=3), "image.keypoints has 3 rows, descriptors has 5"),
    (lambda: _mutate(_image(), keypoints=_array(np.ones((5, 7), np.float32))), "2 to 4 columns"),
    (lambda: _inf_keypoints(), "non-finite keypoint"),
    (lambda: _mutate(_image(), image_id=-4), "negative image id"),
    (lambda: _mutate(_image(), image_id="4"), "image.image_id must be an integer"),
    (lambda: _mutate(_image(), image_id=True), "image.image_id must be an integer"),
    (lambda: _mutate(_image(), time=float("nan")), "image.time must be a finite number"),
    (lambda: _mutate(_image(), time=-1.0), "image.time is negative"),
    (lambda: _mutate(_image(), src=-1), "wrong sender"),
    (lambda: _mutate(_image(), seq=-1), "bad seq"),
    (lambda: msgpack.packb({k: v for k, v in messages.unpack_body(_image()).items() if k != "keypoints"}),
     "lacks field 'keypoints'"),
    (lambda: _mutate(_image(), name=7), "image.name must be a string"),
    (lambda: _image(name="a\nb"), "without control characters"),
    (lambda: _image(name="x" * (messages.MAX_NAME_CHARS + 1)), "at most 4096 characters"),
]


@pytest.mark.parametrize("make,reason", BAD_IMAGES, ids=[r for _, r in BAD_IMAGES])
def test_decode_rejects_malformed_image_messages(make, reason):
    with pytest.raises(messages.MessageError) as err:
        messages.decode(make(), job=JOB)
    assert reason in str(err.value), str(err.value)


def test_image_names_are_optional_and_travel():
    """A name goes through; a message of an older sender (no name field, same version) reads as name ""."""
    named = messages.decode(_image(name="/data/cam1/img 07.png"), job=JOB)
    assert named["name"] == "/data/cam1/img 07.png"
    old = msgpack.packb({k: v for k, v in messages.unpack_body(_image()).items() if k != "name"})
    assert "name" not in msgpack.unpackb(old, raw=False)
    assert messages.decode(old, job=JOB)["name"] == ""
    om = OnlineQuickMatch()
    cs = om.add(np.random.default_rng(0).integers(0, 255, (6, DIM)).astype(np.uint8), np.zeros(6, np.int64))
    raw = messages.changes_message(JOB, cs, "add", 0, sent=1.0, n_images=1, n_features=6, n_clusters=6,
                                   rejected=0, name="img 07.png")
    assert messages.decode(raw, job=JOB)["name"] == "img 07.png"
    old = msgpack.packb({k: v for k, v in messages.unpack_body(raw).items() if k != "name"})
    assert messages.decode(old, job=JOB)["name"] == ""
    with pytest.raises(messages.MessageError, match="changes.name must be at most"):
        messages.decode(_mutate(raw, name="a\x00b"), job=JOB)


def test_decode_checks_dimension_and_size_limits():
    assert messages.decode(_image(kp_rows=5), job=JOB, dim=DIM)["keypoints"].shape == (5, 4)
    assert len(messages.decode(_image(kp_rows=0), job=JOB)["keypoints"]) == 0
    with pytest.raises(messages.MessageError, match="descriptor dimension 64 is not the job's 128"):
        messages.decode(_image(dim=64), job=JOB, dim=DIM)
    with pytest.raises(messages.MessageError, match="exceeds the maximum"):
        messages.decode(_image(n=50), job=JOB, max_bytes=1000)


def test_changes_round_trip_and_rejects_malformed(data):
    X, ids = data
    om = OnlineQuickMatch()
    om.add(X[ids == 0], ids[ids == 0])
    cs = om.add(X[ids == 1], ids[ids == 1])
    raw = messages.changes_message(JOB, cs, "add", 1, sent=12.5, n_images=2, n_features=om.n_features,
                                   n_clusters=len(np.unique(om.cluster_ids)), rejected=3, seq=1)
    msg = messages.decode(raw, job=JOB)
    assert msg["kind"] == "changes" and msg["op"] == "add" and msg["image_id"] == 1 and msg["rejected"] == 3
    assert [e.to_dict() for e in messages.changes_events(msg)] == [e.to_dict() for e in cs.events]
    np.testing.assert_array_equal(msg["added"], cs.added)
    bad = [
        (dict(op="merge"), "changes.op"),
        (dict(event_kind=_array(np.full(len(msg["event_kind"]), 9, np.uint8))), "unknown kind"),
        (dict(new=_array(np.full(len(msg["new"]), 2, np.uint8))), "0 or 1"),
        (dict(cluster=_array(np.zeros(1, np.int64))), "rows"),
        (dict(size=_array(msg["size"] + 1)), "add up to"),
        (dict(keys=_array(-np.ones(len(msg["keys"]), np.int64))), "changes.keys below 0"),
        (dict(source=_array(np.full(len(msg["source"]), -2, np.int64))), "changes.source below -1"),
        (dict(n_features=-1), "negative changes.n_features"),
        (dict(stats={"time": "slow"}), "map of numbers"),
        (dict(image_id=-1), "negative image id"),
    ]
    for change, reason in bad:
        with pytest.raises(messages.MessageError) as err:
            messages.decode(_mutate(raw, **change), job=JOB)
        assert reason in str(err.value), (change, str(err.value))


def test_decode_raises_only_message_errors_on_mutated_images():
    """Random truncations, bit flips and field swaps: MessageError every time, nothing else."""
    rng = np.random.default_rng(0)
    good = _image(kp_rows=5, name="img.png")
    fields = ["v", "kind", "job", "src", "seq", "epoch", "image_id", "time", "descriptors", "keypoints", "name"]
    values = [None, -1, 2 ** 63, 1.5, "x", b"\x00", [], {}, {"dtype": "<f4", "shape": [3], "data": b"1"}, True]
    for trial in range(300):
        r = trial % 3
        if r == 0:
            raw = good[:int(rng.integers(0, len(good)))]
        elif r == 1:
            b = bytearray(good)
            for _ in range(3):
                b[int(rng.integers(0, len(b)))] ^= 1 << int(rng.integers(0, 8))
            raw = bytes(b)
        else:
            raw = _mutate(good, **{fields[int(rng.integers(len(fields)))]: values[int(rng.integers(len(values)))]})
        try:
            messages.decode(raw, job=JOB)
        except messages.MessageError:
            pass


# ---------------------------------------------------------------------- over a router
def _wait_token(session, key, deadline_s=30.0):
    from dqm.runtime.stream import wait_for_token

    assert wait_for_token(session, key, deadline_s), f"no liveliness token {key}"


def test_stream_rejects_counts_and_keeps_going(router, data, tmp_path):
    import zenoh

    from dqm.runtime.bus import open_client

    X, ids = data
    job, window = "stream-e2e", 3
    out = tmp_path / "clusters.npz"
    p = start_dqm(["stream", "--connect", router, "--job", job, "--window", str(window), "--images", "5",
                "--idle", "40", "--out", str(out), "--verbose"])
    session = open_client(router)
    got, lock = [], threading.Lock()

    def on_changes(sample):
        with lock:
            got.append(bytes(sample.payload.to_bytes()))

    sub = session.declare_subscriber(keys.stream_changes(job), on_changes)
    try:
        _wait_token(session, keys.alive_stream(job))
        put = lambda raw, camera=0: session.put(keys.camera_images(job, camera), raw,  # noqa: E731
                                                congestion_control=zenoh.CongestionControl.BLOCK)
        img = lambda i, **kw: messages.image_message(job, i % 2, i, X[ids == i], name=f"img{i}.png",  # noqa: E731
                                                     keypoints=np.c_[X[ids == i][:, :2], np.full((n(i), 2), i)]
                                                     .astype(np.float32), **kw)
        n = lambda i: int((ids == i).sum())  # noqa: E731
        nan = X[ids == 0].astype(np.float32)
        nan[1, 2] = np.nan
        bad = [
            b"\x00garbage\xff",
            messages.image_message(job, 0, 50, nan),
            _mutate(img(1), v=messages.VERSION + 1),
            img(1),  # again: a duplicate (accepted the first time)
            messages.image_message(job, 0, 51, X[ids == 2][:, :64]),
            messages.image_message("other-job", 0, 52, X[ids == 2]),
            messages.image_message(job, 0, 53, np.zeros((0, DIM), np.uint8)),
            messages.encode("finish", job, -1, clusters=1),
            messages.image_message(job, 1, 54, X[ids == 2]),  # camera 1's image on camera 0's key: forged
        ]
        # (message, the camera whose key it goes on): image i comes from camera i % 2
        plan = [(img(0), 0), (bad[0], 0), (img(1), 1), (bad[1], 0), (bad[2], 0), (bad[3], 1), (img(2), 0),
                (bad[4], 0), (bad[5], 0), (img(3), 1), (bad[6], 0), (bad[7], 0), (bad[8], 0), (img(4), 0)]
        for raw, camera in plan:
            put(raw, camera)
            time.sleep(0.05)
        stdout, stderr = p.communicate(timeout=60)
        t0 = time.monotonic()
        while time.monotonic() - t0 < 10:
            with lock:
                if len(got) >= 7:
                    break
            time.sleep(0.05)
    finally:
        sub.undeclare()
        session.close()
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 0, stderr
    assert "Traceback" not in stderr
    assert "stream (5 images accepted)" in stdout
    assert "rejected 9 messages" in stdout, stdout
    for reason in ("not valid msgpack", "non-finite descriptor values", "schema version", "was received before",
                   "descriptor dimension N is not the job's N", "not this job", "has no features",
                   "a finish message on the images key", "an image of camera N on the key"):
        assert reason in stdout, (reason, stdout)
    assert stdout.count("add image") == 5 and stdout.count("remove image") == 2
    msgs = sorted((messages.decode(raw, job=job) for raw in got), key=lambda m: m["seq"])
    assert [(m["op"], m["image_id"]) for m in msgs] == [
        ("add", 0), ("add", 1), ("add", 2), ("remove", 0), ("add", 3), ("remove", 1), ("add", 4)]
    assert [m["seq"] for m in msgs] == list(range(7))
    assert [m["name"] for m in msgs] == [f"img{i}.png" for i in (0, 1, 2, 0, 3, 1, 4)]
    assert msgs[-1]["rejected"] == 9 and msgs[-1]["n_images"] == window
    # the events, replayed over the previous assignment, give every next one; the last equals the file's clusters
    present = [2, 3, 4]
    cl = io.load_clusters(out)
    Xp = np.concatenate([X[ids == i] for i in present])
    idp = np.concatenate([ids[ids == i] for i in present])
    np.testing.assert_array_equal(cl["descriptors"], Xp)
    # the file numbers the present images 0..K-1 in arrival order (image_names row k names image k), and
    # keeps the stream's ids in its params; names and keypoints follow their images
    np.testing.assert_array_equal(cl["image_ids"], np.searchsorted(present, idp))
    assert cl["params"]["stream_image_ids"] == present
    assert [Path(n).name for n in cl["image_names"].tolist()] == [f"img{i}.png" for i in present]
    np.testing.assert_array_equal(cl["keypoints"][:, 2], idp)
    batch = dqm.quickmatch(Xp, idp, kernel="quadratic")
    np.testing.assert_array_equal(cl["labels"], batch.labels)
    assignment, sizes = {}, []
    for m in msgs:
        replay(assignment, messages.changes_events(m))
        sizes.append(len(assignment))
        assert len(assignment) == m["n_features"]
        assert len(set(assignment.values())) == m["n_clusters"]
    # every key present once in arrival order: the replayed clusters equal the batch clusters
    order = sorted(assignment)
    np.testing.assert_array_equal(canonical_labels(np.array([assignment[k] for k in order])), batch.labels)
    # and equal the online engine run over the same images here
    om = OnlineQuickMatch()
    ref = {}
    for m in msgs:
        cs = om.add(X[ids == m["image_id"]], ids[ids == m["image_id"]]) if m["op"] == "add" else om.remove(
            m["image_id"])
        replay(ref, cs.events)
    assert ref == assignment


def test_stream_stops_when_idle_and_on_sigterm(router, tmp_path):
    from dqm.runtime.bus import open_client

    p = start_dqm(["stream", "--connect", router, "--job", "stream-idle", "--idle", "1", "--out",
                str(tmp_path / "c.npz")])
    stdout, stderr = p.communicate(timeout=60)
    assert p.returncode == 0, stderr
    assert "stream (no message for 1 s): 0 images accepted" in stdout
    assert "not written" in stdout and not (tmp_path / "c.npz").exists()
    p = start_dqm(["stream", "--connect", router, "--job", "stream-term"])
    session = open_client(router)
    try:
        _wait_token(session, keys.alive_stream("stream-term"))
    finally:
        session.close()
    # a second stream under the same job id would split the cameras' images: refused in one line
    twin = subprocess.run([sys.executable, "-m", "dqm", "stream", "--connect", router, "--job", "stream-term"],
                          capture_output=True, text=True, timeout=60)
    assert twin.returncode == 2 and "the stream of job 'stream-term' is already running" in twin.stderr, twin.stderr
    assert twin.stderr.strip().count("\n") == 0
    p.terminate()
    stdout, stderr = p.communicate(timeout=30)
    assert p.returncode == 143, stderr
    assert "stream (terminated)" in stdout and "Traceback" not in stderr


def test_missing_router_and_bad_arguments_give_one_line(tmp_path):
    from dqm.runtime.launcher import free_port

    port = free_port()
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-m", "dqm", "stream", "--connect", f"tcp/127.0.0.1:{port}",
                        "--connect-timeout", "1"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    assert p.stderr.strip().count("\n") == 0, p.stderr
    assert f"no zenoh router reachable at tcp/127.0.0.1:{port}" in p.stderr
    assert "Traceback" not in p.stderr and time.monotonic() - t0 < 30
    for args, text in ((["--connect", "127.0.0.1:7447"], "not a zenoh endpoint"),
                       (["--connect", "tcp/127.0.0.1:1", "--job", "a/b"], "job id"),
                       (["--connect", "tcp/127.0.0.1:1", "--out", str(tmp_path / "c.txt")], "unknown format")):
        p = subprocess.run([sys.executable, "-m", "dqm", "stream", *args], capture_output=True, text=True,
                           timeout=60)
        assert p.returncode == 2 and text in p.stderr and "Traceback" not in p.stderr, p.stderr
        assert p.stderr.strip().count("\n") == 0
