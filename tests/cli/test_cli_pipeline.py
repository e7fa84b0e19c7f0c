"""End to end on the command line: dqm scene -> dqm match (images) -> dqm plot / dqm evaluate."""
import csv
import json

import numpy as np
import pytest
from conftest import assert_consistent

import dqm
from dqm import io, plots
from dqm.cli import main
from dqm.evaluation import PRCurve
from dqm.vision import scenes


def png_ok(path):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000, path
    return True


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory):
    root = tmp_path_factory.mktemp("pipeline")
    assert main(["scene", str(root / "scene"), "--images", "3", "--size", "240", "320", "--seed", "5"]) == 0
    rc = main(["match", str(root / "scene"), "--out", str(root / "clusters.npz"), "--quiet",
               "--max-features", "400", "--tracks-csv", str(root / "tracks.csv")])
    assert rc == 0
    return root


def test_match_images_writes_clusters_with_keypoints(pipeline):
    cl = io.load_clusters(pipeline / "clusters.npz")
    assert cl["keypoints"].shape == (len(cl["labels"]), 4)
    assert [n.rsplit("/", 1)[-1] for n in cl["image_names"].tolist()] == ["img1.png", "img2.png", "img3.png"]
    assert np.bincount(cl["image_ids"]).max() <= 410
    assert_consistent(cl["labels"], cl["image_ids"])
    assert cl["params"]["rho"] == dqm.DEFAULT_RHO


def test_tracks_csv_lists_every_multi_image_cluster(pipeline):
    cl = io.load_clusters(pipeline / "clusters.npz")
    rows = list(csv.DictReader(open(pipeline / "tracks.csv")))
    sizes = np.bincount(cl["labels"])
    assert len(rows) == int(sizes[sizes >= 2].sum())
    assert len({r["track"] for r in rows}) == int((sizes >= 2).sum())
    r = rows[0]
    f = int(r["feature"])
    assert int(r["label"]) == cl["labels"][f] and int(r["image_id"]) == cl["image_ids"][f]
    assert float(r["x"]) == pytest.approx(cl["keypoints"][f, 0], abs=1e-3)
    assert r["image"].endswith(".png")


def test_plot_commands(pipeline, capsys):
    out = pipeline / "plots"
    assert main(["plot", "pair", str(pipeline / "clusters.npz"), "--images", "0", "2",
                 "--truth", str(pipeline / "scene"), "--out", str(out / "pair.png")]) == 0
    assert "matches" in capsys.readouterr().out
    assert main(["plot", "clusters", str(pipeline / "clusters.npz"), "--out", str(out / "clusters.png"),
                 "--count", "3"]) == 0
    assert main(["plot", "sizes", str(pipeline / "clusters.npz"), "--out", str(out / "sizes.png")]) == 0
    for name in ("pair.png", "clusters.png", "sizes.png"):
        assert png_ok(out / name)


def test_evaluate_and_plot_pr(pipeline, capsys):
    out = pipeline / "eval"
    rc = main(["evaluate", str(pipeline / "scene"), "--out-dir", str(out), "--quiet",
               "--methods", "quickmatch,bf,bf-drop-track", "--rhos", "0.5,1.0", "--ratios", "0.6,0.9",
               "--max-features", "400"])
    assert rc == 0
    md = (out / "evaluation.md").read_text()
    assert "| scene (" in md and "BF tracks, drop track (OpenMVG)" in md and "FLANN" not in md.split("## Results")[1]
    data = json.loads((out / "evaluation.json").read_text())
    rows = data["datasets"]["scene"]["methods"]
    assert [r["method"] for r in rows] == ["quickmatch", "bf", "bf-drop-track"]
    assert PRCurve.from_dict(rows[0]["curve"]).thresholds.tolist() == sorted([0.5, dqm.DEFAULT_RHO, 1.0])
    assert png_ok(out / "pr_scene.png")
    capsys.readouterr()
    assert main(["plot", "pr", str(out / "evaluation.json"), "--out-dir", str(out / "again")]) == 0
    assert png_ok(out / "again" / "pr_scene.png")


def test_command_line_errors_are_one_clear_line(tmp_path, pipeline, capsys):
    def err(argv):
        assert main(argv) == 2
        return capsys.readouterr().err

    assert "input not found" in err(["match", str(tmp_path / "missing.png"), str(tmp_path / "b.png"),
                                     "--out", str(tmp_path / "o.npz")])
    assert "at least 2 images" in err(["match", str(pipeline / "scene" / "img1.png"), "--out",
                                       str(tmp_path / "o.npz"), "--quiet"])
    (tmp_path / "empty.png").write_bytes(b"")
    assert "cannot read image" in err(["match", str(pipeline / "scene" / "img1.png"), str(tmp_path / "empty.png"),
                                       "--out", str(tmp_path / "o.npz"), "--quiet"])
    assert "unknown method" in err(["evaluate", "scene", "--methods", "quickmatch,orb", "--out-dir",
                                    str(tmp_path)])
    assert "not found" in err(["evaluate", str(tmp_path / "nothing"), "--out-dir", str(tmp_path)])
    assert "not found" in err(["plot", "sizes", str(tmp_path / "nope.npz"), "--out", str(tmp_path / "x.png")])
    assert "out of range" in err(["plot", "pair", str(pipeline / "clusters.npz"), "--images", "0", "7",
                                  "--out", str(tmp_path / "x.png")])
    assert "not a dqm evaluate JSON" in err(["plot", "pr", str(pipeline / "clusters.npz"),
                                             "--out-dir", str(tmp_path)])
    assert not (tmp_path / "o.npz").exists()


def test_plot_functions_directly():
    sc = scenes.generate_scene(2, (120, 160), seed=1)
    xy = np.array([[10.0, 20.0], [50.0, 60.0]])
    png = plots.pair_figure(sc.images[0], sc.images[1], xy, xy + 1, np.array([True, False]))
    assert "2 matches, 1 correct" in png.axes[0].get_title()
    with pytest.raises(Exception, match="one row per match"):
        plots.pair_figure(sc.images[0], sc.images[1], xy, xy[:1])
    fig = plots.clusters_figure(sc.images, np.c_[xy, [8.0, 8.0]], np.array([0, 1]), [np.array([0, 1])],
                                point_ids=np.array([3, 4]))
    mosaic = np.asarray(fig.axes[0].images[0].get_array())  # the patches as one image, in one axes
    assert len(fig.axes) == 1 and mosaic.shape[:2] == (2 * 32 + 1 + 16, 2 * (2 * 32 + 1 + 16) - 16 + 2)
    red = np.all(mosaic == (215, 48, 39), axis=-1)  # the second feature's point is not the cluster's: framed red
    assert red[:, mosaic.shape[1] // 2:].sum() > 4 * 65 and not red[:, :mosaic.shape[1] // 2].any()
    fig = plots.cluster_sizes_figure(np.array([0, 0, 1, 2, 2, 2]))
    assert "6 features, 3 clusters" in fig.axes[0].get_title()
    c = PRCurve("quickmatch", "rho", np.array([0.5, 1.0]), np.array([0.9, 0.7]), np.array([0.3, 0.5]))
    fig = plots.pr_figure([c], {"quickmatch": (0.3, 0.9)}, labels={"quickmatch": "QuickMatch"})
    assert "QuickMatch (AUC" in fig.axes[0].get_legend().get_texts()[0].get_text()
