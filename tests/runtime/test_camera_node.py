"""dqm camera: camera nodes feed folders of images to dqm stream over a router on loopback."""
import argparse
import itertools
import re
import signal
import subprocess
import sys
import threading
import time

import cv2
import numpy as np
import pytest
from runtime_helpers import start_dqm

import dqm
from dqm import io
from dqm.cli import main as cli_main
from dqm.commands import camera
from dqm.distributed import keys, messages
from dqm.runtime.stream import IMAGES_PER_CAMERA, camera_image_id, split_image_id
from dqm.vision import scenes
from dqm.vision.features import extract

MAX_FEATURES = 150


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    """Five 320x240 views of one textured plane (about 100-150 SIFT features each at --max-features 150)."""
    d = tmp_path_factory.mktemp("views")
    for k, im in enumerate(scenes.generate_scene(5, (240, 320), seed=3).images):
        cv2.imwrite(str(d / f"view{k}.png"), im)
    return d


def _camera(*args, endpoint, job):
    return start_dqm(["camera", *map(str, args), "--connect", endpoint, "--job", job,
                      "--max-features", str(MAX_FEATURES)])


class Listener:
    """Collects the decoded ``changes`` messages of a job (a zenoh client of the router)."""

    def __init__(self, endpoint, job):
        from dqm.runtime.bus import open_client

        self.job, self.raw, self.lock = job, [], threading.Lock()
        self.session = open_client(endpoint)
        self.sub = self.session.declare_subscriber(keys.stream_changes(job), self._on)

    def _on(self, sample):
        with self.lock:
            self.raw.append(bytes(sample.payload.to_bytes()))

    def messages(self):
        with self.lock:
            return sorted((messages.decode(r, job=self.job) for r in self.raw), key=lambda m: m["seq"])

    def wait_for(self, test, deadline_s=30.0):
        t0 = time.monotonic()
        while time.monotonic() - t0 < deadline_s:
            if test(self.messages()):
                return
            time.sleep(0.05)
        raise AssertionError(f"not seen within {deadline_s} s: {[(m['op'], m['image_id']) for m in self.messages()]}")

    def close(self):
        self.sub.undeclare()
        self.session.close()


def _finish(*procs, timeout=60):
    out = []
    for p in procs:
        try:
            out.append(p.communicate(timeout=timeout))
        finally:
            if p.poll() is None:
                p.kill()
                p.wait()
    return out


def test_image_ids_are_namespaced_by_camera():
    assert camera_image_id(0, 5) == 5 and camera_image_id(2, 17) == 2_000_000_017
    assert split_image_id(camera_image_id(7, 123)) == (7, 123)
    ids = {camera_image_id(c, k) for c in range(4) for k in (0, 1, IMAGES_PER_CAMERA - 1)}
    assert len(ids) == 12 and max(ids) < 2 ** 63
    for c, k in ((-1, 0), (0, -1), (0, IMAGES_PER_CAMERA), (2 ** 31, 0)):
        with pytest.raises(dqm.InputError):
            camera_image_id(c, k)


def test_two_cameras_feed_one_stream_whose_result_plots(router, views, tmp_path):
    """Camera 0 sends three views (a glob), camera 1 two views in a loop (--limit 4, --first-index 10): the
    stream gets every image under a distinct id with its name, and its CLUSTERS file is batch QuickMatch of
    the same SIFT, with image_names and keypoints that dqm plot draws."""
    job, out = "cam-e2e", tmp_path / "clusters.npz"
    stream = start_dqm(["stream", "--connect", router, "--job", job, "--images", "7", "--idle", "60",
                                 "--out", str(out)])
    listener = Listener(router, job)
    try:
        cam0 = _camera(views / "view[012].png", "--camera", 0, "--rate", 10, endpoint=router, job=job)
        cam1 = _camera(views / "view3.png", views / "view4.png", "--camera", 1, "--rate", 5, "--loop", "--limit", 4,
                       "--first-index", 10, endpoint=router, job=job)
        (o0, e0), (o1, e1), (_, es) = _finish(cam0, cam1, stream)
        listener.wait_for(lambda ms: len(ms) == 7)
        msgs = listener.messages()
    finally:
        listener.close()
    assert (cam0.returncode, cam1.returncode, stream.returncode) == (0, 0, 0), (e0, e1, es)
    assert e0 == e1 == "", (e0, e1)  # piped: no progress, no log
    assert "camera 0 (done): put 3 images (ids 0..2)" in o0
    assert "camera 1 (done): put 4 images (ids 1000000010..1000000013)" in o1 and "0 behind their slot" in o1
    arrival = [m["image_id"] for m in msgs]
    assert [m["op"] for m in msgs] == ["add"] * 7
    assert sorted(arrival) == [0, 1, 2] + [IMAGES_PER_CAMERA + k for k in range(10, 14)]
    path = {i: str((views / f"view{i}.png").resolve()) for i in range(5)}
    sent_view = {0: 0, 1: 1, 2: 2, IMAGES_PER_CAMERA + 10: 3, IMAGES_PER_CAMERA + 11: 4,
                 IMAGES_PER_CAMERA + 12: 3, IMAGES_PER_CAMERA + 13: 4}
    assert [m["name"] for m in msgs] == [path[sent_view[i]] for i in arrival]
    # camera 1 put its images 1/rate = 0.2 s apart (the sender's clock, echoed in the change sets)
    t1 = [m["time"] for m in msgs if m["image_id"] >= IMAGES_PER_CAMERA]
    assert all(b - a >= 0.18 for a, b in itertools.pairwise(t1)), t1
    # the stream's file: image k is the k-th arrival; descriptors, keypoints and clusters as computed here
    cl = io.load_clusters(out)
    feats = {v: extract(views / f"view{v}.png", max_features=MAX_FEATURES) for v in range(5)}
    X = np.concatenate([feats[sent_view[i]].descriptors for i in arrival])
    file_ids = np.concatenate([np.full(len(feats[sent_view[i]]), k) for k, i in enumerate(arrival)])
    np.testing.assert_array_equal(cl["descriptors"], X)
    np.testing.assert_array_equal(cl["image_ids"], file_ids)
    np.testing.assert_array_equal(cl["keypoints"], np.concatenate([feats[sent_view[i]].keypoints for i in arrival]))
    assert cl["image_names"].tolist() == [path[sent_view[i]] for i in arrival]
    assert cl["params"]["stream_image_ids"] == arrival
    batch = dqm.quickmatch(X, file_ids, kernel="quadratic")
    np.testing.assert_array_equal(cl["labels"], batch.labels)
    # views 3 and 4 were sent twice: the second copies match the first ones feature for feature
    assert batch.n_clusters < len(X)
    assert cli_main(["plot", "clusters", str(out), "--out", str(tmp_path / "clusters.png")]) == 0
    assert cli_main(["plot", "pair", str(out), "--images", "0", "1", "--out", str(tmp_path / "pair.png")]) == 0
    assert (tmp_path / "clusters.png").stat().st_size > 0 and (tmp_path / "pair.png").stat().st_size > 0


def test_frames_names_loop_and_images_without_features(views, tmp_path):
    blank, broken = tmp_path / "blank.png", tmp_path / "broken.png"
    cv2.imwrite(str(blank), np.full((64, 64), 128, np.uint8))  # no SIFT feature: not sent
    broken.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)  # a PNG header, then nothing decodable
    paths = [views / "view0.png", blank, broken, views / "view1.png"]
    ref = [extract(p, max_features=MAX_FEATURES) for p in (paths[0], paths[3])]
    for names, expected in (("path", [str(paths[0].resolve()), str(paths[3].resolve())]),
                            ("file", ["view0.png", "view1.png"]), ("none", ["", ""])):
        args = argparse.Namespace(preset="rootsift", max_features=MAX_FEATURES, skip_bad_images=True, loop=False,
                                  names=names)
        skipped, empty = [], []
        got = list(camera.frames(paths, args, skipped, empty))
        assert [f.name for f in got] == expected
        assert skipped == [str(broken)] and empty == [str(blank)]
        for f, r in zip(got, ref):
            np.testing.assert_array_equal(f.descriptors, r.descriptors)
            np.testing.assert_array_equal(f.keypoints, r.keypoints)
    args.loop = True  # the images again and again, SIFT once
    looped = list(zip(range(5), camera.frames(paths, args, [], [])))
    assert [f.descriptors is looped[k % 2][1].descriptors for k, f in looped] == [True] * 5
    args.skip_bad_images = False
    with pytest.raises(dqm.InputError, match="cannot read image"):
        list(camera.frames(paths, args, [], []))
    # a loop over images of which none has a feature ends instead of spinning
    assert list(camera.frames([blank], args, [], [])) == []


def test_bad_input_gives_one_line_before_any_work(views, tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    (tmp_path / "text.png").write_text("not an image")
    nowhere = "tcp/127.0.0.1:1"  # nothing listens: these are refused before any connection
    cases = [
        (["--rate", "0"], "--rate must be above 0, got 0"),
        (["--rate", "-2"], "--rate must be above 0"),
        (["--rate", "fast"], "--rate must be a number, got 'fast'"),
        (["--rate", "inf"], "--rate must be above 0"),
        (["--rate", "nan"], "--rate must be above 0"),
        (["--camera", "-1"], "--camera must be at least 0 and at most 2147483647, got -1"),
        (["--camera", "1.5"], "--camera must be a whole number"),
        (["--limit", "0"], "--limit must be at least 1"),
        (["--wait", "0"], "--wait must be above 0"),
        (["--first-index", str(IMAGES_PER_CAMERA - 2)], "leaves fewer than 5 image numbers"),
        (["--max-features", "-3"], "max_features must be >= 0"),
        (["--job", "a/b"], "job id"),
        (["--tls-ca", "ca.pem"], "mutual TLS needs all of"),
    ]
    for extra, text in cases:
        assert cli_main(["camera", str(views), "--connect", nowhere, *extra]) == 2, extra
        err = capsys.readouterr().err
        assert text in err and err.count("\n") == 1 and err.startswith("dqm camera: error:"), (extra, err)
    for inputs, text in (([tmp_path / "empty"], "no image files"), ([tmp_path / "nope.png"], "input not found"),
                         ([views / "*.jpg"], "no image files match"),
                         ([views / "view0.png", tmp_path / "text.png"], "cannot read image(s)")):
        assert cli_main(["camera", *map(str, inputs), "--connect", nowhere]) == 2
        err = capsys.readouterr().err
        assert text in err and err.count("\n") == 1, (inputs, err)
    assert cli_main(["camera", str(views), "--connect", "127.0.0.1:7447"]) == 2
    assert "not a zenoh endpoint" in capsys.readouterr().err
    # no router: one line after --connect-timeout
    from dqm.runtime.launcher import free_port

    port = free_port()
    p = subprocess.run([sys.executable, "-m", "dqm", "camera", str(views), "--connect", f"tcp/127.0.0.1:{port}",
                        "--connect-timeout", "1"], capture_output=True, text=True, timeout=60, check=False)
    assert p.returncode == 2 and p.stderr.count("\n") == 1, p.stderr
    assert f"no zenoh router reachable at tcp/127.0.0.1:{port}" in p.stderr and "Traceback" not in p.stderr


def test_no_stream_and_a_stream_that_goes_away(router, views):
    p = _camera(views, "--wait", 1, endpoint=router, job="cam-nobody")
    (_, err), = _finish(p)
    assert p.returncode == 2 and err.count("\n") == 1, err
    assert "no dqm stream of job 'cam-nobody'" in err and "Traceback" not in err
    # the stream stops after two images; the looping camera notices its token gone and leaves (exit 1)
    job = "cam-gone"
    stream = start_dqm(["stream", "--connect", router, "--job", job, "--images", "2", "--idle", "60"])
    cam = _camera(views, "--loop", "--rate", 10, "--wait", 1, endpoint=router, job=job)
    (o, e), (so, se) = _finish(cam, stream)
    assert stream.returncode == 0 and "stream (2 images accepted)" in so, se
    assert cam.returncode == 1, e
    assert e.count("\n") == 1 and "went away and did not come back within 1 s" in e and "Traceback" not in e
    assert "camera 0 (stream lost): put" in o


@pytest.mark.parametrize("sig,code,why", [(signal.SIGTERM, 143, "terminated"), (signal.SIGINT, 130, "interrupted")])
def test_camera_leaves_cleanly_on_signals(router, views, sig, code, why):
    job = f"cam-{why}"
    stream = start_dqm(["stream", "--connect", router, "--job", job, "--idle", "60"])
    listener = Listener(router, job)
    cam = None
    try:
        cam = _camera(views, "--loop", "--rate", 4, "--camera", 5, endpoint=router, job=job)
        listener.wait_for(lambda ms: len(ms) >= 2)
        cam.send_signal(sig)
        (o, e), = _finish(cam, timeout=30)
        stream.terminate()
        (_, se), = _finish(stream, timeout=30)
        n = int(re.search(r"put (\d+) images", o).group(1))
        listener.wait_for(lambda ms: len(ms) == n, 10)
    finally:
        listener.close()
        for p in (cam, stream):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
    assert cam.returncode == code, e
    assert "Traceback" not in e and "Traceback" not in se
    assert f"camera 5 ({why}): put" in o
    # every image it put reached the stream, under camera 5's ids
    assert [m["image_id"] for m in listener.messages()] == [camera_image_id(5, k) for k in range(n)]
