"""dqm export: COLMAP camera options (model, shared cameras, parameters) and the hloc export (matches, pairs,
features), read back as hloc reads them and reconstructed by pycolmap."""
import dataclasses

import cv2
import numpy as np
import pytest

import dqm
from dqm import InputError, io, synthetic
from dqm.cli import main

pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is not installed (pip install 'dqm[colmap]')")
h5py = pytest.importorskip("h5py", reason="h5py is not installed (pip install 'dqm[colmap]')")

from dqm.vision import colmap, hloc

#: the small image set: name -> (width, height); two folders, one image of another size
IMAGES = {"s1/a.png": (64, 48), "s1/b.png": (64, 48), "s2/c.png": (80, 60)}


@pytest.fixture(scope="module")
def clusters(tmp_path_factory):
    """QuickMatch clusters of generated descriptors on three small image files (random keypoints inside them)."""
    root = tmp_path_factory.mktemp("export")
    rng = np.random.default_rng(1)
    paths = []
    for name, (w, h) in IMAGES.items():
        p = root / "images" / name
        p.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(p), rng.integers(0, 255, (h, w), dtype=np.uint8))
        paths.append(p)
    ds = synthetic.sift_like(n_images=3, n_points=60, clutter_per_image=15, seed=2)
    r = dqm.quickmatch(ds.descriptors, ds.image_ids)
    kp = np.zeros((len(ds), 4), np.float32)
    for k, (w, h) in enumerate(IMAGES.values()):
        rows = np.flatnonzero(ds.image_ids == k)
        kp[rows, :2] = rng.uniform([0, 0], [w - 1, h - 1], (len(rows), 2))
        kp[rows, 2], kp[rows, 3] = rng.uniform(2, 9, len(rows)), rng.uniform(0, 360, len(rows))
    fs = io.FeatureSet(descriptors=ds.descriptors, image_ids=ds.image_ids, keypoints=kp,
                       image_names=np.array([str(p) for p in paths]))
    io.save_clusters(root / "clusters.npz", fs, r)
    return {"root": root, "paths": paths, "fs": fs, "labels": r.labels, "file": root / "clusters.npz"}


def reference_matches(labels, ids):
    """Every two members of every cluster, by image pair (lower image first), as sets of feature pairs."""
    out = {}
    for lab in np.unique(labels):
        m = sorted(np.flatnonzero(labels == lab).tolist(), key=lambda f: ids[f])
        for x in range(len(m)):
            for y in range(x + 1, len(m)):
                out.setdefault((int(ids[m[x]]), int(ids[m[y]])), set()).add((m[x], m[y]))
    return out


def test_camera_options_are_checked_in_one_line():
    assert colmap.camera_options() == colmap.CameraOptions("SIMPLE_RADIAL", "per-image", None)
    assert colmap.camera_options("opencv", "single", "500, 510, 320, 240, 0.01, 0, 0, 0").params == \
        (500.0, 510.0, 320.0, 240.0, 0.01, 0.0, 0.0, 0.0)
    assert colmap.camera_options("PINHOLE", params=[400, 400, 32, 24]).params == (400.0, 400.0, 32.0, 24.0)
    bad = [(("FISHEYE_9000",), "not a COLMAP camera model; use one of SIMPLE_PINHOLE, PINHOLE"),
           (("PINHOLE", "per-image", "400,400,32"), r"PINHOLE has 4 parameters \(fx, fy, cx, cy\), got 3"),
           (("SIMPLE_RADIAL", "per-image", "f,1,2,3"), "give 4 comma-separated numbers"),
           (("SIMPLE_PINHOLE", "per-image", "-5,32,24"), "focal length f must be positive"),
           (("SIMPLE_PINHOLE", "per-image", "nan,32,24"), "must be finite"),
           (("PINHOLE", "per-rig"), "camera mode 'per-rig'")]
    for args, msg in bad:
        with pytest.raises(InputError, match=msg) as exc:
            colmap.camera_options(*args)
        assert "\n" not in str(exc.value)


def read_cameras(db_path):
    db = pycolmap.Database.open(str(db_path))
    try:
        images = sorted(db.read_all_images(), key=lambda im: im.image_id)
        cams = {im.name: db.read_camera(im.camera_id) for im in images}
        return cams, db.num_cameras(), db.num_rigs(), db.num_frames()
    finally:
        db.close()


def test_colmap_export_shares_cameras_as_colmap_image_reader(clusters, tmp_path):
    c = clusters
    args = (c["fs"].keypoints, c["fs"].image_ids, c["paths"], c["labels"])
    colmap.export_database(tmp_path / "each.db", *args, verify=False)
    cams, n_cams, n_rigs, n_frames = read_cameras(tmp_path / "each.db")
    assert (n_cams, n_rigs, n_frames) == (3, 3, 3)
    assert cams["s2/c.png"].model_name == "SIMPLE_RADIAL" and (cams["s2/c.png"].width, cams["s2/c.png"].height) == \
        (80, 60)
    assert cams["s2/c.png"].focal_length == pytest.approx(1.2 * 80) and not cams["s2/c.png"].has_prior_focal_length

    s = colmap.export_database(tmp_path / "folder.db", *args, verify=False,
                               camera=colmap.camera_options("OPENCV", "per-folder"))
    cams, n_cams, n_rigs, n_frames = read_cameras(tmp_path / "folder.db")
    assert (s.n_cameras, n_cams, n_rigs, n_frames) == (2, 2, 2, 3)
    assert cams["s1/a.png"].camera_id == cams["s1/b.png"].camera_id != cams["s2/c.png"].camera_id
    assert cams["s1/a.png"].model_name == "OPENCV"
    np.testing.assert_allclose(cams["s1/a.png"].params, [1.2 * 64, 1.2 * 64, 32, 24, 0, 0, 0, 0])

    # one camera for images of two sizes: refused before the database exists
    with pytest.raises(InputError, match=r"one camera for all images needs one image size: s1/a.png is 64x48, "
                                         r"s2/c.png is 80x60"):
        colmap.export_database(tmp_path / "single.db", *args, verify=False, camera=colmap.camera_options(
            mode="single"))
    assert not (tmp_path / "single.db").exists()

    # the two images of one size under one camera with given parameters (a prior, as COLMAP marks them)
    first = np.isin(c["fs"].image_ids, [0, 1])
    s = colmap.export_database(tmp_path / "single.db", c["fs"].keypoints[first], c["fs"].image_ids[first],
                               c["paths"][:2], c["labels"][first], verify=False,
                               camera=colmap.camera_options("pinhole", "single", "70,71,31.5,23.5"))
    cams, n_cams, n_rigs, n_frames = read_cameras(tmp_path / "single.db")
    assert (s.n_cameras, n_cams, n_rigs, n_frames) == (1, 1, 1, 2)
    cam = cams["a.png"]
    assert cam.model_name == "PINHOLE" and cam.has_prior_focal_length
    np.testing.assert_array_equal(cam.params, [70, 71, 31.5, 23.5])


def test_export_cli_refuses_bad_options_before_any_work(clusters, tmp_path, capsys):
    f = str(clusters["file"])
    db = tmp_path / "db.db"
    cases = [
        (["colmap", f, "--database", str(db), "--camera-model", "FOO"], "--camera-model FOO: not a COLMAP camera"),
        (["colmap", f, "--database", str(db), "--camera-params", "1,2"], "SIMPLE_RADIAL has 4 parameters"),
        (["colmap", f, "--database", str(db), "--matches", str(tmp_path / "m.h5")],
         "--matches is an option of dqm export hloc, not of dqm export colmap"),
        (["colmap", f], "dqm export colmap needs one of --database"),
        (["hloc", f, "--matches", str(tmp_path / "m.h5")], "dqm export hloc needs --pairs"),
        (["hloc", f, "--matches", str(tmp_path / "m.h5"), "--pairs", str(tmp_path / "p.txt"), "--single-camera"],
         "--single-camera is an option of dqm export colmap"),
        (["hloc", f, "--matches", str(tmp_path / "x.h5"), "--pairs", str(tmp_path / "x.h5")],
         "--pairs " + str(tmp_path / "x.h5") + ": unknown format .h5; use one of .txt"),
        (["colmap", f, "--database", str(db), "--partners", "-3"], "--partners must be >= 0"),
        (["hloc", f, "--matches", str(tmp_path / "m.h5"), "--pairs", str(tmp_path / "p.txt"), "--partners", "3"],
         "--partners is an option of dqm export colmap"),
    ]
    for argv, msg in cases:
        capsys.readouterr()
        assert main(["export"] + argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert msg in err and err.count("\n") == 0, err
    assert not any(tmp_path.iterdir())  # nothing written
    # an existing output is never replaced, and the other outputs are not written either
    (tmp_path / "p.txt").write_text("keep me\n")
    assert main(["export", "hloc", f, "--matches", str(tmp_path / "m.h5"), "--pairs", str(tmp_path / "p.txt")]) == 2
    assert "--pairs" in capsys.readouterr().err and (tmp_path / "p.txt").read_text() == "keep me\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.txt"]
    # clusters with two features of one image (not QuickMatch's: C2) would match an image with itself: refused
    labels, ids = clusters["labels"].copy(), clusters["fs"].image_ids
    a, b = np.flatnonzero(ids == 0)[:2]
    labels[b] = labels[a]
    twice = clusters["root"] / "twice.npz"
    io.write_clusters(twice, clusters["fs"], {"labels": labels}, {})
    for argv in (["colmap", str(twice), "--database", str(tmp_path / "t.db")],
                 ["hloc", str(twice), "--matches", str(tmp_path / "t.h5"), "--pairs", str(tmp_path / "t.txt")]):
        assert main(["export"] + argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert f"cluster {labels[a]} holds two features of image {clusters['paths'][0]} (rows {a} and {b}); dqm " \
               f"export {argv[0]} takes clusters of at most one feature an image" in err and err.count("\n") == 0, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.txt"]


def test_hloc_export_writes_every_cluster_pair_in_hlocs_layout(clusters, tmp_path, capsys):
    c, out = clusters, tmp_path / "hloc"
    assert main(["export", "hloc", str(c["file"]), "--matches", str(out / "matches.h5"), "--pairs",
                 str(out / "pairs.txt"), "--features", str(out / "features.h5"), "--tracks",
                 str(out / "tracks.csv")]) == 0
    assert f"3 images under {c['root'] / 'images'}" in capsys.readouterr().out
    names = list(IMAGES)  # relative to the images' common folder, '/'-separated
    ids, labels, kp = c["fs"].image_ids, c["labels"], c["fs"].keypoints
    start = [int(np.flatnonzero(ids == k)[0]) for k in range(3)]  # features are stored image by image
    want = reference_matches(labels, ids)
    assert len(want) == 3 and all(len(v) > 5 for v in want.values())

    lines = (out / "pairs.txt").read_text().splitlines()
    assert lines == [f"{names[a]} {names[b]}" for a, b in sorted(want)]
    with h5py.File(out / "matches.h5", "r") as fd:
        for line in lines:  # as hloc's get_matches: names_to_pair, matches0 != -1
            n0, n1 = line.split()
            grp = fd[n0.replace("/", "-") + "/" + n1.replace("/", "-")]
            a, b = names.index(n0), names.index(n1)
            m0, s0 = grp["matches0"][()], grp["matching_scores0"][()]
            assert m0.shape == s0.shape == ((ids == a).sum(),) and s0.dtype == np.float16
            idx = np.flatnonzero(m0 != -1)
            got = {(int(i) + start[a], int(j) + start[b]) for i, j in zip(idx, m0[idx])}
            assert got == want[(a, b)]
            assert all(labels[f] == labels[g] and ids[f] != ids[g] for f, g in got)
            np.testing.assert_array_equal(s0 == 1, m0 != -1)
            # dqm's reader finds the pair in either order, as hloc's find_pair
            np.testing.assert_array_equal(hloc.read_h5_matches(out / "matches.h5", n1, n0),
                                          hloc.read_h5_matches(out / "matches.h5", n0, n1)[:, ::-1])
    with h5py.File(out / "features.h5", "r") as fd:
        for k, name in enumerate(names):
            np.testing.assert_array_equal(fd[name]["keypoints"][()], kp[ids == k, :2])
            assert fd[name]["image_size"][()].tolist() == list(IMAGES[name])
    back = hloc.read_h5_features(out / "features.h5", names=names)
    np.testing.assert_array_equal(back.keypoints, kp)
    assert (out / "tracks.csv").exists()
    # run again: every output exists, so nothing is replaced
    assert main(["export", "hloc", str(c["file"]), "--matches", str(out / "m2.h5"), "--pairs",
                 str(out / "p2.txt"), "--features", str(out / "features.h5")]) == 2
    assert not (out / "m2.h5").exists() and not (out / "p2.txt").exists()


def test_hloc_export_takes_the_cluster_matches_rule(tmp_path, capsys):
    """dqm export hloc writes the matches that --cluster-matches names, as dqm export colmap does: a track of 24
    members through 24 frames gets its log-spaced matches under auto (the default) and log, every two under all;
    short clusters every two under each rule."""
    n_img = 24
    rng = np.random.default_rng(1)
    ids = np.repeat(np.arange(n_img), 5)
    labels = np.arange(len(ids))
    labels[ids * 5] = 0  # the first feature of every frame: one track through all 24 frames
    pair = np.flatnonzero(ids < 2) % 5 == 1
    labels[np.flatnonzero(ids < 2)[pair]] = 1  # the second feature of frames 0 and 1: a cluster of two
    images = tmp_path / "frames"
    images.mkdir()
    kp = np.c_[rng.uniform(0, 64, (len(ids), 2)), np.ones(len(ids)), np.zeros(len(ids))].astype(np.float32)
    fs = io.FeatureSet(descriptors=rng.normal(size=(len(ids), 8)).astype(np.float32), image_ids=ids, keypoints=kp,
                       image_names=np.array([str(images / f"f{k:02d}.jpg") for k in range(n_img)]))
    r = dqm.quickmatch(fs.descriptors, ids)
    io.save_clusters(tmp_path / "clusters.npz", fs, dataclasses.replace(r, labels=labels))
    names = [f"f{k:02d}.jpg" for k in range(n_img)]
    got = {}
    for rule in (None, "auto", "log", "all"):
        out = tmp_path / str(rule)
        argv = ["export", "hloc", str(tmp_path / "clusters.npz"), "--matches", str(out / "m.h5"), "--pairs",
                str(out / "p.txt"), "--image-dir", str(images)] + (["--cluster-matches", rule] if rule else [])
        assert main(argv) == 0
        want = colmap.cluster_pairs(labels, ids, rule or colmap.DEFAULT_CLUSTER_MATCHES)
        pairs = [tuple(line.split()) for line in (out / "p.txt").read_text().splitlines()]
        assert pairs == [(names[a], names[b]) for a, b in sorted(want)]
        got[rule] = {}
        for a, b in sorted(want):
            m = hloc.read_h5_matches(out / "m.h5", names[a], names[b])
            got[rule][(a, b)] = {(int(i) + 5 * a, int(j) + 5 * b) for i, j in m}
            assert got[rule][(a, b)] == {tuple(e) for e in want[(a, b)].tolist()}
        assert f"{sum(len(v) for v in want.values())} matches in {len(want)} image pairs" in capsys.readouterr().out
    n = {rule: sum(len(v) for v in g.values()) for rule, g in got.items()}
    assert got[None] == got["auto"] == got["log"] and n["all"] == n_img * (n_img - 1) // 2 + 1 > n["log"]
    assert got["all"][(0, 1)] == {(0, 5), (1, 6)} and got["auto"][(0, 1)] == got["all"][(0, 1)]


def test_hloc_names_must_survive_the_pairs_file_and_names_to_pair():
    assert hloc.names_to_pair("seq1/img0.jpg", "img1.jpg") == "seq1-img0.jpg/img1.jpg"
    assert hloc.check_pair_names(["seq1/a.jpg", "b.jpg"]) == ["seq1/a.jpg", "b.jpg"]
    with pytest.raises(InputError, match="holds white space"):
        hloc.check_pair_names(["my photo.jpg", "b.jpg"])
    with pytest.raises(InputError, match=r"'a/b.jpg' and 'a-b.jpg' get one hloc pair name"):
        hloc.check_pair_names(["a/b.jpg", "a-b.jpg"])
    with pytest.raises(InputError, match="relative path"):
        hloc.check_pair_names(["../up.jpg"])


def test_hloc_files_reconstruct_as_hloc_imports_them(tmp_path):
    """Clusters of generated descriptors at exact projections of 3-D points through 6 known cameras: the exported
    files, imported the way hloc.reconstruction does (keypoints + 0.5, matches by names_to_pair, COLMAP's
    verification over pairs.txt), give pycolmap a model of every image."""
    n_img, n_pts, (w, h), f = 6, 250, (640, 480), 500.0
    ds = synthetic.sift_like(n_images=n_img, n_points=n_pts, visibility=0.8, clutter_per_image=30, seed=3)
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-2, 2, n_pts), rng.uniform(-1.5, 1.5, n_pts), rng.uniform(5, 8, n_pts)]
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    kp = np.zeros((len(ds), 4), np.float32)
    for k in range(n_img):  # cameras on an arc, looking at (0, 0, 6.5)
        a = (k - (n_img - 1) / 2) * 0.08
        C = np.array([6.5 * np.sin(a), 0, 6.5 - 6.5 * np.cos(a)])
        z = (np.array([0, 0, 6.5]) - C) / np.linalg.norm(np.array([0, 0, 6.5]) - C)
        x = np.cross([0, 1, 0], z) / np.linalg.norm(np.cross([0, 1, 0], z))
        R = np.stack([x, np.cross(z, x), z])
        rows = np.flatnonzero(ds.image_ids == k)
        pid = ds.point_ids[rows]
        Xc = (X[np.maximum(pid, 0)] - C) @ R.T
        uv = (Xc @ K.T)[:, :2] / Xc[:, 2:3]  # COLMAP's pixel convention (top-left centre at 0.5)
        uv[pid < 0] = rng.uniform([0, 0], [w, h], (int((pid < 0).sum()), 2))  # clutter
        kp[rows, :2] = uv + rng.normal(0, 0.3, uv.shape) - 0.5
    r = dqm.quickmatch(ds.descriptors, ds.image_ids)
    images = tmp_path / "images"
    images.mkdir()
    rel = [f"cam{k % 2}/view{k}.jpg" for k in range(n_img)]
    fs = io.FeatureSet(descriptors=ds.descriptors, image_ids=ds.image_ids, keypoints=kp,
                       image_names=np.array([str(images / n) for n in rel]))
    io.save_clusters(tmp_path / "clusters.npz", fs, r)
    assert main(["export", "hloc", str(tmp_path / "clusters.npz"), "--matches", str(tmp_path / "matches.h5"),
                 "--pairs", str(tmp_path / "pairs.txt"), "--features", str(tmp_path / "features.h5"),
                 "--image-dir", str(images)]) == 0

    db_path = tmp_path / "database.db"
    db = pycolmap.Database.open(str(db_path))
    image_ids = {}
    with h5py.File(tmp_path / "features.h5", "r") as fd:
        for name in rel:  # hloc.reconstruction: import_images (COLMAP's reader), then import_features
            cam = pycolmap.Camera.create_from_model_name(0, "PINHOLE", f, w, h)
            cam.camera_id = db.write_camera(cam)
            rig = pycolmap.Rig()
            rig.add_ref_sensor(cam.sensor_id)
            rig_id = db.write_rig(rig)
            image_ids[name] = db.write_image(pycolmap.Image(name=name, camera_id=cam.camera_id))
            frame = pycolmap.Frame()
            frame.rig_id = rig_id
            frame.add_data_id(pycolmap.data_t(sensor_id=cam.sensor_id, id=image_ids[name]))
            db.write_frame(frame)
            db.write_keypoints(image_ids[name], fd[name]["keypoints"][()] + 0.5)
    with h5py.File(tmp_path / "matches.h5", "r") as fd:  # import_matches
        for line in (tmp_path / "pairs.txt").read_text().splitlines():
            n0, n1 = line.split()
            m0 = fd[n0.replace("/", "-") + "/" + n1.replace("/", "-")]["matches0"][()]
            idx = np.flatnonzero(m0 != -1)
            db.write_matches(image_ids[n0], image_ids[n1], np.stack([idx, m0[idx]], -1))
    db.close()
    pycolmap.verify_matches(str(db_path), str(tmp_path / "pairs.txt"))  # estimation_and_geometric_verification
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = 1
    (tmp_path / "sparse").mkdir()
    recs = pycolmap.incremental_mapping(str(db_path), str(images), str(tmp_path / "sparse"), options=opts)
    best = max(recs.values(), key=lambda rec: rec.num_reg_images())
    assert best.num_reg_images() == n_img
    assert best.num_points3D() > 0.8 * n_pts
    assert best.compute_mean_reprojection_error() < 1.0
