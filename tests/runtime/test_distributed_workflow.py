"""The workflow the distributed runtime exists for (issue 21): robots that each extract their own
images, then run agents; the job's clusters must be the centralized ones, flow into a CLUSTERS
file that plot / export / evaluate read, and two jobs must not share a job id silently."""
import json
import subprocess
import sys
import time

import numpy as np
import pytest

import dqm
from dqm import io
from dqm.cli import main
from dqm.distributed import DQMConfig, simulate
from dqm.distributed.sources import agent_features, assemble_clusters, split_features
from dqm.runtime.bus import live_tokens, open_client
from dqm.runtime.launcher import Processes, free_port
from dqm.runtime.multihost import finish_job, start_job, start_router
from dqm.synthetic import sift_like

pytest.importorskip("zenoh")


def robot_files(tmp_path, ds, groups):
    """One FEATURES file per robot, as `dqm extract` writes them: each numbers its own images 0, 1, ...
    (with image names and keypoints). Returns the paths and the images' true global ids per row."""
    rng = np.random.default_rng(0)
    kp = rng.uniform(0, 500, size=(len(ds.image_ids), 4)).astype(np.float32)
    paths, order = [], []
    for r, images in enumerate(groups):
        rows = np.flatnonzero(np.isin(ds.image_ids, images))
        local = np.searchsorted(images, ds.image_ids[rows])
        p = tmp_path / f"robot{r}.npz"
        io.save_features(p, io.FeatureSet(ds.descriptors[rows], local, keypoints=kp[rows],
                                          image_names=np.array([f"robot{r}/img{k}.png" for k in range(len(images))]),
                                          point_ids=ds.point_ids[rows]))
        paths.append(p)
        order.append(rows)
    return paths, np.concatenate(order), kp


def test_agents_numbering_their_images_alike_give_the_centralized_clusters(tmp_path):
    ds = sift_like(n_images=6, n_points=150, clutter_per_image=60, noise=0.3, seed=3)
    paths, rows, kp = robot_files(tmp_path, ds, [np.array([0, 1, 2]), np.array([3, 4, 5])])
    X, true_ids = ds.descriptors[rows], ds.image_ids[rows]
    expected = dqm.quickmatch(X, true_ids, kernel="quadratic").labels
    # the data is such that taking the colliding numbers for the images would change the clusters
    colliding = np.concatenate([np.searchsorted([0, 1, 2], true_ids[true_ids < 3]),
                                np.searchsorted([3, 4, 5], true_ids[true_ids >= 3])])
    assert not np.array_equal(dqm.quickmatch(X, colliding, kernel="quadratic").labels, expected)

    cfg = DQMConfig(agents=2, seed=1, job="robots")
    port = free_port()
    procs = Processes()
    clusters = tmp_path / "out" / "clusters.npz"
    try:
        start_router(procs, [f"tcp/127.0.0.1:{port}"], tmp_path, ("127.0.0.1", port))
        (tmp_path / "report.failure.json").write_text('{"what": "an earlier job\'s failure"}')
        job = start_job(procs, cfg, paths, tmp_path, connect=lambda a: f"tcp/127.0.0.1:{port}", clusters=clusters)
        assert not (tmp_path / "report.failure.json").exists()  # not read as this job's if its coordinator dies
        rep = finish_job(job, 90)
    finally:
        procs.stop_all()
    assert rep["agent_exit_codes"] == [0, 0]
    np.testing.assert_array_equal(np.asarray(rep["labels"]), expected)
    assert "image id(s) 0, 1, 2 are used by more than one FEATURES file (agents 0, 1)" in rep["images_note"]
    c = io.load_clusters(clusters)
    np.testing.assert_array_equal(c["labels"], expected)
    np.testing.assert_array_equal(c["image_ids"], true_ids)  # numbered agent after agent: 0..2, then 3..5
    assert [str(n) for n in c["image_names"]] == [f"robot{r}/img{k}.png" for r in range(2) for k in range(3)]
    np.testing.assert_array_equal(c["keypoints"], kp[rows])
    np.testing.assert_array_equal(c["point_ids"], ds.point_ids[rows])
    assert c["params"]["distributed"] and c["params"]["agents"] == 2 and "descriptors" not in c
    # the same split, simulated: the runtime's names for the images are the simulator's
    np.testing.assert_array_equal(simulate(X, true_ids, cfg).labels, expected)


def test_catalogs_keep_image_ids_that_do_not_collide():
    ds = sift_like(n_images=5, n_points=60, seed=1)
    fs = io.FeatureSet(ds.descriptors, ds.image_ids, image_names=np.array([f"im{k}" for k in range(5)]),
                       point_ids=ds.point_ids)
    parts = split_features(fs, 2)
    held = [agent_features([p], a) for a, p in enumerate(parts)]
    labels = np.arange(len(fs)) % 7
    out = assemble_clusters(np.arange(len(fs)), labels, {a: h.catalog for a, h in enumerate(held)})
    assert out.note == ""
    np.testing.assert_array_equal(out.features.image_ids, ds.image_ids)  # global ids stay
    assert [str(n) for n in out.features.image_names] == [f"im{k}" for k in range(5)]
    np.testing.assert_array_equal(out.features.point_ids, ds.point_ids)
    # wire image ids name the source: no two agents share one
    assert not set(held[0].image_ids.tolist()) & set(held[1].image_ids.tolist())


def test_split_keeps_keypoints_names_and_feature_ids(tmp_path, capsys):
    ds = sift_like(n_images=5, n_points=80, seed=2)
    kp = np.random.default_rng(1).uniform(0, 99, (len(ds.image_ids), 4)).astype(np.float32)
    names = np.array([f"/data/cam/img{k}.jpg" for k in range(5)])
    src = tmp_path / "all.npz"
    io.save_features(src, io.FeatureSet(ds.descriptors, ds.image_ids, kp, names, ds.point_ids))
    assert main(["split", str(src), "--agents", "2", "--out", str(tmp_path / "s")]) == 0
    assert "dqm agent --id 0 --agents 2" in capsys.readouterr().out
    parts = [io.load_features(tmp_path / "s" / f"agent{a}.npz") for a in range(2)]
    assert [sorted(np.unique(p.image_ids).tolist()) for p in parts] == [[0, 2, 4], [1, 3]]
    fid = np.concatenate([p.feature_ids for p in parts])
    assert sorted(fid.tolist()) == list(range(len(ds.image_ids)))
    for p in parts:
        np.testing.assert_array_equal(p.keypoints, kp[p.feature_ids])
        np.testing.assert_array_equal(p.descriptors, ds.descriptors[p.feature_ids])
        np.testing.assert_array_equal(p.point_ids, ds.point_ids[p.feature_ids])
        assert list(p.image_names) == list(names)
    # by lists of images: ids, paths or file names
    (tmp_path / "l0.txt").write_text("# robot 0\n0\nimg3.jpg\n")
    (tmp_path / "l1.txt").write_text("/data/cam/img1.jpg\n2\n\n4\n")
    assert main(["split", str(src), "--image-lists", str(tmp_path / "l0.txt"), str(tmp_path / "l1.txt"),
                 "--out", str(tmp_path / "t")]) == 0
    got = [sorted(np.unique(io.load_features(tmp_path / "t" / f"agent{a}.npz").image_ids).tolist()) for a in range(2)]
    assert got == [[0, 3], [1, 2, 4]]
    (tmp_path / "bad.txt").write_text("0\nnot-an-image.jpg\n")
    capsys.readouterr()
    assert main(["split", str(src), "--image-lists", str(tmp_path / "bad.txt"), str(tmp_path / "l1.txt"),
                 "--out", str(tmp_path / "u")]) == 2
    err = capsys.readouterr().err
    assert "bad.txt:2" in err and "not-an-image.jpg" in err and len(err.strip().splitlines()) == 1
    assert main(["split", str(src), "--agents", "9", "--out", str(tmp_path / "v")]) == 2


def test_dqm_run_writes_clusters_that_plot_export_and_evaluate_read(tmp_path, capsys):
    scene = tmp_path / "scene"
    assert main(["scene", str(scene), "--images", "3", "--size", "240", "320", "--seed", "2"]) == 0
    feats = tmp_path / "f.npz"
    assert main(["extract", str(scene), "--out", str(feats), "--max-features", "300", "--quiet"]) == 0
    out = tmp_path / "run" / "clusters.npz"
    assert main(["run", "--agents", "2", "--features", str(feats), "--out", str(out),
                 "--report", str(tmp_path / "run.json")]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    central = tmp_path / "central.npz"
    assert main(["match", str(feats), "--out", str(central), "--kernel", "quadratic", "--quiet", "--no-guided"]) == 0
    c, m = io.load_clusters(out), io.load_clusters(central)
    np.testing.assert_array_equal(c["labels"], m["labels"])
    # one traffic ledger: the runtime sent what the simulator meters, catalogs included
    rep = json.loads((tmp_path / "run.json").read_text())
    fs = io.load_features(feats)
    sim = simulate(fs.descriptors, fs.image_ids, DQMConfig(agents=2), catalog=True, features=fs)
    assert {k: (v["bytes"], v["messages"]) for k, v in rep["kinds"].items()
            if k not in ("stats", "progress")} == sim.traffic.per_kind()
    assert rep["kinds"]["catalog"]["messages"] == 2
    for key in ("image_ids", "keypoints", "image_names"):
        np.testing.assert_array_equal(c[key], m[key])
    assert main(["plot", "clusters", str(out), "--out", str(tmp_path / "c.png")]) == 0
    assert main(["plot", "pair", str(out), "--out", str(tmp_path / "p.png")]) == 0
    assert main(["evaluate", "--clusters", str(out), str(scene), "--out-dir", str(tmp_path / "ev")]) == 0
    capsys.readouterr()
    # a JSON report is not a CLUSTERS file: one line that says so
    assert main(["plot", "sizes", str(tmp_path / "run.json"), "--out", str(tmp_path / "s.png")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "JSON" in err[0] and "not a CLUSTERS" in err[0], err
    pytest.importorskip("pycolmap")
    assert main(["export", "colmap", str(out), "--database", str(tmp_path / "db.db")]) == 0


def _cli_all(*commands, timeout=60):
    """Run several dqm commands at the same time; their completed processes (returncode, stdout, stderr)."""
    procs = [subprocess.Popen([sys.executable, "-m", "dqm", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for args in commands]
    done = []
    for p in procs:
        out, err = p.communicate(timeout=timeout)
        done.append(subprocess.CompletedProcess(p.args, p.returncode, out, err))
    return done


def test_a_second_job_under_a_live_job_id_is_refused_and_missing_agents_are_named(tmp_path):
    ds = sift_like(n_images=4, n_points=50, seed=0)
    f = tmp_path / "a.npz"
    io.save_features(f, io.FeatureSet(ds.descriptors, ds.image_ids))
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    procs = Processes()
    try:
        start_router(procs, [ep], tmp_path, ("127.0.0.1", port))
        agent = procs.start(["agent", "--id", "0", "--agents", "3", "--connect", ep, "--job", "busy", str(f)],
                            tmp_path / "agent0.log")
        coord = procs.start(["coordinator", "--agents", "3", "--connect", ep, "--job", "busy", "--ready-timeout", "6",
                             "--max-lost", "1", "--no-clusters"], tmp_path / "coordinator.log")
        watcher = open_client(ep)
        try:  # both are up (their tokens live) and waiting for the missing agents
            t0 = time.monotonic()
            while len(live_tokens(watcher, "dqm/busy/alive/**")) < 2 and time.monotonic() - t0 < 30:
                time.sleep(0.05)
        finally:
            watcher.close()
        # all three at once, well within the first coordinator's ready timeout
        second, twin, other = _cli_all(
            ["coordinator", "--agents", "3", "--connect", ep, "--job", "busy", "--no-clusters"],
            ["agent", "--id", "0", "--agents", "3", "--connect", ep, "--job", "busy", str(f)],
            ["coordinator", "--agents", "1", "--connect", ep, "--job", "other", "--ready-timeout", "1",
             "--no-clusters"])
        rc = coord.wait(timeout=30)
        agent.wait(timeout=30)
    finally:
        procs.stop_all()
    assert second.returncode == 2
    assert "the coordinator of job 'busy' is already running" in second.stderr, second.stderr
    assert twin.returncode == 2 and "agent 0 of job 'busy' is already running" in twin.stderr, twin.stderr
    assert "Traceback" not in second.stderr + twin.stderr
    assert other.returncode == 3  # another job id is free (and has no agents)
    assert rc == 3
    log = (tmp_path / "coordinator.log").read_text()
    assert "2 of 3 agent processes (1, 2) did not appear within the ready timeout of 6 s" in log, log
