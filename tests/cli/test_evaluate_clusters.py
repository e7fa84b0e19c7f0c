"""dqm evaluate --clusters: a CLUSTERS file scored by the code that scores the built-in QuickMatch row.

End to end on the command line: dqm scene -> dqm match -> dqm evaluate --clusters gives the
scores of benchmark.evaluate's QuickMatch row for the same features and settings; generated
descriptor sets are scored against their point_ids (also without descriptors / sigma /
density, as a distributed run may write them); a file that does not fit the data set is
refused with one line before anything is written.
"""
import json
import shutil

import numpy as np
import pytest

import dqm
from dqm import benchmark, evaluation, io, synthetic
from dqm.cli import main

MAX_FEATURES = 300


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A small generated scene on disk and its CLUSTERS files (plain, verified, grown) made by dqm match."""
    root = tmp_path_factory.mktemp("evalclusters")
    assert main(["scene", str(root / "scene"), "--images", "3", "--size", "240", "320", "--seed", "5"]) == 0
    # dqm evaluate's tables use the rootsift preset; dqm match on images defaults to sfm's
    for name, extra in (("clusters.npz", ["--no-guided"]), ("verified.npz", ["--verify"]), ("guided.npz", [])):
        assert main(["match", str(root / "scene"), "--out", str(root / name), "--quiet", "--preset", "rootsift",
                     "--max-features", str(MAX_FEATURES), *extra]) == 0
    return root


def _row(path):
    data = json.loads(path.read_text())
    (name, d), = data["datasets"].items()
    (row,) = d["methods"]
    return name, d, row


def test_match_then_evaluate_clusters_equals_the_builtin_quickmatch_row(scene, capsys):
    capsys.readouterr()
    out = scene / "out"
    assert main(["evaluate", "--clusters", str(scene / "clusters.npz"), str(scene / "scene"),
                 "--out-dir", str(out)]) == 0
    printed = capsys.readouterr().out
    bench = benchmark.load_benchmark(scene / "scene", max_features=MAX_FEATURES)
    rows = {r.method: r for r in benchmark.evaluate(bench, ["quickmatch", "quickmatch-verify", "quickmatch-guided"],
                                                    curves=False)}
    name, d, row = _row(out / "evaluation_clusters_scene.json")
    assert name == "scene" and d["kind"] == "homography" and d["n_features"] == len(bench)
    assert row["scores"] == rows["quickmatch"].scores.as_dict()
    assert row["violations"] == rows["quickmatch"].violations.as_dict()
    assert row["threshold"] == dqm.DEFAULT_RHO
    s = rows["quickmatch"].scores
    assert f"precision {s.precision:.3f}, recall {s.recall:.3f}, F1 {s.f1:.3f}" in printed
    assert "C1 features 0, C2 tracks 0" in printed and "| scene (" in printed
    # dqm match --verify against the built-in verified row: the same verification, the same scores
    assert main(["evaluate", "--clusters", str(scene / "verified.npz"), str(scene / "scene"),
                 "--out-dir", str(out)]) == 0
    _, _, row = _row(out / "evaluation_verified_scene.json")
    assert row["scores"] == rows["quickmatch-verify"].scores.as_dict()
    assert "verified" in row["label"]
    # dqm match on images grows the clusters by geometry by default: the built-in guided row
    assert main(["evaluate", "--clusters", str(scene / "guided.npz"), str(scene / "scene"),
                 "--out-dir", str(out)]) == 0
    _, _, row = _row(out / "evaluation_guided_scene.json")
    assert row["scores"] == rows["quickmatch-guided"].scores.as_dict()
    assert "guided" in row["label"]
    assert rows["quickmatch-guided"].scores.f1 > rows["quickmatch"].scores.f1


def test_generated_descriptors_are_scored_against_their_point_ids(tmp_path, capsys):
    ds = synthetic.sift_like(n_images=5, n_points=120, clutter_per_image=40, seed=4)
    io.save_features(tmp_path / "f.npz", io.FeatureSet(descriptors=ds.descriptors, image_ids=ds.image_ids,
                                                       point_ids=ds.point_ids))
    assert main(["match", str(tmp_path / "f.npz"), "--out", str(tmp_path / "c.npz"), "--quiet"]) == 0
    expected = evaluation.cluster_scores_landmarks(dqm.quickmatch(ds.descriptors, ds.image_ids).labels,
                                                   ds.point_ids, ds.image_ids)
    assert expected.n_truth > 0 and 0 < expected.f1 < 1
    assert main(["evaluate", "--clusters", str(tmp_path / "c.npz"), "--out-dir", str(tmp_path / "o")]) == 0
    _, d, row = _row(tmp_path / "o" / "evaluation_c.json")
    assert d["kind"] == "landmarks" and row["scores"] == expected.as_dict()
    # what a distributed run may write: labels, image ids, point ids and nothing else
    z = dict(np.load(tmp_path / "c.npz"))
    np.savez(tmp_path / "lean.npz", **{k: z[k] for k in ("labels", "image_ids", "point_ids")})
    assert main(["evaluate", "--clusters", str(tmp_path / "lean.npz"), "--out-dir", str(tmp_path / "o")]) == 0
    text = (tmp_path / "o" / "evaluation_lean.json").read_text()
    assert "NaN" not in text  # no rho recorded: null, strict JSON
    _, _, row = _row(tmp_path / "o" / "evaluation_lean.json")
    assert row["scores"] == expected.as_dict() and row["threshold"] is None


def test_a_file_that_does_not_fit_is_one_line_before_any_output(scene, tmp_path, capsys):
    def err(*argv):
        assert main(["evaluate", *argv, "--out-dir", str(tmp_path / "o")]) == 2
        e = capsys.readouterr().err
        assert e.count("\n") == 1 and "Traceback" not in e, e
        return e

    cl = str(scene / "clusters.npz")
    assert main(["scene", str(tmp_path / "four"), "--images", "4", "--size", "240", "320", "--seed", "5"]) == 0
    assert main(["scene", str(tmp_path / "big"), "--images", "3", "--size", "300", "400", "--seed", "5"]) == 0
    assert main(["scene", str(tmp_path / "tiny"), "--images", "3", "--size", "120", "160", "--seed", "5"]) == 0
    capsys.readouterr()
    assert "from 3 image(s), the data set has 4" in err("--clusters", cl, str(tmp_path / "four"))
    assert "is 320x240, the data set's is 400x300" in err("--clusters", cl, str(tmp_path / "big"))
    # the clusters' images are gone: their keypoints must still lie inside the data set's images
    moved = tmp_path / "moved.npz"
    shutil.copy(cl, moved)
    z = dict(np.load(moved))
    z["image_names"] = np.array([str(tmp_path / "gone" / f"img{k}.png") for k in (1, 2, 3)])
    np.savez(moved, **z)
    assert "keypoints of image 0 lie outside its 160x120 pixels" in err("--clusters", str(moved),
                                                                          str(tmp_path / "tiny"))
    assert "no point_ids" in err("--clusters", cl)
    assert "--rho, --preset do not apply" in err("--clusters", cl, str(scene / "scene"), "--rho", "0.5",
                                                 "--preset", "opencv")
    assert "one DATA set, got 2" in err("--clusters", cl, str(scene / "scene"), str(tmp_path / "four"))
    (tmp_path / "text.npz").write_text("not a zip")
    assert "not an .npz clusters file" in err("--clusters", str(tmp_path / "text.npz"), str(scene / "scene"))
    np.savez(tmp_path / "nokp.npz", labels=np.zeros(3, np.int64), image_ids=np.arange(3))
    assert "no 'keypoints' array" in err("--clusters", str(tmp_path / "nokp.npz"), str(scene / "scene"))
    assert not (tmp_path / "o").exists() or not list((tmp_path / "o").iterdir())
