"""What a user types that went wrong in issue 36, one test per defect: contradicting flags, values that
start with '-', a bad job id, a limit on features that did not hold, messages that misled, and the hloc
export of a distributed job's clusters."""
import subprocess
import sys
import time
import zipfile

import numpy as np
import pytest

from dqm import io, wording
from dqm.cli import main
from dqm.synthetic import sized


def one_line(capsys, argv, *needles, code=2):
    assert main(argv) == code, argv
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for needle in needles:
        assert needle in err[0], err[0]
    return err[0]


@pytest.fixture(scope="module")
def features(tmp_path_factory):
    path = tmp_path_factory.mktemp("errors") / "f.npz"
    ds = sized(600, seed=0)
    io.save_features(path, io.FeatureSet(ds.descriptors, ds.image_ids))
    return str(path)


@pytest.mark.parametrize("argv, first, second", [
    (["match", "{f}", "--out", "{o}", "--guided", "--no-guided"], "--guided", "--no-guided"),
    (["sfm", "photos", "--out", "{o}", "--no-triangulate", "--triangulate"], "--no-triangulate", "--triangulate"),
    (["run", "--cell-weights", "--no-cell-weights"], "--cell-weights", "--no-cell-weights"),
    (["stream", "--connect", "tcp/127.0.0.1:1", "--quiet", "--verbose"], "--quiet", "--verbose"),
])
def test_contradicting_flags_are_refused(tmp_path, capsys, features, argv, first, second):
    argv = [a.format(f=features, o=str(tmp_path / "o.npz")) for a in argv]
    one_line(capsys, argv, f"{first} and {second} contradict each other")
    assert list(tmp_path.iterdir()) == []


def test_a_value_that_starts_with_a_minus_is_taken_as_the_value(tmp_path, capsys):
    """--camera-params -1,1,2,3 used to need '='; now the focal length is what is refused."""
    c = tmp_path / "c.npz"
    assert main(["scene", str(tmp_path / "s"), "--images", "2", "--size", "120", "160"]) == 0
    assert main(["match", str(tmp_path / "s"), "--out", str(c), "--quiet", "--max-features", "80"]) == 0
    capsys.readouterr()
    one_line(capsys, ["export", "colmap", str(c), "--database", str(tmp_path / "d.db"), "--camera-params",
                      "-1,1,2,3"], "focal length")


def test_a_bad_job_id_is_refused_before_anything_starts(capsys):
    t = time.monotonic()
    one_line(capsys, ["run", "--agents", "2", "--job", "bad job/x"], "job id", "'bad job/x'")
    assert time.monotonic() - t < 5  # no router, agent or coordinator was started


def test_max_features_is_a_limit_per_image(tmp_path):
    assert main(["scene", str(tmp_path / "s"), "--images", "3", "--size", "240", "320", "--seed", "1"]) == 0
    for limit in (45, 78):  # OpenCV alone gives 46 and 82 on the first image
        out = tmp_path / f"f{limit}.npz"
        assert main(["extract", str(tmp_path / "s"), "--out", str(out), "--max-features", str(limit),
                     "--quiet"]) == 0
        per_image = np.bincount(io.load_features(out).image_ids)
        assert per_image.max() == limit and (per_image <= limit).all(), per_image  # OpenCV alone gave limit + 1


def test_durations_and_counts_read_right():
    assert wording.seconds(0.5) == "0.5 s" and wording.seconds(12) == "12 s" and wording.seconds(600) == "600 s"
    assert wording.count(1, "image") == "1 image" and wording.count(3, "image") == "3 images"
    assert wording.count(1, "agent process", "agent processes") == "1 agent process"
    assert wording.count(25_000, "feature") == "25,000 features"


def test_a_corrupt_npz_member_is_named(tmp_path, capsys, features):
    bad = tmp_path / "f.npz"
    raw = bytearray(open(features, "rb").read())
    with zipfile.ZipFile(features) as z:
        info = z.getinfo("descriptors.npy")
    start = info.header_offset + 30 + len(info.filename) + len(info.extra) + 200
    raw[start:start + 64] = bytes(64)  # damage the compressed data of one member
    bad.write_bytes(bytes(raw))
    line = one_line(capsys, ["match", str(bad), "--out", str(tmp_path / "c.npz")], "array 'descriptors'",
                    "damaged")
    assert "(error)" not in line


def test_a_file_that_is_not_a_database_gets_our_line_only(tmp_path):
    pytest.importorskip("pycolmap")
    bad = tmp_path / "x.db"
    bad.write_text("hello\n")
    p = subprocess.run([sys.executable, "-m", "dqm", "import", "colmap", str(bad), "--out", str(tmp_path / "f.npz")],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    assert p.stderr.strip().splitlines() == [f"dqm import: error: {bad}: not a COLMAP database (not an SQLite file)"]


def test_a_missing_pycolmap_is_named_for_the_command(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # import pycolmap raises ImportError
    assert main(["scene", str(tmp_path / "s"), "--images", "2", "--size", "120", "160"]) == 0
    capsys.readouterr()
    one_line(capsys, ["sfm", str(tmp_path / "s"), "--out", str(tmp_path / "m")], "dqm sfm (COLMAP's mapper) needs "
             "pycolmap")
    one_line(capsys, ["extract", str(tmp_path / "s"), "--out", str(tmp_path / "f.npz"), "--preset", "colmap"],
             "--preset colmap (COLMAP's SIFT) needs pycolmap")


def test_hloc_export_of_clusters_without_descriptors(tmp_path, capsys):
    """A dqm run / dqm coordinator CLUSTERS file has keypoints and image names but no descriptors."""
    h5py = pytest.importorskip("h5py")
    assert main(["scene", str(tmp_path / "s"), "--images", "3", "--size", "160", "200"]) == 0
    assert main(["match", str(tmp_path / "s"), "--out", str(tmp_path / "c.npz"), "--quiet",
                 "--max-features", "100"]) == 0
    c = dict(np.load(tmp_path / "c.npz"))
    del c["descriptors"]
    np.savez(tmp_path / "run.npz", **c)
    capsys.readouterr()
    assert main(["export", "hloc", str(tmp_path / "run.npz"), "--matches", str(tmp_path / "m.h5"), "--pairs",
                 str(tmp_path / "p.txt"), "--features", str(tmp_path / "feats.h5")]) == 0
    assert "keypoints only" in capsys.readouterr().out
    with h5py.File(tmp_path / "feats.h5", "r") as f:
        groups = [f[k] for k in f]
        assert len(groups) == 3 and all("keypoints" in g and "descriptors" not in g for g in groups)
        assert sum(len(g["keypoints"]) for g in groups) == len(c["labels"])


def test_connect_timeout_holds_against_a_listener_that_is_not_a_router():
    """A TCP port that accepts and never answers: zenoh's own 10 s open timeout used to hold the command."""
    import socket

    from dqm.runtime.bus import RouterUnreachable, open_client

    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)
        endpoint = f"tcp/127.0.0.1:{silent.getsockname()[1]}"
        t = time.monotonic()
        with pytest.raises(RouterUnreachable) as err:
            open_client(endpoint, deadline_s=1.0)
        took = time.monotonic() - t
    assert took < 3.0, f"--connect-timeout 1 took {took:.1f} s"
    assert "after 1 s" in str(err.value) and "is not a zenoh router" in str(err.value)
