"""dqm sfm end to end on a generated 3-D scene with known cameras: the model, its cameras against the
ground truth (--gt, both formats), the same model bit for bit on a second run, scripts/bench_sfm.py
(small, on a generated scene), and the shared photos' ground-truth cameras."""
import glob
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from dqm.cli import main
from dqm.io import load_clusters

pytest.importorskip("pycolmap", reason="pycolmap is not installed (pip install 'dqm[colmap]')")
ROOT = Path(__file__).resolve().parents[2]


def write_strecha(scene, folder: Path) -> Path:
    """The scene's cameras as Strecha camera files (K, 0 0 0, R camera-to-world, centre, size)."""
    folder.mkdir()
    h, w = scene.size
    for k in range(len(scene)):
        R, t = np.asarray(scene.R[k]), np.asarray(scene.t[k])
        rows = [*scene.K.tolist(), [0, 0, 0], *R.T.tolist(), (-R.T @ t).tolist(), [w, h]]
        (folder / f"img{k + 1}.png.camera").write_text("\n".join(" ".join(f"{v:.15g}" for v in r) for r in rows))
    return folder


def test_dqm_sfm_cameras_against_ground_truth_and_the_same_model_twice(tmp_path, capsys):
    from generators.scenes3d import generate_scene3d

    from dqm import io

    scene = generate_scene3d(seed=0, n_images=6)
    images = scene.save(tmp_path / "img")
    gt = write_strecha(scene, tmp_path / "gt")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    assert main(["sfm", str(images), "--out", str(tmp_path / "full"), "--quiet"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert (tmp_path / "full" / "keep.txt").read_text() == "mine"

    assert main(["sfm", str(images), "--out", str(tmp_path / "m1"), "--gt", str(gt), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "6 of 6 images registered" in out and "guided growth" not in out  # plain QuickMatch by default
    assert "SIFT preset budget (auto: 6 images, budget below 30)" in out  # a small scene: COLMAP's feature budget
    assert "cameras against ground truth: 6 of 6 registered" in out
    for name in ("clusters.npz", "database.db", "model.png", "tracks.csv", "sparse/0", "sfm.json"):
        assert (tmp_path / "m1" / name).exists(), name
    report = json.loads((tmp_path / "m1" / "sfm.json").read_text())
    assert report["options"]["preset"] == "budget" and report["model"]["registered"] == 6
    assert set(report["times"]) == {"extract", "match", "export", "map", "triangulate", "total"}
    # the generated cameras are recovered: pairwise pose errors mostly well under 1 degree (AUC@1 0.83 measured)
    assert report["poses"]["median_rotation_deg"] < 2.0 and report["poses"]["auc"]["1"] > 0.6
    assert "guided" not in io.load_clusters(tmp_path / "m1" / "clusters.npz")["params"] or \
        io.load_clusters(tmp_path / "m1" / "clusters.npz")["params"]["guided"] is False

    # a second run is the same model bit for bit: against the first as ground truth (a COLMAP model) every
    # pairwise error is 0, and the model files are byte-identical
    assert main(["sfm", str(images), "--out", str(tmp_path / "m2"), "--gt", str(tmp_path / "m1" / "sparse" / "0"),
                 "--quiet"]) == 0
    line = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("cameras against")][0]
    assert re.search(r"AUC@1° 1\.000, AUC@2° 1\.000, AUC@5° 1\.000", line), line
    for name in ("images.bin", "points3D.bin", "cameras.bin"):
        assert (tmp_path / "m1/sparse/0" / name).read_bytes() == (tmp_path / "m2/sparse/0" / name).read_bytes(), name


def test_dqm_sfm_starts_from_a_clusters_file(tmp_path, capsys, monkeypatch):
    """--clusters FILE: a run's clusters.npz (or dqm match's on images) goes to the export, the mapper and the last
    stage with no extraction or matching; from a dqm sfm run's own file the model is the same bit for bit, and a
    run stopped after its clusters were written says how to go on from them. The options of the extraction and
    the matching, images beside the file, a file whose images are gone and clusters with two features of one
    image are refused in one line before any work."""
    from generators.scenes3d import generate_scene3d

    from dqm import io
    from dqm.vision import sfm

    images = generate_scene3d(seed=1, n_images=5, width=480, height=360).save(tmp_path / "img")
    assert main(["sfm", str(images), "--out", str(tmp_path / "m1"), "--quiet"]) == 0
    made = tmp_path / "m1" / "clusters.npz"
    assert io.load_clusters(made)["params"]["preset"] == "budget"  # the SIFT choice is recorded
    capsys.readouterr()
    assert main(["sfm", "--clusters", str(made), "--out", str(tmp_path / "m2"), "--quiet", "--threads", "1"]) == 0
    out = capsys.readouterr().out
    assert f"features and clusters of {made}:" in out and "grown" not in out
    report = json.loads((tmp_path / "m2" / "sfm.json").read_text())
    assert set(report["times"]) == {"export", "map", "triangulate", "total"}  # nothing extracted or matched
    assert report["options"]["clusters"] == str(made) and report["options"]["preset"] == "budget"
    assert (tmp_path / "m2" / "clusters.npz").read_bytes() == made.read_bytes()
    assert (tmp_path / "m2" / "tracks.csv").read_bytes() == (tmp_path / "m1" / "tracks.csv").read_bytes()
    for name in ("images.bin", "points3D.bin", "cameras.bin"):
        assert (tmp_path / "m1/sparse/0" / name).read_bytes() == (tmp_path / "m2/sparse/0" / name).read_bytes(), name

    def stopped(*args, **kwargs):  # Ctrl-C while the mapper runs
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(sfm, "reconstruct", stopped)
        assert main(["sfm", str(images), "--out", str(tmp_path / "stopped"), "--quiet"]) == 130
    kept = tmp_path / "stopped" / "clusters.npz"
    assert f"note: {kept} holds the features and the clusters: dqm sfm --clusters {kept} --out NEW_DIR goes on " \
           "from them" in capsys.readouterr().err
    assert main(["sfm", "--clusters", str(kept), "--out", str(tmp_path / "went-on"), "--quiet"]) == 0
    assert (tmp_path / "m1/sparse/0/points3D.bin").read_bytes() == \
        (tmp_path / "went-on/sparse/0/points3D.bin").read_bytes()

    # dqm match's file (grown by geometry, its default on images) is taken as it is, and said so
    assert main(["match", str(images), "--out", str(tmp_path / "c.npz"), "--quiet"]) == 0
    assert io.load_clusters(tmp_path / "c.npz")["params"]["preset"] == "sfm"
    assert main(["sfm", "--clusters", str(tmp_path / "c.npz"), "--out", str(tmp_path / "m3"), "--quiet"]) == 0
    assert "grown by geometry" in capsys.readouterr().out
    assert json.loads((tmp_path / "m3" / "sfm.json").read_text())["options"]["guided"] is True

    c = dict(np.load(made))
    both = c["labels"].copy()
    first_two = np.flatnonzero(c["image_ids"] == 0)[:2]
    both[first_two[1]] = both[first_two[0]]
    np.savez(tmp_path / "twice.npz", **dict(c, labels=both))
    np.savez(tmp_path / "moved.npz", **dict(c, image_names=np.array([f"/nowhere/{k}.png" for k in range(5)])))
    for extra, says in [([str(images)], "give images or --clusters, not both"),
                        (["--rho", "0.8"], "--rho is a choice of the extraction or the matching"),
                        (["--preset", "sfm"], "--preset is a choice of the extraction or the matching")]:
        assert main(["sfm", "--clusters", str(made), "--out", str(tmp_path / "no"), *extra]) == 2
        assert says in capsys.readouterr().err
    assert main(["sfm", "--clusters", str(tmp_path / "twice.npz"), "--out", str(tmp_path / "no")]) == 2
    assert f"cluster {both[first_two[0]]} holds two features of image " in capsys.readouterr().err  # C2, as export
    assert main(["sfm", "--clusters", str(tmp_path / "moved.npz"), "--out", str(tmp_path / "no")]) == 2
    assert "names image /nowhere/0.png, which is not there (--image-dir: where it is now)" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()

    # images moved since (another host's paths): --image-dir finds them by name, and the model is the same
    shutil.copytree(images, tmp_path / "now")
    old = [f"/elsewhere/{Path(str(name)).name}" for name in c["image_names"]]
    np.savez(tmp_path / "elsewhere.npz", **dict(c, image_names=np.array(old)))
    assert main(["sfm", "--clusters", str(tmp_path / "elsewhere.npz"), "--image-dir", str(tmp_path / "now"),
                 "--out", str(tmp_path / "m4"), "--quiet"]) == 0
    assert (tmp_path / "m1/sparse/0/points3D.bin").read_bytes() == (tmp_path / "m4/sparse/0/points3D.bin").read_bytes()
    two = [f"/a/{Path(old[0]).name}", f"/b/{Path(old[0]).name}", *old[2:]]  # one file found for two images
    np.savez(tmp_path / "two.npz", **dict(c, image_names=np.array(two)))
    assert main(["sfm", "--clusters", str(tmp_path / "two.npz"), "--image-dir", str(tmp_path / "now"),
                 "--out", str(tmp_path / "no")]) == 2
    assert f"images {two[0]} and {two[1]} are both found as " in capsys.readouterr().err


def test_dqm_sfm_maps_a_distributed_jobs_clusters(tmp_path, capsys):
    """A distributed job's CLUSTERS file (dqm run: the descriptors stay with the agents) into dqm sfm --clusters:
    with --features, the FEATURES file the job ran on, the last stage gets their descriptors; with
    --no-triangulate the mapper's model alone; with neither, one line says so. A FEATURES file of other
    features is refused."""
    from generators.scenes3d import generate_scene3d

    images = generate_scene3d(seed=1, n_images=5, width=480, height=360).save(tmp_path / "img")
    features, job = tmp_path / "f.npz", tmp_path / "job.npz"
    assert main(["extract", str(images), "--out", str(features), "--preset", "budget"]) == 0
    assert main(["run", "--agents", "2", "--features", str(features), "--out", str(job)]) == 0
    assert "descriptors" not in load_clusters(job)
    capsys.readouterr()
    assert main(["sfm", "--clusters", str(job), "--out", str(tmp_path / "no")]) == 2
    assert "has no descriptors (a distributed job's file" in capsys.readouterr().err
    assert main(["sfm", "--clusters", str(job), "--features", str(features), "--out", str(tmp_path / "m"),
                 "--quiet"]) == 0
    report = json.loads((tmp_path / "m" / "sfm.json").read_text())
    assert report["model"]["registered"] == 5 and report["model"]["points"] > report["model_before_triangulation"][
        "points"] > 0  # the last stage matched the FEATURES' descriptors
    assert main(["sfm", "--clusters", str(job), "--no-triangulate", "--out", str(tmp_path / "bare"), "--quiet"]) == 0
    bare = json.loads((tmp_path / "bare" / "sfm.json").read_text())
    assert bare["model"] == report["model_before_triangulation"] and "triangulate" not in bare["times"]
    other = tmp_path / "other.npz"
    assert main(["extract", str(images), "--out", str(other), "--preset", "sfm"]) == 0
    capsys.readouterr()
    assert main(["sfm", "--clusters", str(job), "--features", str(other), "--out", str(tmp_path / "no")]) == 2
    assert f"--features {other}: " in capsys.readouterr().err and not (tmp_path / "no").exists()

    # the agents' files as dqm split cut them (on several hosts: copied back), with their feature ids: the same model
    assert main(["split", str(features), "--agents", "2", "--out", str(tmp_path / "s")]) == 0
    parts = [str(tmp_path / "s" / f"agent{a}.npz") for a in range(2)]
    assert main(["sfm", "--clusters", str(job), "--features", *parts, "--out", str(tmp_path / "m2"), "--quiet"]) == 0
    assert (tmp_path / "m/sparse/0/points3D.bin").read_bytes() == (tmp_path / "m2/sparse/0/points3D.bin").read_bytes()
    capsys.readouterr()
    for given, says in [([parts[0]], f"of --clusters {job} is not there"),
                        ([parts[0], parts[0]], "is there twice")]:
        assert main(["sfm", "--clusters", str(job), "--features", *given, "--out", str(tmp_path / "no")]) == 2
        assert says in capsys.readouterr().err and not (tmp_path / "no").exists()


def test_dqm_sfm_maps_a_job_of_robots_own_files(tmp_path, capsys):
    """Robots that each extracted their own photos (FEATURES files without feature ids, each numbering its own
    images 0, 1, ...) ran a job on two agents (real processes over zenoh): its CLUSTERS file numbers their
    features (agent << 32) + row, so dqm sfm --features takes each file as AGENT=FILE, and maps every photo
    with the last stage matching their descriptors. A file without ids given bare, or under the other agent's
    number, is refused."""
    pytest.importorskip("zenoh")
    from generators.scenes3d import generate_scene3d

    from dqm.distributed import DQMConfig
    from dqm.runtime.launcher import Processes, finish_job, free_port, start_job
    from dqm.runtime.multihost import start_router

    images = generate_scene3d(seed=1, n_images=5, width=480, height=360).save(tmp_path / "img")
    robots = []
    for r, ks in enumerate([(1, 3, 5), (2, 4)]):
        (tmp_path / f"r{r}").mkdir()
        for k in ks:
            shutil.copy(images / f"img{k}.png", tmp_path / f"r{r}" / f"img{k}.png")
        robots.append(tmp_path / f"robot{r}.npz")
        assert main(["extract", str(tmp_path / f"r{r}"), "--out", str(robots[-1]), "--preset", "budget",
                     "--quiet"]) == 0
    job = tmp_path / "job.npz"
    port, procs = free_port(), Processes()
    try:
        start_router(procs, [f"tcp/127.0.0.1:{port}"], tmp_path, ("127.0.0.1", port))
        started = start_job(procs, DQMConfig(agents=2, seed=1, job="robots-sfm"), robots, tmp_path,
                            connect=lambda a: f"tcp/127.0.0.1:{port}", clusters=job)
        assert finish_job(started, 90)["agent_exit_codes"] == [0, 0]
    finally:
        procs.stop_all()
    capsys.readouterr()
    assert main(["sfm", "--clusters", str(job), "--features", *map(str, robots), "--out", str(tmp_path / "no")]) == 2
    assert f"--features {robots[0]}: no feature_ids array" in capsys.readouterr().err
    assert main(["sfm", "--clusters", str(job), "--features", f"0={robots[1]}", f"1={robots[0]}",
                 "--out", str(tmp_path / "no")]) == 2
    assert "--features 0=" in capsys.readouterr().err and not (tmp_path / "no").exists()
    assert main(["sfm", "--clusters", str(job), "--features", f"0={robots[0]}", f"1={robots[1]}",
                 "--out", str(tmp_path / "m"), "--quiet"]) == 0
    report = json.loads((tmp_path / "m" / "sfm.json").read_text())
    assert report["model"]["registered"] == 5 and report["model"]["points"] > report["model_before_triangulation"][
        "points"] > 0


def test_images_mapped_again_take_their_features_from_the_run(tmp_path):
    """A repair that maps some of the run's images again (their SIFT choice the run's) takes their features from
    the run's rather than extracting them again: each image's features are its own, so they are the same arrays."""
    from generators.scenes3d import generate_scene3d

    from dqm.commands.sfm import _features_of
    from dqm.vision.features import extract_images

    folder = generate_scene3d(seed=4, n_images=4, width=240, height=180, n_planes=2).save(tmp_path / "img")
    paths = [str(folder / f"img{k}.png") for k in (1, 2, 3, 4)]
    run = extract_images(paths, preset="budget")
    alone = extract_images([paths[2], paths[0]], preset="budget")
    taken = _features_of(run, [2, 0])
    assert [str(n) for n in taken.image_names] == [str(n) for n in alone.image_names]
    for name in ("descriptors", "image_ids", "keypoints"):
        assert np.array_equal(getattr(taken, name), getattr(alone, name)), name


def test_sfm_presets_follow_the_collections_size_as_the_mapper_does():
    """--preset auto: COLMAP's budget below GLOBAL_FROM images, the sfm preset capped at COLMAP's 8,192 features an
    image from there; a --max-features given is kept (0: no limit), and a preset given is never capped unasked."""
    from dqm.vision.sfm import GLOBAL_FROM, choose_features, choose_mapper

    assert [choose_features("auto", None, n) for n in (2, GLOBAL_FROM - 1, GLOBAL_FROM, 500)] == \
        [("budget", 0), ("budget", 0), ("sfm", 8192), ("sfm", 8192)]
    assert [choose_features("auto", m, 500) for m in (0, 5000)] == [("sfm", 0), ("sfm", 5000)]
    assert choose_features("auto", 5000, 3) == ("budget", 5000)
    assert [choose_mapper("auto", n) for n in (GLOBAL_FROM - 1, GLOBAL_FROM)] == ["incremental", "global"]
    assert choose_features("rootsift", None, 3) == ("rootsift", 0) and choose_features("sfm", None, 100) == ("sfm", 0)
    assert choose_features("budget", 2000, 100) == ("budget", 2000)


def test_dqm_sfm_gt_problems_are_one_line_before_any_work(tmp_path, capsys):
    from generators.scenes3d import generate_scene3d

    images = generate_scene3d(seed=3, n_images=3, width=160, height=120, n_planes=2).save(tmp_path / "img")
    (tmp_path / "gt").mkdir()
    assert main(["sfm", str(images), "--out", str(tmp_path / "m"), "--gt", str(tmp_path / "gt")]) == 2
    assert "neither Strecha" in capsys.readouterr().err
    (tmp_path / "gt" / "other.jpg.camera").write_text("1 0 0\n0 1 0\n0 0 1\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 0\n9 9\n")
    assert main(["sfm", str(images), "--out", str(tmp_path / "m"), "--gt", str(tmp_path / "gt")]) == 2
    assert "no camera for any of the 3 images" in capsys.readouterr().err
    assert main(["sfm", str(images), "--out", str(tmp_path / "m"), "--seed", "-2"]) == 2
    assert main(["sfm", str(images), "--out", str(tmp_path / "m"), "--partners", "-1"]) == 2
    assert "--partners must be >= 0" in capsys.readouterr().err.replace("--seed, --mapper-threads and ", "")
    assert main(["sfm", str(images), "--out", str(tmp_path / "m"), "--max-features", "-1"]) == 2
    captured = capsys.readouterr()
    assert "--max-features must be >= 0 (0 = no limit), got -1" in captured.err and "SIFT preset" not in captured.out
    assert not (tmp_path / "m").exists()


def test_dqm_sfm_verifies_and_maps_each_images_strongest_pairs(tmp_path, capsys):
    """--partners N: only each image's N image pairs with the most shared clusters are written, verified and
    mapped (the default 100 keeps every pair of a small scene); what is left out is said and reported."""
    from generators.scenes3d import generate_scene3d

    images = generate_scene3d(seed=4, n_images=5).save(tmp_path / "img")
    for name, partners in (("all", []), ("two", ["--partners", "2"])):
        assert main(["sfm", str(images), "--out", str(tmp_path / name), "--no-triangulate", "--quiet",
                     *partners]) == 0
    out = capsys.readouterr().out
    every, two = (json.loads((tmp_path / d / "sfm.json").read_text()) for d in ("all", "two"))
    assert every["options"]["partners"] == 100 and every["pairs"]["beyond_partners"] == 0
    assert every["pairs"]["written"] == 10  # 5 images that all see one another
    assert two["options"]["partners"] == 2 and 0 < two["pairs"]["beyond_partners"]
    assert two["pairs"]["written"] + two["pairs"]["beyond_partners"] == 10
    assert f"{two['pairs']['beyond_partners']} pair" in out and "outside both images' 2 strongest left out" in out
    assert two["model"]["registered"] == 5  # the strongest pairs still hold every image


def test_bench_sfm_small_with_ground_truth(tmp_path):
    """scripts/bench_sfm.py on a generated 4-image scene with its true cameras (Strecha files), dqm's default
    beside COLMAP's pipeline: both register every image, and the JSON's AUC is the AUC of its pairwise
    errors. (The benchmark's real runs are on photos: docs/sfm.md.)"""
    from generators.scenes3d import generate_scene3d

    from dqm.vision import poses

    scene = generate_scene3d(seed=0, n_images=4)
    saved = scene.save(tmp_path / "scene")
    images = tmp_path / "images"  # the photos only (COLMAP reads every file of the folder)
    images.mkdir()
    for p in sorted(saved.glob("img*.png")):
        (images / p.name).symlink_to(p)
    gt = write_strecha(scene, tmp_path / "gt")
    p = subprocess.run([sys.executable, "scripts/bench_sfm.py", "--images", str(images), "--gt", str(gt),
                        "--pipelines", "colmap,dqm", "--out-dir", str(tmp_path / "out")],
                       capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert p.returncode == 0, p.stderr[-2000:]
    table = (tmp_path / "out" / "sfm.md").read_text()
    rows = [ln for ln in table.splitlines() if ln.startswith(("| colmap", "| dqm"))]
    assert len(rows) == 2 and all("| 4 / 4 |" in ln for ln in rows), table
    assert re.search(r"^- dqm: AUC@1° [0-9.]+ vs [0-9.]+ \((met|missed)\)", table, re.M), table
    data = json.loads((tmp_path / "out" / "sfm.json").read_text())
    for name in ("colmap", "dqm"):
        run = data["results"][name][0]
        assert len(run["pair_errors"]) == 6  # 4 images, 6 pairs
        auc = poses.pose_auc(run["pair_errors"])
        assert [run["poses"]["auc"][k] for k in ("1", "2", "5")] == pytest.approx(auc)
    assert (tmp_path / "out" / "sfm_poses.png").stat().st_size > 10_000


def test_bench_sfm_keeps_its_working_folder_when_a_pipeline_fails(tmp_path):
    """A pipeline that fails stops scripts/bench_sfm.py with its error and the path of the run's working folder,
    which stays (a 9-minute `dqm sfm` of a collection that failed in its last stage left nothing to look at);
    no table is written."""
    import cv2

    from dqm.vision.scenes import texture

    images = tmp_path / "images"
    images.mkdir()
    for k in range(2):
        cv2.imwrite(str(images / f"img{k}.png"), texture(120, 160, seed=k))
    temp = tmp_path / "temp"
    temp.mkdir()
    p = subprocess.run([sys.executable, "scripts/bench_sfm.py", "--images", str(images), "--pipelines",
                        "dqm --rho -1", "--out-dir", str(tmp_path / "out")], capture_output=True, text=True,
                       timeout=300, cwd=ROOT, env={**os.environ, "TMPDIR": str(temp)})
    assert p.returncode == 1, p.stderr[-2000:]
    assert "failed (exit 2)" in p.stderr and "--rho" in p.stderr, p.stderr[-2000:]
    kept = Path(re.search(r"working folder is kept: (\S+)", p.stderr).group(1))
    assert kept.is_dir() and kept.parent == temp
    assert not (tmp_path / "out" / "sfm.md").exists()


def test_points_gap_classifies_every_colmap_point(tmp_path):
    """scripts/sfm_points_gap.py on a generated 4-image scene: every COLMAP point of 2+ images falls in one
    class, the classes add up to COLMAP's points, and most of them are dqm's too (the same scene, both
    pipelines register it); a second run reuses the kept pipelines (--work) and gives the same numbers."""
    from generators.scenes3d import generate_scene3d

    scene = generate_scene3d(seed=0, n_images=4)
    saved = scene.save(tmp_path / "scene")
    images = tmp_path / "images"
    images.mkdir()
    for p in sorted(saved.glob("img*.png")):
        (images / p.name).symlink_to(p)
    runs = []
    for k in range(2):
        out = tmp_path / f"gap{k}.json"
        p = subprocess.run([sys.executable, "scripts/sfm_points_gap.py", "--images", str(images), "--work",
                            str(tmp_path / "work"), "--json", str(out)], capture_output=True, text=True,
                           timeout=600, cwd=ROOT)
        assert p.returncode == 0, p.stderr[-2000:]
        runs.append(json.loads(out.read_text()))
    gap = runs[0]
    classes = gap["classes"]
    assert sum(c["points"] for c in classes.values()) == gap["colmap_points"] > 50
    assert classes["ours too"]["share"] > 0.5, classes
    assert gap["dqm_points"] > 0 and gap["colmap_model_points"] >= gap["colmap_points"]
    assert runs[1] == runs[0]


def test_the_strecha_cameras_of_the_shared_photos_are_read():
    """The ground truth the benchmark's real runs use (strecha/entry-P10): ten cameras, rotations."""
    from conftest import require_data

    from dqm.vision import poses

    truth = poses.read_strecha(require_data("strecha", "entry-P10") / "gt_cameras")
    assert len(truth) == 10 and all(name.endswith(".jpg") for name in truth)
    for pose in truth.values():
        R = np.asarray(pose.R)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0


def test_model_guided_triangulation_adds_true_points_and_keeps_the_cameras(tmp_path, capsys):
    """dqm sfm's last stage: matches under the model's own geometry are true correspondences (checked
    against the generated scene), the model gains points seen in 3+ images; with --no-bundle-adjust its
    cameras are the mapper's, bit for bit (--no-triangulate gives the same poses); by default one bundle
    adjustment then moves them, lowering the reprojection error, and they stay as close to the truth."""
    import pycolmap
    from generators.scenes3d import generate_scene3d

    from dqm import io
    from dqm.vision import colmap
    from dqm.vision.triangulation import model_guided_matches

    scene = generate_scene3d(seed=2, n_images=5)
    images = scene.save(tmp_path / "img")
    gt = write_strecha(scene, tmp_path / "gt")
    assert main(["sfm", str(images), "--out", str(tmp_path / "plain"), "--no-triangulate", "--quiet",
                 "--gt", str(gt)]) == 0
    assert main(["sfm", str(images), "--out", str(tmp_path / "dense"), "--no-bundle-adjust", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "model-guided triangulation:" in out and "bundle adjustment" not in out
    plain = pycolmap.Reconstruction(str(tmp_path / "plain/sparse/0"))
    dense = pycolmap.Reconstruction(str(tmp_path / "dense/sparse/0"))
    assert dense.num_points3D() > plain.num_points3D()
    for image_id, image in plain.images.items():
        assert np.array_equal(image.cam_from_world().matrix(), dense.images[image_id].cam_from_world().matrix())
    new = [p for i, p in dense.points3D.items() if i > max(plain.point3D_ids())]
    assert new and min(p.track.length() for p in new) >= 3
    report = json.loads((tmp_path / "dense" / "sfm.json").read_text())
    assert report["model_before_triangulation"]["points"] == plain.num_points3D()
    assert report["model"]["points"] == dense.num_points3D() and "triangulate" in report["times"]
    assert report["options"]["bundle_adjust"] is False

    # the default adjusts the triangulated model once: the same points, cameras moved, a lower error. COLMAP's log
    # stays quiet and writes no file: pycolmap's bundle adjustment sets glog's flags to INFO and log files (in the
    # temporary folder, named after this process) and leaves them so
    flags = {name: getattr(pycolmap.logging, name) for name in ("logtostderr", "minloglevel")}
    assert flags == {"logtostderr": True, "minloglevel": int(pycolmap.logging.FATAL)}
    assert main(["sfm", str(images), "--out", str(tmp_path / "ba"), "--quiet", "--gt", str(gt)]) == 0
    assert {name: getattr(pycolmap.logging, name) for name in flags} == flags
    folders = {tempfile.gettempdir(), "/tmp", os.environ.get("TMPDIR") or "/tmp", os.environ.get("TMP") or "/tmp"}
    assert not [f for d in folders for f in glob.glob(f"{d}/*.log.*.{os.getpid()}", include_hidden=True)]
    # and the flags as they were after pycolmap's bundle adjustment too, within colmap_log_kept
    flags = {name: getattr(pycolmap.logging, name) for name in ("logtostderr", "alsologtostderr", "minloglevel")}
    with colmap.colmap_log_kept(pycolmap):
        pycolmap.bundle_adjustment(pycolmap.Reconstruction(str(tmp_path / "ba/sparse/0")))
    assert {name: getattr(pycolmap.logging, name) for name in flags} == flags
    line = [ln for ln in capsys.readouterr().out.splitlines() if "bundle adjustment" in ln][0]
    before, after = map(float, re.search(r"error ([0-9.]+) -> ([0-9.]+) px", line).groups())
    assert after <= before, line  # the mapper adjusted this small clean scene already: equal to 3 digits
    adjusted = pycolmap.Reconstruction(str(tmp_path / "ba/sparse/0"))
    assert adjusted.num_points3D() == dense.num_points3D()
    assert any(not np.array_equal(image.cam_from_world().matrix(), adjusted.images[i].cam_from_world().matrix())
               for i, image in plain.images.items())
    ba, mapped = (json.loads((tmp_path / d / "sfm.json").read_text())["poses"] for d in ("ba", "plain"))
    assert ba["median_rotation_deg"] <= mapped["median_rotation_deg"] * 1.1 + 0.01, (ba, mapped)

    # the guided matches, checked against the scene: a match is true when the scene maps one keypoint
    # within 2 px of the other
    z = io.load_clusters(tmp_path / "plain" / "clusters.npz")
    names = [f"img{k + 1}.png" for k in range(len(scene))]
    by_id = {image_id: names.index(image.name) for image_id, image in plain.images.items()}
    kp = {i: z["keypoints"][z["image_ids"] == k, :2] for i, k in by_id.items()}
    desc = {i: z["descriptors"][z["image_ids"] == k] for i, k in by_id.items()}
    found = model_guided_matches(plain, kp, desc)
    assert found
    true = total = 0
    for (a, b), m in found.items():
        uv, ok = scene.correspondence(by_id[a], by_id[b], kp[a][m[:, 0]].astype(np.float64))
        hit = ok & (np.linalg.norm(uv - kp[b][m[:, 1]], axis=1) <= 2.0)
        true, total = true + int(hit.sum()), total + len(m)
    assert total > 1000 and true / total > 0.9, (true, total)

    # a camera whose radial distortion folds back (as the global mapper estimated for cmu_hotel's frames, where
    # the stage stopped on the NaN positions): its keypoints beyond the fold take no part, the rest still match
    from dqm.vision.triangulation import _undistorted

    folded = pycolmap.Reconstruction(str(tmp_path / "plain/sparse/0"))
    cam = folded.cameras[folded.images[1].camera_id]
    assert cam.model.name == "SIMPLE_RADIAL"
    cam.params = [cam.params[0], cam.params[1], cam.params[2], -0.6]  # no inverse beyond ~0.5 f from the centre
    lost = ~np.isfinite(_undistorted(folded, 1, kp[1])).all(axis=1)
    assert 0 < lost.sum() < len(lost)
    again = model_guided_matches(folded, kp, desc)
    assert any(1 in pair for pair in again)
    for (a, b), m in again.items():
        if a == 1:
            assert not lost[m[:, 0]].any()
        if b == 1:
            assert not lost[m[:, 1]].any()


def test_every_long_stage_of_dqm_sfm_shows_progress_on_a_terminal(tmp_path, capsys, monkeypatch):
    """On a terminal every stage after QuickMatch shows its progress: the export's pairs written then verified,
    the incremental mapper's registered images (callbacks of COLMAP's), the model-guided matches' pairs, and
    the time taken by the calls that report nothing (COLMAP's global mapper, triangulator, bundle
    adjustment); --quiet shows none, and the model is the same either way."""
    import io as _io

    from generators.scenes3d import generate_scene3d

    class Terminal(_io.StringIO):
        def isatty(self) -> bool:
            return True

    images = generate_scene3d(seed=1, n_images=4).save(tmp_path / "img")
    err = Terminal()
    monkeypatch.setattr(sys, "stderr", err)
    assert main(["sfm", str(images), "--out", str(tmp_path / "inc")]) == 0
    text = err.getvalue()
    for shown in ("export (write, then verify): 100%", "model-guided matches: 100%",
                  "triangulation (COLMAP's triangulator): 00:00 elapsed", "bundle adjustment: 00:00 elapsed"):
        assert shown in text, shown
    mapped = [bar for bar in re.split(r"[\r\n]", text) if bar.startswith("mapping: 100%")]
    assert mapped and "| 4/4 [" in mapped[-1], mapped  # every image registered, counted as the mapper went
    assert "mapping (COLMAP's global mapper)" not in text

    err.seek(0), err.truncate()
    assert main(["sfm", str(images), "--out", str(tmp_path / "glob"), "--mapper", "global", "--no-triangulate"]) == 0
    assert "mapping (COLMAP's global mapper): 00:00 elapsed" in err.getvalue()

    err.seek(0), err.truncate()
    assert main(["sfm", str(images), "--out", str(tmp_path / "quiet"), "--quiet"]) == 0
    assert "export (write" not in err.getvalue() and "elapsed" not in err.getvalue()
    inc, quiet = (json.loads((tmp_path / d / "sfm.json").read_text())["model"] for d in ("inc", "quiet"))
    assert inc == quiet and inc["registered"] == 4
    capsys.readouterr()


def test_covisible_partners_are_each_images_most_covisible_ones():
    """The triangulation stage's pairs: every image with the k images that share the most points with it
    (at least min_shared; ties by the lower id), the union of those choices, each pair once."""
    from types import SimpleNamespace as NS

    from dqm.vision.triangulation import covisible_pairs, covisible_partners

    rng = np.random.default_rng(4)
    points = []
    shared = {}
    for a in range(12):
        for b in range(a + 1, 12):
            n = int(rng.integers(0, 40)) if b - a < 6 else 0
            shared[(a, b)] = n
            points += [NS(track=NS(elements=[NS(image_id=a), NS(image_id=b), NS(image_id=b)]))] * n
    rec = NS(points3D=dict(enumerate(points)))
    assert covisible_pairs(rec, 15) == sorted(p for p, n in shared.items() if n >= 15)
    for k in (1, 3, 20):
        want = set()
        for a in range(12):
            mine = [(-n, p[1] if a == p[0] else p[0]) for p, n in shared.items() if a in p and n >= 15]
            want |= {(min(a, b), max(a, b)) for _, b in sorted(mine)[:k]}
        got = covisible_partners(rec, k, 15)
        assert got == sorted(want) and len(set(got)) == len(got)
    assert covisible_partners(rec, 20, 15) == covisible_pairs(rec, 15)  # enough partners: every covisible pair
    assert len(covisible_partners(rec, 1, 15)) < len(covisible_partners(rec, 3, 15)) < len(covisible_pairs(rec, 15))


def test_a_collection_of_two_scenes_gives_a_model_each_every_one_triangulated_and_reported(tmp_path, capsys):
    """Two generated scenes in one call (two folders): COLMAP's mapper makes a model of each; dqm sfm's last
    stage runs on every model (more points in each, cameras unchanged), sfm.json and the summary report
    every model with the stages' times and peak memory, each model is drawn, and no model holds images of
    both scenes."""
    import pycolmap
    from generators.scenes3d import generate_scene3d

    a = generate_scene3d(seed=2, n_images=4).save(tmp_path / "a")
    b = generate_scene3d(seed=5, n_images=5).save(tmp_path / "b")
    assert main(["sfm", str(a), str(b), "--out", str(tmp_path / "m"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "2 models, 9 of 9 images registered" in out and out.count("model-guided triangulation:") == 2
    report = json.loads((tmp_path / "m" / "sfm.json").read_text())
    models = report["models"]
    assert [m["registered"] for m in models] == [5, 4] and report["model"] == {k: models[0][k] for k in
                                                                             report["model"]}
    for m in models:
        rec = pycolmap.Reconstruction(str(tmp_path / "m" / m["folder"]))
        folders = {image.name.split("/")[0] for image in rec.images.values()}
        assert len(folders) == 1 and rec.num_points3D() == m["points"] > m["before_triangulation"]["points"]
    assert set(report["peak_memory_bytes"]) == {"extract", "match", "export", "map", "triangulate"}
    assert all(v > 10 << 20 for v in report["peak_memory_bytes"].values())
    assert report["pairs"]["verified"] == 6 + 10 and report["clusters_across_models"]["clusters"] > 0
    assert (tmp_path / "m" / "model.png").exists() and (tmp_path / "m" / "model-2.png").exists()
    # QuickMatch joins glyphs of both scenes' textures: COLMAP verifies some pairs of images of two scenes on 15-20
    # chance inliers; they are dropped as weak for both images (the global mapper joined the two scenes into one
    # model with them; with them left in, dqm sfm splits that model by its scenes: the next test)
    assert report["pairs"]["dropped_as_weak"] > 0


def test_a_model_of_two_scenes_that_share_almost_no_point_is_split(tmp_path, capsys, monkeypatch):
    """COLMAP 4's global mapper placed three scenes of the shared mixed collection in one model, joined by 6
    verified image pairs and no 3-D point. Here the weak-pair filter is taken away so that the chance pairs
    between two generated scenes reach the global mapper, which then makes one model of both (images of the two
    scenes share one chance point, images of one scene 500-800): dqm sfm splits it by the points its images
    share (15 or more link two images), one model per scene (each then triangulated and reported as any
    model: the previous test)."""
    import pycolmap
    from generators.scenes3d import generate_scene3d

    from dqm.vision import colmap, sfm

    a = generate_scene3d(seed=2, n_images=4, width=480, height=360).save(tmp_path / "a")
    b = generate_scene3d(seed=5, n_images=5, width=480, height=360).save(tmp_path / "b")
    monkeypatch.setattr(colmap, "drop_weak_pairs", lambda database: 0)
    argv = ["sfm", str(a), str(b), "--mapper", "global", "--quiet", "--no-triangulate"]
    real = sfm.split_scenes
    monkeypatch.setattr(sfm, "split_scenes", lambda models, out: models)
    assert main([*argv, "--out", str(tmp_path / "joined")]) == 0
    assert "model: 9 of 9 images registered" in capsys.readouterr().out  # one: what the global mapper made
    joined = pycolmap.Reconstruction(str(tmp_path / "joined" / "sparse" / "0"))
    groups = sfm.scene_groups(joined)
    assert sorted(len(g) for g in groups) == [4, 5]
    assert [len({joined.image(i).name.split("/")[0] for i in g}) for g in groups] == [1, 1]
    # what dqm sfm does with such a model (the step taken away above; the previous test runs dqm sfm through two
    # models end to end, each triangulated and reported): a model per group, written where the mapper's are
    sparse = tmp_path / "joined" / "sparse"
    models = real([sfm.Model(0, joined, sparse / "0")], sparse)
    assert [len(m.rec.reg_image_ids()) for m in models] == [5, 4] and sorted(m.key for m in models) == [0, 1]
    for m in models:
        rec = pycolmap.Reconstruction(str(m.folder))
        assert len({rec.image(i).name.split("/")[0] for i in rec.reg_image_ids()}) == 1
        assert rec.num_reg_images() == len(m.rec.reg_image_ids()) and rec.num_points3D() > 0


def _forced_split(monkeypatch, last: int):
    """dqm sfm's split of a model by its scenes made to cut the mapper's one model into two: its images but the
    ``last`` highest ids, and those (one scene, where the real split keeps one model)."""
    from dqm.vision import sfm

    real_split, real_groups = sfm.split_scenes, sfm.scene_groups

    def split(models, out):
        ids = sorted(models[0].rec.reg_image_ids())
        monkeypatch.setattr(sfm, "scene_groups", lambda rec: [ids[:-last], ids[-last:]])
        try:
            return real_split(models, out)
        finally:
            monkeypatch.setattr(sfm, "scene_groups", real_groups)

    monkeypatch.setattr(sfm, "split_scenes", split)


def test_a_small_model_of_a_scenes_images_is_joined_into_the_scenes_model(tmp_path, capsys, monkeypatch):
    """COLMAP 4's global mapper left 3 to 9 of nerf_lego's 100 renders in a model of their own in the mixed
    collection. Here one generated scene's model is cut in two (4 images and 2, the split of dqm sfm forced):
    COLMAP's incremental mapper, continuing the larger model, registers both images of the smaller, which is
    joined into it (its folder removed; sfm.json's joins say so), and the cameras are the scene's true ones."""
    import pycolmap
    from generators.scenes3d import generate_scene3d

    scene = generate_scene3d(seed=0, n_images=6)
    images = scene.save(tmp_path / "img")
    gt = write_strecha(scene, tmp_path / "gt")
    _forced_split(monkeypatch, 2)
    assert main(["sfm", str(images), "--out", str(tmp_path / "m"), "--gt", str(gt), "--quiet",
                 "--no-triangulate"]) == 0
    out = capsys.readouterr().out
    assert "model 1 (2 images) joined into sparse/0: COLMAP's incremental mapper continuing that model " \
           "registered 2 of them" in out
    report = json.loads((tmp_path / "m" / "sfm.json").read_text())
    assert len(report["models"]) == 1 and report["model"]["registered"] == 6
    (join,) = report["models"][0]["joins"]
    assert join["joined"] and (join["model"], join["images"], join["registered"], join["larger_kept"]) == (1, 2, 2, 4)
    assert join["pairs"] >= 2
    assert not (tmp_path / "m" / "sparse" / "1").exists()
    assert pycolmap.Reconstruction(str(tmp_path / "m" / "sparse" / "0")).num_reg_images() == 6
    # the joined model's cameras are the generated ones (AUC@1 0.83 for the scene mapped whole in the first test)
    assert report["poses"]["registered"] == 6 and report["poses"]["auc"]["1"] > 0.6


def test_a_small_model_of_another_scene_is_not_joined(tmp_path, capsys, monkeypatch):
    """The joining's guards: the images of two generated scenes make no verified pair (so no join is tried);
    with the least pairs an image lowered to 0 the smaller scene's model is tried into the larger one, and COLMAP's
    mapper, continuing it, registers none of its images from the other scene's points: both models stay, each
    one scene."""
    import pycolmap
    from generators.scenes3d import generate_scene3d

    from dqm.vision import sfm

    a = generate_scene3d(seed=2, n_images=4).save(tmp_path / "a")
    b = generate_scene3d(seed=5, n_images=5).save(tmp_path / "b")
    argv = ["sfm", str(a), str(b), "--quiet", "--no-triangulate"]
    assert main([*argv, "--out", str(tmp_path / "m")]) == 0
    assert [m["joins"] for m in json.loads((tmp_path / "m" / "sfm.json").read_text())["models"]] == [[], []]
    monkeypatch.setattr(sfm, "JOIN_PAIRS_PER_IMAGE", 0)
    assert main([*argv, "--out", str(tmp_path / "tried")]) == 0
    out = capsys.readouterr().out
    assert "model 1 (4 images) kept apart from sparse/0" in out
    report = json.loads((tmp_path / "tried" / "sfm.json").read_text())
    assert [m["registered"] for m in report["models"]] == [5, 4]
    (join,) = report["models"][0]["joins"]
    assert not join["joined"] and join["registered"] == 0 and join["pairs"] == 0
    for m in report["models"]:
        rec = pycolmap.Reconstruction(str(tmp_path / "tried" / m["folder"]))
        assert len({rec.image(i).name.split("/")[0] for i in rec.reg_image_ids()}) == 1
        assert rec.num_reg_images() == m["registered"]


def test_bench_sfm_collection_of_two_generated_scenes(tmp_path):
    """scripts/bench_sfm.py with two image folders (a collection of two scenes, mapped at once): every scene
    is scored in its own model against its own ground truth, with the points seen from two scenes, the
    verified pairs by scene pair and dqm's peak memory by stage. (The real run, beside COLMAP's pipeline: the
    shared photo sets together, docs/sfm.md. COLMAP 4's own mapper takes minutes on these two scenes, its
    structure-less fallback trying every image of the other scene: not run here.)"""
    from generators.scenes3d import generate_scene3d

    folders, gts = [], []
    for name, seed in (("one", 2), ("two", 5)):
        scene = generate_scene3d(seed=seed, n_images=4)
        saved = scene.save(tmp_path / f"{name}-saved")
        folders.append(tmp_path / name / "images")
        folders[-1].mkdir(parents=True)
        for p in sorted(saved.glob("img*.png")):
            (folders[-1] / p.name).symlink_to(p)
        gts.append(write_strecha(scene, tmp_path / name / "gt"))
    p = subprocess.run([sys.executable, "scripts/bench_sfm.py", "--images", *map(str, folders), "--gt",
                        *map(str, gts), "--pipelines", "dqm", "--out-dir", str(tmp_path / "out")],
                       capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert p.returncode == 0, p.stderr[-2000:]
    data = json.loads((tmp_path / "out" / "sfm.json").read_text())
    assert data["scenes"] == {"one": 4, "two": 4}
    for name in ("dqm",):
        run = data["results"][name][0]
        c = run["collection"]
        assert c["models"] == 2 and c["points_seen_from_two_scenes"] == 0, (name, c)
        for scene in ("one", "two"):
            e = c["scenes"][scene]
            assert e["registered"] == e["model_images"] == 4 and e["poses"]["auc"]["5"] > 0.5, (name, scene, e)
        assert run["verified_pairs"].get("one|one", 0) >= 3 and run["verified_pairs"].get("two|two", 0) >= 3
    dqm_run = data["results"]["dqm"][0]
    assert dqm_run["clusters_across_scenes"]["clusters"] >= 0 and set(dqm_run["peak_memory_bytes"]) >= {"match", "map"}
    mi = dqm_run["mapper_input"]  # what the clusters hand the mapper, by scene
    assert sum(e["features"] for e in mi["scenes"].values()) == dqm_run["features"]
    for e in mi["scenes"].values():  # a cluster of k >= 2 members: k (k - 1) / 2 matches, at least k / 2
        assert 0 < e["observations"] <= e["features"] and e["observations"] / 2 <= e["matches"]
        assert 2 <= e["largest"] <= 4 and e["matches_in_clusters_of_10"] == 0  # 4 images a scene
    n = [e["features"] for e in mi["scenes"].values()]
    assert mi["apart"] == pytest.approx((n[0] ** 2 + n[1] ** 2) / sum(n) ** 2) and 0.5 <= mi["apart"] < 0.6
    table = (tmp_path / "out" / "sfm.md").read_text()
    assert f"- Matching each scene apart would cost {mi['apart']:.2f} of dqm's" in table
    assert "| one | dqm | 4 / 4 |" in table and "| two | dqm | 4 / 4 |" in table


def test_images_registered_in_two_models_are_counted_once():
    """COLMAP's incremental mapper can start a model from images another model holds (sacre_coeur's 10 photos: a
    model of all 10 and one of 2 of them); dqm sfm's summary said '12 of 10 images registered'."""
    from types import SimpleNamespace

    from dqm.commands.sfm import registered_images

    def model(*names, unposed=()):
        images = [SimpleNamespace(name=n, has_pose=True) for n in names]
        images += [SimpleNamespace(name=n, has_pose=False) for n in unposed]
        return SimpleNamespace(rec=SimpleNamespace(
            reg_image_ids=lambda: [k for k, im in enumerate(images) if im.has_pose], image=images.__getitem__))

    ten = [f"{k}.jpg" for k in range(10)]
    assert registered_images([model(*ten), model("3.jpg", "4.jpg", unposed=["5.jpg"])]) == (10, 2)
    assert registered_images([model(*ten), model("3.jpg"), model("3.jpg", "x.jpg")]) == (11, 1)
    assert registered_images([model(*ten[:5]), model(*ten[5:])]) == (10, 0)


def test_a_model_with_no_point_is_drawn_and_reported_as_strict_json(tmp_path, capsys):
    """cmu_hotel's 101 frames with --single-camera --mapper incremental: COLMAP's incremental mapper left three
    frames in a model with no 3-D point after the triangulation stage, and drawing it raised LinAlgError after
    six minutes, before sfm.json was written. A model with fewer than three points is drawn with its cameras'
    axes, and sfm.json is written before the figures. No model at all has no track length and no reprojection
    error: null in strict JSON, not NaN."""
    import pycolmap
    from generators.scenes3d import generate_scene3d

    from dqm import outputs
    from dqm.vision.sfm import model_figure, model_numbers

    scene = generate_scene3d(seed=1, n_images=4)
    images = scene.save(tmp_path / "img")
    assert main(["sfm", str(images), "--out", str(tmp_path / "m"), "--no-triangulate", "--quiet"]) == 0
    rec = pycolmap.Reconstruction(str(tmp_path / "m/sparse/0"))
    assert rec.num_points3D() > 3 and rec.num_reg_images() >= 3
    for keep in (1, 0):  # one point left, then none
        for point_id in sorted(rec.point3D_ids())[keep:]:
            rec.delete_point3D(point_id)
        assert rec.num_points3D() == keep
        model_figure(rec, tmp_path / f"model-{keep}.png", f"{keep} points")
        assert (tmp_path / f"model-{keep}.png").stat().st_size > 10_000
    assert model_numbers(rec)["points"] == 0
    numbers = model_numbers(None)  # no model at all: no track length, no reprojection error
    assert numbers["registered"] == 0 and np.isnan(numbers["track"])
    outputs.write_json(tmp_path / "numbers.json", {"model": numbers, "curve": [1.0, float("inf")]})

    def refuse(constant):
        raise ValueError(f"not JSON: {constant}")

    strict = json.loads((tmp_path / "numbers.json").read_text(), parse_constant=refuse)
    assert strict == {"model": dict(numbers, track=None, reproj=None), "curve": [1.0, None]}
    report = json.loads((tmp_path / "m" / "sfm.json").read_text(), parse_constant=refuse)  # written as strict
    assert report["model"]["registered"] >= 3 and report["model"]["track"] > 1


def test_where_the_global_mapper_auto_chose_makes_no_model_the_incremental_one_runs(tmp_path, capsys,
                                                                                   monkeypatch):
    """cmu_hotel's 101 video frames with --single-camera: COLMAP's global mapper (--mapper auto's choice from 30
    images) made no model on one thread (101 frames on two), and dqm sfm stopped at 'no model'; the incremental
    mapper registers all 101 from the same database. Now it runs where the global mapper auto chose makes no
    model; the global mapper asked for by name is not replaced. (The global mapper's failure is made to happen
    here: these generated scenes give it a model.)"""
    import pycolmap
    from generators.scenes3d import generate_scene3d

    scene = generate_scene3d(seed=0, n_images=5)
    images = scene.save(tmp_path / "img")
    monkeypatch.setattr("dqm.vision.sfm.GLOBAL_FROM", 3)  # --mapper auto chooses the global mapper for 5 images
    calls = []

    def no_model(database, *args, **kwargs):
        calls.append(database)
        return {}

    monkeypatch.setattr(pycolmap, "global_mapping", no_model)
    assert main(["sfm", str(images), "--out", str(tmp_path / "auto"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert len(calls) == 1 and "COLMAP's global mapper made no model" in out and "incremental mapping instead" in out
    assert "5 of 5 images registered" in out
    report = json.loads((tmp_path / "auto" / "sfm.json").read_text())
    assert report["options"]["mapper"] == "incremental" and report["model"]["registered"] == 5
    assert main(["sfm", str(images), "--out", str(tmp_path / "asked"), "--mapper", "global", "--quiet"]) == 1
    out = capsys.readouterr().out
    assert "no model" in out and "instead" not in out
    # no image registered, a camera each: mapped again with one camera per folder, by the mapper asked for
    assert len(calls) == 3 and "0 of 5 images registered with a camera each" in out
    assert Path(calls[2]) == tmp_path / "asked" / "shared-camera" / "all" / "database.db"
    report = json.loads((tmp_path / "asked" / "sfm.json").read_text())
    assert not report["few_registered_again"]["taken"] and report["few_registered_again"]["mapper"] == "global"


def test_a_model_of_bogus_cameras_is_mapped_again_with_one_camera_per_folder(tmp_path, capsys, monkeypatch):
    """cmu_hotel's 101 video frames, a camera a frame (dqm sfm's default, COLMAP's too): COLMAP's global mapper
    gave every frame a radial distortion k of -3 to -4, cameras COLMAP itself calls bogus, and a model of 391
    points (185 after the last stage). Where a model has bogus cameras and its images share one size a folder
    with no EXIF focal length, they are mapped again with one camera per folder into shared-camera/<k>/, which
    replaces the first model (kept in sparse/<k>) where it registers as many images with fewer bogus cameras and
    as many 3-D points; mapped again by the incremental mapper, which checks the cameras as it goes. Here the
    mappings' models are spoiled as the global mapper spoiled cmu_hotel's (these
    generated views give it sound cameras): some cameras made bogus, some points taken away. The first model is
    kept where the second has fewer points, where the second cannot be made, and where the cameras are shared
    already (--single-camera), each with a warning."""
    import pycolmap
    from generators.scenes3d import generate_scene3d

    from dqm.commands import sfm as command
    from dqm.validation import InputError
    from dqm.vision import sfm

    images = generate_scene3d(seed=0, n_images=5, width=480, height=360).save(tmp_path / "img")
    real, calls, plan = sfm.reconstruct, [], {}

    def spoiled(database, *args, **kwargs):  # plan: {mapping: (bogus cameras, share of the points kept)}
        models, seconds = real(database, *args, **kwargs)
        calls.append(database)
        bogus, keep = plan.get(len(calls), (0, 1.0))
        for m in models:
            for image_id in sorted(m.rec.reg_image_ids())[:bogus]:
                camera = m.rec.cameras[m.rec.image(image_id).camera_id]
                camera.params = [*camera.params[:3], -3.0]  # SIMPLE_RADIAL's k
            for point_id in sorted(m.rec.point3D_ids())[int(keep * m.rec.num_points3D()):]:
                m.rec.delete_point3D(point_id)
        return models, seconds

    def run(name, *options, spoil):
        calls.clear()
        plan.clear()
        plan.update(spoil)
        assert main(["sfm", str(images), "--out", str(tmp_path / name), "--quiet", *options]) == 0
        return capsys.readouterr(), json.loads((tmp_path / name / "sfm.json").read_text())

    monkeypatch.setattr(sfm, "reconstruct", spoiled)
    global_from = sfm.GLOBAL_FROM
    monkeypatch.setattr(sfm, "GLOBAL_FROM", 3)  # the first mapping by the global mapper, the second incremental
    captured, report = run("m", spoil={1: (5, 0.5)})
    monkeypatch.setattr(sfm, "GLOBAL_FROM", global_from)
    assert "sparse/0: 5 of 5 registered images have a camera COLMAP calls bogus" in captured.out
    assert "it replaces sparse/0" in captured.out
    assert f"{tmp_path / 'm'}/shared-camera" in captured.out.splitlines()[-1]
    [again] = report["shared_camera_again"]
    assert again["taken"] and (again["images"], again["bogus_cameras"]) == (5, 5) and len(calls) == 2
    assert (again["registered_again"], again["bogus_cameras_again"]) == (5, 0)
    assert report["options"]["mapper"] == "global" and again["mapper"] == "incremental"
    assert again["points_again"] > again["model_before"]["points"] > 0
    assert report["models"][0]["folder"] == "shared-camera/0/sparse/0" and report["model"]["bogus_cameras"] == 0
    assert report["model"]["registered"] == 5 and report["model"]["points"] > 0
    assert report["few_registered_again"] is None  # every image registered: no reason to map them all again
    shared = pycolmap.Reconstruction(str(tmp_path / "m" / "shared-camera/0/sparse/0"))
    assert {image.camera_id for image in shared.images.values()} == {1}  # one camera for the folder
    first = pycolmap.Reconstruction(str(tmp_path / "m" / "sparse/0"))  # the first model stays (as written)
    assert len({image.camera_id for image in first.images.values()}) == 5
    assert sfm.bogus_cameras(first) == [] and sfm.bogus_cameras(shared) == []
    camera = first.cameras[first.images[1].camera_id]
    camera.params = [camera.params[0] * 20, *camera.params[1:]]  # a focal length beyond 10x the image: bogus too
    assert sfm.bogus_cameras(first) == [first.images[1].name]

    captured, report = run("fewer", spoil={1: (1, 1.0), 2: (0, 0.5)})  # one bogus camera; fewer points again
    assert "sparse/0: 1 of 5 registered images have a camera COLMAP calls bogus" in captured.out
    assert "bogus cameras, " in captured.err and "; sparse/0 is kept" in captured.err
    [again] = report["shared_camera_again"]
    assert not again["taken"] and again["points_again"] < again["model_before"]["points"]
    assert report["models"][0]["folder"] == "sparse/0" and len(calls) == 2

    real_match_and_map = command._match_and_map

    def fails_again(args, out, *rest, **kwargs):
        if "shared-camera" in str(out):
            raise InputError("made to fail")
        return real_match_and_map(args, out, *rest, **kwargs)

    monkeypatch.setattr(command, "_match_and_map", fails_again)
    captured, report = run("fails", spoil={1: (5, 1.0)})
    assert "sparse/0 not mapped again (made to fail); sparse/0 is kept" in captured.err
    assert report["shared_camera_again"][0]["error"] == "made to fail" and len(calls) == 1
    assert report["models"][0]["folder"] == "sparse/0" and report["model"]["registered"] == 5
    monkeypatch.setattr(command, "_match_and_map", real_match_and_map)

    # (--no-triangulate: the last stage's bundle adjustment would mend these made-up cameras)
    captured, report = run("one", "--single-camera", "--no-triangulate", spoil={1: (5, 1.0)})
    assert "not mapped again with one camera per folder (the images share cameras already)" in captured.err
    assert "sparse/0: 5 of 5 registered images have a camera COLMAP calls bogus (focal length or distortion out " \
           "of its bounds): their poses are not to be trusted" in captured.err
    assert [e["taken"] for e in report["shared_camera_again"]] == [False] and len(calls) == 1
    assert report["model"]["bogus_cameras"] == 5 and not (tmp_path / "one" / "shared-camera").exists()


def test_a_mapping_that_registers_few_images_a_camera_each_is_done_again_with_one_camera_per_folder(
        tmp_path, capsys, monkeypatch):
    """cmu_hotel's 101 video frames with --mapper incremental, a camera a frame: COLMAP's incremental mapper,
    which drops an image whose camera it calls bogus, registered 12 of them. Where the mapper's models hold fewer
    than half of the images, each with a camera of its own, and one camera per folder fits them (one size a folder,
    no EXIF focal length), every image is mapped again with one camera per folder into shared-camera/all/, whose
    models replace the first where their largest registers more images. Here the first mapping keeps 2 of 5
    images, as the incremental mapper kept cmu_hotel's; with --single-camera nothing is mapped again."""
    import pycolmap
    from generators.scenes3d import generate_scene3d

    from dqm.commands import sfm as command
    from dqm.vision import sfm

    images = generate_scene3d(seed=0, n_images=5, width=480, height=360).save(tmp_path / "img")
    real, calls = sfm.reconstruct, []
    made, real_extract, real_cluster = [], command.extract, command.cluster
    monkeypatch.setattr(command, "extract", lambda *a, **kw: made.append("extract") or real_extract(*a, **kw))
    monkeypatch.setattr(command, "cluster", lambda *a, **kw: made.append("match") or real_cluster(*a, **kw))

    def few(database, *args, **kwargs):  # the first mapping keeps two images registered
        models, seconds = real(database, *args, **kwargs)
        calls.append(database)
        if len(calls) == 1:
            for m in models:
                for image_id in sorted(m.rec.reg_image_ids())[2:]:
                    m.rec.deregister_frame(m.rec.image(image_id).frame_id)
        return models, seconds

    monkeypatch.setattr(sfm, "reconstruct", few)
    assert main(["sfm", str(images), "--out", str(tmp_path / "m"), "--quiet", "--mapper", "incremental"]) == 0
    out = capsys.readouterr().out
    report = json.loads((tmp_path / "m" / "sfm.json").read_text())
    entry = report["few_registered_again"]
    assert "2 of 5 images registered with a camera each" in out and "its models replace the first" in out
    assert entry["taken"] and (entry["images"], entry["registered_again"], entry["registered_of"]) == (2, 5, 5)
    assert entry["model_folder"] == "sparse/0" and entry["folder"] == "shared-camera/all/sparse/0" and len(calls) == 2
    assert report["models"][0]["folder"] == "shared-camera/all/sparse/0" and report["model"]["registered"] == 5
    assert report["shared_camera_again"] == [] and report["model"]["points"] > report["model_before_triangulation"][
        "points"] > 0  # the new model went through the last stage
    model = pycolmap.Reconstruction(str(tmp_path / "m" / "shared-camera/all/sparse/0"))
    assert {image.camera_id for image in model.images.values()} == {1}  # one camera for the folder
    assert f"{tmp_path / 'm'}/shared-camera" in out.splitlines()[-1]
    # the same frames with the same SIFT choice: their features and clusters are reused, only the cameras differ
    assert made == ["extract", "match"] and not (tmp_path / "m" / "shared-camera/all/clusters.npz").exists()

    # from the run's clusters.npz (--clusters) the repair is the same, with nothing extracted or matched
    calls.clear()
    made.clear()
    assert main(["sfm", "--clusters", str(tmp_path / "m" / "clusters.npz"), "--out", str(tmp_path / "again"),
                 "--quiet", "--mapper", "incremental"]) == 0
    again = json.loads((tmp_path / "again" / "sfm.json").read_text())
    assert made == [] and again["few_registered_again"]["taken"] and again["model"] == report["model"]

    calls.clear()
    assert main(["sfm", str(images), "--out", str(tmp_path / "one"), "--quiet", "--mapper", "incremental",
                 "--single-camera", "--no-triangulate"]) == 0
    report = json.loads((tmp_path / "one" / "sfm.json").read_text())
    assert report["few_registered_again"] is None and report["model"]["registered"] == 2 and len(calls) == 1
    assert not (tmp_path / "one" / "shared-camera").exists()


def test_cameras_the_last_stage_leaves_bogus_are_mapped_again_with_one_camera_per_folder(tmp_path, capsys,
                                                                                         monkeypatch):
    """The repair above looks at the mapper's model; the last stage's bundle adjustment can make cameras bogus
    that were not (cmu_hotel in the 270-photo collection with --cluster-matches auto: 0 before it, 33 after, 822
    points against 2,714 with the repair). Such a model is mapped again with one camera per folder too (sfm.json:
    ``after`` the last stage), and the new model goes through the last stage in its place. Here the first
    triangulation's cameras are spoiled as cmu_hotel's were; the second's are not."""
    import pycolmap
    from generators.scenes3d import generate_scene3d

    from dqm.commands import sfm as command
    from dqm.vision import sfm

    images = generate_scene3d(seed=0, n_images=5, width=480, height=360).save(tmp_path / "img")
    real, folders = command._triangulate, []

    def spoiled(rec, database, *args):
        rec, stats = real(rec, database, *args)
        folders.append(Path(database).parent.name)
        if len(folders) == 1:
            for camera in rec.cameras.values():
                camera.params = [*camera.params[:3], -3.0]  # SIMPLE_RADIAL's k beyond COLMAP's bounds
        return rec, stats

    real_reconstruct, mappings = sfm.reconstruct, []

    def fewer_points(database, *args, **kwargs):  # the first mapping's model a tenth poorer, as cmu_hotel's was
        models, seconds = real_reconstruct(database, *args, **kwargs)
        mappings.append(database)
        for m in models if len(mappings) == 1 else []:
            for point_id in sorted(m.rec.point3D_ids())[int(0.9 * m.rec.num_points3D()):]:
                m.rec.delete_point3D(point_id)
        return models, seconds

    monkeypatch.setattr(command, "_triangulate", spoiled)
    monkeypatch.setattr(sfm, "reconstruct", fewer_points)
    assert main(["sfm", str(images), "--out", str(tmp_path / "m"), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "sparse/0: 5 of 5 registered images have a camera COLMAP calls bogus after the last stage's bundle " \
           "adjustment" in captured.out and "it replaces sparse/0" in captured.out
    assert "not to be trusted" not in captured.err and folders == ["m", "0"] and len(mappings) == 2
    report = json.loads((tmp_path / "m" / "sfm.json").read_text())
    [again] = report["shared_camera_again"]
    assert again["after"] == "triangulate" and again["taken"] and again["model_before"]["bogus_cameras"] == 0
    assert again["bogus_cameras"] == 5 and again["bogus_cameras_again"] == 0 and again["mapper"] == "incremental"
    assert report["models"][0]["folder"] == "shared-camera/0/sparse/0" and report["model"]["bogus_cameras"] == 0
    assert report["model"]["points"] > report["model_before_triangulation"]["points"] == again["points_again"]
    assert sfm.bogus_cameras(pycolmap.Reconstruction(str(tmp_path / "m" / "shared-camera/0/sparse/0"))) == []


def test_one_camera_per_folder_fits_images_of_one_size_without_exif(tmp_path):
    """What a bogus model's repair checks before it maps again: one size a folder, no EXIF focal length (a
    prior of the image's own; photos of several cameras often carry one)."""
    from PIL import Image

    from dqm.vision.colmap import shared_camera_unfit

    rng = np.random.default_rng(0)
    for folder, size in (("a", (160, 120)), ("b", (200, 150))):
        (tmp_path / folder).mkdir()
        for k in range(2):
            Image.fromarray(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)).save(
                tmp_path / folder / f"{k}.png")
    pngs = sorted(tmp_path.glob("*/*.png"))
    assert shared_camera_unfit(pngs) is None  # a camera a folder: each folder one size
    Image.fromarray(rng.integers(0, 255, (150, 200, 3), dtype=np.uint8)).save(tmp_path / "a" / "2.png")
    assert "needs one image size: a/0.png is 160x120, a/2.png is 200x150" in shared_camera_unfit(
        [*pngs, tmp_path / "a" / "2.png"])
    exif = Image.Exif()
    exif.get_ifd(0x8769)[41989] = 28  # focal length in 35 mm film
    Image.open(tmp_path / "a" / "1.png").convert("RGB").save(tmp_path / "a" / "1.jpg", exif=exif)
    assert shared_camera_unfit([tmp_path / "a" / "0.png", tmp_path / "a" / "1.jpg"]) == \
        "1 image (1.jpg, ...) with an EXIF focal length"


def test_colmaps_own_pipeline_with_one_camera_for_every_image(tmp_path):
    """The peer in scripts/bench_sfm.py, as a user runs COLMAP through pycolmap: its SIFT, exhaustive matching and
    incremental mapper, a camera per image by default and one for all with ``single_camera`` (bench_sfm's
    ``colmap --single-camera``, beside ``dqm sfm --single-camera`` on a video's frames)."""
    from generators.scenes3d import generate_scene3d

    from dqm.vision.sfm import colmap_pipeline

    images = generate_scene3d(seed=2, n_images=4).save(tmp_path / "img")
    for single, cameras in ((False, 4), (True, 1)):
        models, times = colmap_pipeline(images, tmp_path / f"colmap-{single}", seed=0, single_camera=single)
        rec = models[0].rec
        assert rec.num_reg_images() == 4 and rec.num_points3D() > 100, rec.summary()
        assert len(rec.cameras) == cameras and set(times) == {"extract", "match", "map"}


def test_a_model_the_mapper_left_without_a_point_is_left_out(tmp_path, capsys, monkeypatch):
    """COLMAP's incremental mapper left cmu_hotel's frames 54, 56 and 61 (--single-camera) in a model with no 3-D
    point beside the model of all 101 frames; dqm sfm reported two models, '3 images in more than one', and made
    that model again alone. Registered images without structure are no model: left out with a warning, its
    folder kept. (Such a model is made here from the mapper's own: these generated scenes give none.)"""
    import pycolmap
    from generators.scenes3d import generate_scene3d

    images = generate_scene3d(seed=0, n_images=5, width=480, height=360).save(tmp_path / "img")
    real = pycolmap.incremental_mapping

    def with_a_model_without_points(database, image_dir, out, *args, **kwargs):
        recs = real(database, image_dir, out, *args, **kwargs)
        empty = pycolmap.Reconstruction(str(Path(out) / "0"))
        for point_id in list(empty.point3D_ids()):
            empty.delete_point3D(point_id)
        (Path(out) / "1").mkdir()
        empty.write(str(Path(out) / "1"))
        return {**recs, 1: empty}

    monkeypatch.setattr(pycolmap, "incremental_mapping", with_a_model_without_points)
    assert main(["sfm", str(images), "--out", str(tmp_path / "m"), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "model" in captured.err and "(5 images) has no 3-D point: left out" in captured.err
    assert "5 of 5 images registered" in captured.out and "2 models" not in captured.out
    report = json.loads((tmp_path / "m" / "sfm.json").read_text())
    assert [m["folder"] for m in report["models"]] == ["sparse/0"] and report["model"]["points"] > 100
    assert (tmp_path / "m" / "sparse" / "1" / "images.bin").exists()  # what the mapper wrote stays


def test_dqm_sfm_one_camera_per_folder(tmp_path, capsys):
    """--single-camera-per-folder (COLMAP's ImageReader.single_camera_per_folder): a video a folder, each folder's
    frames one camera; --single-camera one for all; both at once refused before any work."""
    import pycolmap
    from generators.scenes3d import generate_scene3d

    for name, seed in (("one", 2), ("two", 5)):
        generate_scene3d(seed=seed, n_images=4, width=480, height=360).save(tmp_path / "photos" / name)
    photos = str(tmp_path / "photos")
    for flag, cameras in (("--single-camera-per-folder", 2), ("--single-camera", 1)):
        out = tmp_path / flag.strip("-")
        assert main(["sfm", photos, "--recursive", "--out", str(out), flag, "--no-triangulate", "--quiet"]) == 0
        db = pycolmap.Database.open(str(out / "database.db"))
        try:
            images = db.read_all_images()
            assert len(images) == 8 and len({im.camera_id for im in images}) == cameras
            if cameras == 2:
                for folder in ("one", "two"):
                    assert len({im.camera_id for im in images if im.name.startswith(folder + "/")}) == 1
        finally:
            db.close()
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main(["sfm", photos, "--out", str(tmp_path / "both"), "--single-camera", "--single-camera-per-folder"])
    assert "not allowed with argument" in capsys.readouterr().err and not (tmp_path / "both").exists()
    # a folder whose frames differ in size cannot share a camera: one line before any work (it came after the
    # extraction and QuickMatch, from the export)
    import cv2

    first = sorted((tmp_path / "photos" / "two").glob("*.png"))[0]
    cv2.imwrite(str(first), cv2.resize(cv2.imread(str(first)), None, fx=0.5, fy=0.5))
    assert main(["sfm", photos, "--recursive", "--out", str(tmp_path / "sizes"), "--single-camera-per-folder"]) == 2
    captured = capsys.readouterr()
    assert "one camera for the images of folder 'two' needs one image size" in captured.err
    assert captured.err.count("\n") == 1 and "SIFT" not in captured.out and not (tmp_path / "sizes").exists()


def test_dqm_sfm_log_spaced_cluster_matches(tmp_path, capsys):
    """--cluster-matches log hands the mapper each cluster as fewer matches (one track still) and registers every
    image of a generated scene; the option is in sfm.json; dqm export colmap takes it too (not given there: None,
    which the export reads as DEFAULT_CLUSTER_MATCHES, auto, as dqm sfm's default is)."""
    import pycolmap
    from generators.scenes3d import generate_scene3d

    images = generate_scene3d(seed=0, n_images=6).save(tmp_path / "img")
    written = {}
    for how in ("all", "log"):
        assert main(["sfm", str(images), "--out", str(tmp_path / how), "--cluster-matches", how, "--quiet"]) == 0
        out = capsys.readouterr().out
        written[how] = int(re.search(r"([\d,]+) matches in", out).group(1).replace(",", ""))
        report = json.loads((tmp_path / how / "sfm.json").read_text())
        assert report["options"]["cluster_matches"] == how and report["model"]["registered"] == 6
        assert report["pairs"]["matches"] == written[how] and (report["pairs"]["log_spaced_clusters"] > 0) == (
            how == "log")
    assert written["log"] < written["all"]  # the pairs with 15 matches or more (COLMAP verifies no fewer)
    from dqm.cli import build_parser

    parser = build_parser()  # auto, the default of every command: a video's tracks log-spaced, every other as all
    assert parser.parse_args(["sfm", str(images), "--out", "x"]).cluster_matches == "auto"
    assert parser.parse_args(["export", "colmap", "c.npz", "--database", "d.db"]).cluster_matches == "auto"
    assert parser.parse_args(["export", "hloc", "c.npz", "--matches", "m.h5", "--pairs", "p.txt"]).cluster_matches \
        == "auto"
    sizes = np.bincount(load_clusters(tmp_path / "log" / "clusters.npz")["labels"])
    assert sizes.max() >= 4  # clusters where log-spaced matches are fewer than every two members
    for how, want in (("all", sum(s * (s - 1) // 2 for s in sizes)),
                      ("log", sum(sum(s - d for d in (1, 2, 4) if d < s) for s in sizes))):
        db_path = tmp_path / f"export-{how}.db"  # every pair written, none verified: each cluster's matches
        assert main(["export", "colmap", str(tmp_path / "log" / "clusters.npz"), "--database", str(db_path),
                     "--cluster-matches", how, "--no-verify", "--quiet"]) == 0
        db = pycolmap.Database.open(str(db_path))
        try:
            assert db.num_matches() == want, how
        finally:
            db.close()
