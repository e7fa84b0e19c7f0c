"""What a new user met in issue 60 beyond lost outputs and stops: images that moved, databases read without a
trace and the reason a database cannot be read, arguments a command does not have, a missing --gt folder, a
truncated JPEG, the router's exit codes, the hints of --into-database and -v on every command."""
import signal
import subprocess
import sys

import numpy as np
import pytest
from runtime_helpers import stop_once_ready
from test_user_errors import one_line

from dqm import io
from dqm.cli import main
from dqm.runtime.launcher import free_port


@pytest.fixture(scope="module")
def matched(tmp_path_factory):
    """A scene of 3 images and its CLUSTERS file (absolute image names, keypoints)."""
    d = tmp_path_factory.mktemp("messages")
    assert main(["scene", str(d / "scene"), "--images", "3", "--size", "160", "200", "--seed", "4"]) == 0
    assert main(["match", str(d / "scene"), "--out", str(d / "c.npz"), "--quiet", "--max-features", "150"]) == 0
    return d


def test_plot_finds_images_that_moved_under_image_dir(matched, tmp_path, capsys):
    """The names in a CLUSTERS file are absolute; after the images moved, --image-dir finds them by file name (as
    dqm export colmap --image-dir does); without it, or with the wrong folder, one line says which was tried."""
    import shutil

    moved = tmp_path / "moved"
    shutil.copytree(matched / "scene", moved)
    c = io.load_clusters(matched / "c.npz")
    names = [str(moved / "gone" / p.split("/")[-1]) for p in c["image_names"].tolist()]  # where they were
    gone = tmp_path / "c.npz"
    io.write_clusters(gone, io.FeatureSet(c["descriptors"], c["image_ids"], keypoints=c["keypoints"],
                                          image_names=names), {"labels": c["labels"]}, {})
    assert main(["plot", "clusters", str(gone), "--out", str(tmp_path / "a.png"), "--image-dir", str(moved)]) == 0
    assert (tmp_path / "a.png").stat().st_size > 0
    capsys.readouterr()
    one_line(capsys, ["plot", "clusters", str(gone), "--out", str(tmp_path / "b.png")], "not found",
             "use --image-dir")
    one_line(capsys, ["plot", "clusters", str(gone), "--out", str(tmp_path / "b.png"), "--image-dir",
                      str(tmp_path)], "not found nor under --image-dir")


@pytest.fixture(scope="module")
def colmap_db(tmp_path_factory, matched):
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is not installed (pip install 'dqm[colmap]')")
    d = tmp_path_factory.mktemp("db")
    pycolmap.extract_features(str(d / "colmap.db"), str(matched / "scene"))
    return d / "colmap.db"


def test_reading_a_database_leaves_nothing_beside_it_and_says_why_it_cannot(colmap_db, tmp_path, capsys):
    """COLMAP's databases are in WAL mode: a read-only reader left -shm / -wal beside them, and a database pycolmap
    could not open was 'not a COLMAP database (RuntimeError)'."""
    import shutil

    db = tmp_path / "colmap.db"
    shutil.copyfile(colmap_db, db)
    assert main(["-v", "import", "colmap", str(db), "--out", str(tmp_path / "f.npz")]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["colmap.db", "f.npz"]
    assert capsys.readouterr().err.startswith("import colmap: reading the features of")  # -v said nothing
    cut = tmp_path / "cut.db"
    cut.write_bytes(db.read_bytes()[:20000])
    one_line(capsys, ["import", "colmap", str(cut), "--out", str(tmp_path / "g.npz")],
             "cannot be read as a COLMAP database: it is truncated (20,000 bytes of the")


def test_an_option_another_command_has_is_refused_by_this_command(capsys):
    """`dqm run --max-memory 1M` printed the top-level usage ('dqm: error: unrecognized arguments')."""
    with pytest.raises(SystemExit) as exc:
        main(["run", "--agents", "2", "--max-memory", "1M"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "usage: dqm run" in err and "dqm run: error: unrecognized arguments: --max-memory 1M" in err


def test_a_missing_ground_truth_folder_is_called_missing(tmp_path, capsys):
    pytest.importorskip("pycolmap")
    photos = tmp_path / "photos"
    assert main(["scene", str(photos), "--images", "2", "--size", "120", "160"]) == 0
    capsys.readouterr()
    one_line(capsys, ["sfm", str(photos), "--out", str(tmp_path / "m"), "--gt", str(tmp_path / "nope")],
             "--gt", "nope: no such folder")


def test_a_truncated_jpeg_is_named(tmp_path):
    """libjpeg decodes a truncated file with a warning that names no file ('Premature end of JPEG file')."""
    import cv2

    rng = np.random.default_rng(0)
    for k in range(2):
        img = cv2.GaussianBlur(rng.integers(0, 255, (240, 320), dtype=np.uint8), (0, 0), 2)
        cv2.imwrite(str(tmp_path / f"{k}.jpg"), img)
    whole = (tmp_path / "1.jpg").read_bytes()
    (tmp_path / "1.jpg").write_bytes(whole[:len(whole) // 2])
    p = subprocess.run([sys.executable, "-m", "dqm", "extract", str(tmp_path), "--out", str(tmp_path / "f.npz"),
                        "--quiet"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert f"warning: {tmp_path / '1.jpg'} is a truncated JPEG file" in p.stderr
    assert f"{tmp_path / '0.jpg'} is a truncated" not in p.stderr


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_the_router_stops_with_the_codes_of_every_command(tmp_path, sig, code):
    log = tmp_path / "router.log"
    p, took = stop_once_ready(["router", "--listen", f"tcp/127.0.0.1:{free_port()}"], log, "listening on", sig)
    assert p.returncode == code and took < 2.0, log.read_text()
    assert log.read_text().strip().splitlines()[-1] == \
        f"[router] {'interrupted' if sig == signal.SIGINT else 'terminated'}"


def test_every_command_says_what_it_does_with_v(matched, tmp_path, capsys):
    """-v said nothing for split, export, plot, import and scene."""
    f = tmp_path / "f.npz"
    c = io.load_clusters(matched / "c.npz")
    io.save_features(f, io.FeatureSet(c["descriptors"], c["image_ids"]))
    runs = {
        "split": ["split", str(f), "--agents", "2", "--out", str(tmp_path / "split")],
        "scene": ["scene", str(tmp_path / "s"), "--images", "2", "--size", "100", "120"],
        "plot": ["plot", "sizes", str(matched / "c.npz"), "--out", str(tmp_path / "sizes.png")],
        "export": ["export", "hloc", str(matched / "c.npz"), "--matches", str(tmp_path / "m.h5"), "--pairs",
                   str(tmp_path / "pairs.txt")],
    }
    for name, argv in runs.items():
        if name == "export":
            pytest.importorskip("h5py")
        capsys.readouterr()
        assert main(["-v", *argv]) == 0, name
        assert capsys.readouterr().err.split()[0].rstrip(":") == name, name


def test_a_stopped_evaluation_leaves_no_figure_that_blocks_its_rerun(tmp_path, capsys, monkeypatch):
    """An interrupted `dqm evaluate` left pr_*.png, and the rerun of the same command was refused (its --out-dir
    check refuses pr_*.png): a stop now removes the figures of the evaluation it did not finish."""
    from dqm import benchmark

    real, calls = benchmark.evaluate, []

    def stop_at_the_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(benchmark, "evaluate", stop_at_the_second)
    argv = ["evaluate", "scene:1", "scene:2", "--out-dir", str(tmp_path / "ev"), "--quiet", "--methods", "quickmatch"]
    assert main(argv) == 130
    assert capsys.readouterr().err.strip() == "dqm evaluate: interrupted"
    assert not [p for p in (tmp_path / "ev").glob("*")]
    monkeypatch.setattr(benchmark, "evaluate", real)
    assert main(argv) == 0
    assert sorted(p.name for p in (tmp_path / "ev").glob("pr_*.png")) == ["pr_scene-1.png", "pr_scene-2.png"]
