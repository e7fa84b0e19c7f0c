"""dqm match grows the clusters by geometry by default where that serves what follows (GUIDED_HELP)."""
import numpy as np

from dqm import io
from dqm.cli import main


def test_match_grows_by_default_unless_verify_no_guided_or_no_keypoints(tmp_path, capsys):
    assert main(["scene", str(tmp_path / "scene"), "--images", "3", "--size", "240", "320", "--seed", "5"]) == 0
    runs = {}
    for name, extra in (("default", []), ("plain", ["--no-guided"]), ("verify", ["--verify"])):
        capsys.readouterr()
        assert main(["match", str(tmp_path / "scene"), "--out", str(tmp_path / f"{name}.npz"), "--quiet",
                     *extra]) == 0
        runs[name] = (capsys.readouterr().out, io.load_clusters(tmp_path / f"{name}.npz"))
    out, c = runs["default"]
    assert "guided growth:" in out and c["params"]["guided"] is True
    out, c = runs["plain"]
    assert "guided growth" not in out and "verified" not in out and not c["params"].get("guided", False)
    out, c = runs["verify"]
    assert "guided growth" not in out and "verified 3 of 3 image pairs" in out
    assert c["params"]["verify"] is True and not c["params"].get("guided", False)
    # growth only joins clusters and splits off what verification rejects: more multi-image members here
    grown, plain = runs["default"][1]["labels"], runs["plain"][1]["labels"]
    assert (np.bincount(grown) >= 2).sum() != (np.bincount(plain) >= 2).sum()
    # features without keypoints: a note, QuickMatch's clusters; asking for growth is refused
    fs = io.load_features(tmp_path / "plain.npz")
    io.save_features(tmp_path / "nokp.npz", io.FeatureSet(descriptors=fs.descriptors, image_ids=fs.image_ids))
    capsys.readouterr()
    assert main(["match", str(tmp_path / "nokp.npz"), "--out", str(tmp_path / "n.npz"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "note: the features have no keypoints, so the clusters are not grown" in out
    np.testing.assert_array_equal(io.load_clusters(tmp_path / "n.npz")["labels"], plain)
    assert main(["match", str(tmp_path / "nokp.npz"), "--out", str(tmp_path / "g.npz"), "--guided"]) == 2
    assert "--guided needs keypoints" in capsys.readouterr().err
