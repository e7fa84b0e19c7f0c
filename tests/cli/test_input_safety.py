"""Inputs that used to give a wrong answer, a blow-up or a confusing message (issue 21): absurd
descriptor magnitudes, degenerate duplicates, FEATURES inputs to dqm match, image names that do
not fit the image ids, TLS files that are missing, small option checks."""
import argparse
import time

import numpy as np
import pytest

import dqm
from dqm import io
from dqm.cli import build_parser, main
from dqm.distributed import DQMConfig, simulate
from dqm.synthetic import sift_like
from dqm.validation import InputError


@pytest.fixture(scope="module")
def data():
    ds = sift_like(n_images=5, n_points=200, clutter_per_image=60, noise=0.3, seed=4)
    return ds.descriptors.astype(np.float64), ds.image_ids


@pytest.mark.parametrize("factor", [1e17, 1e-30, 3e300, 1e-300])
def test_clusters_do_not_depend_on_a_common_scale_however_absurd(data, factor):
    X, ids = data
    ref = dqm.quickmatch(X, ids)
    r = dqm.quickmatch(X * factor, ids)
    np.testing.assert_array_equal(r.labels, ref.labels)
    np.testing.assert_allclose(r.sigma, ref.sigma * factor, rtol=1e-12)
    finite = np.isfinite(ref.parent_distance)
    np.testing.assert_allclose(r.parent_distance[finite], ref.parent_distance[finite] * factor, rtol=1e-12)
    np.testing.assert_allclose(r.density, ref.density, rtol=1e-5)  # float32 pass values within their bounds
    assert r.stats["descriptor_scale_exponent"] != 0


def test_where_no_common_rescaling_is_possible_the_magnitude_is_refused_in_one_line(data):
    X, ids = data
    with pytest.raises(InputError, match=r"largest magnitude .* outside the range"):
        dqm.OnlineQuickMatch(rho=0.9).add(X * 1e17, ids)
    with pytest.raises(InputError, match=r"largest magnitude"):
        simulate(X * 1e-30, ids, DQMConfig(agents=2))
    # within the range nothing changes: the distributed result is the centralized one
    np.testing.assert_array_equal(simulate(X * 1e3, ids, DQMConfig(agents=2)).labels,
                                  dqm.quickmatch(X, ids, kernel="quadratic").labels)


def test_many_exact_duplicates_cost_no_pair_lists():
    """All-equal descriptors (sigma 0 everywhere): no candidate pair can exist, and none is gathered."""
    X = np.zeros((6000, 128), np.uint8)
    ids = np.arange(6000) % 5
    r = dqm.quickmatch(X, ids)
    assert r.n_clusters == 6000 and (r.sigma == 0).all()
    assert r.stats["n_pass_edges"] == 0 and r.stats["streaming"] == 0


def test_sigma_with_duplicates_equals_the_brute_force_definition():
    rng = np.random.default_rng(0)
    X = rng.integers(0, 3, (500, 6)).astype(np.uint8)  # many exact duplicates within and across images
    ids = rng.integers(0, 6, 500)
    d = np.sqrt(((X[:, None, :].astype(int) - X[None, :, :]) ** 2).sum(-1))
    same = ids[:, None] == ids[None, :]
    np.fill_diagonal(same, False)
    np.testing.assert_array_equal(dqm.quickmatch(X, ids).sigma, np.where(same, d, np.inf).min(axis=1))


def one_line(capsys, argv, *needles, code=2):
    assert main(argv) == code
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for needle in needles:
        assert needle in err[0], err[0]
    return err[0]


def test_match_reads_features_files_by_content_and_several_at_once(tmp_path, capsys):
    ds = sift_like(n_images=4, n_points=80, seed=0)
    half = ds.image_ids < 2
    a, b = tmp_path / "a.npz", tmp_path / "B.NPZ"
    io.save_features(a, io.FeatureSet(ds.descriptors[half], ds.image_ids[half],
                                      image_names=np.array(["a0.png", "a1.png"])))
    io.save_features(b, io.FeatureSet(ds.descriptors[~half], ds.image_ids[~half] - 2,
                                      image_names=np.array(["b0.png", "b1.png"])))
    out = tmp_path / "c.npz"
    assert main(["match", str(b), "--out", str(out), "--quiet"]) == 0  # upper-case suffix
    noext = tmp_path / "features"
    noext.write_bytes(a.read_bytes())
    assert main(["match", str(noext), "--out", str(out), "--quiet", "--overwrite"]) == 0  # no suffix: by content
    capsys.readouterr()
    assert main(["match", str(a), str(b), "--out", str(out), "--quiet", "--kernel", "quadratic", "--overwrite"]) == 0
    assert "each file numbers its own images" in capsys.readouterr().out
    c = io.load_clusters(out)
    np.testing.assert_array_equal(c["image_ids"], np.concatenate([ds.image_ids[half], ds.image_ids[~half]]))
    assert [str(n) for n in c["image_names"]] == ["a0.png", "a1.png", "b0.png", "b1.png"]
    X = np.concatenate([ds.descriptors[half], ds.descriptors[~half]])
    np.testing.assert_array_equal(c["labels"], dqm.quickmatch(X, c["image_ids"], kernel="quadratic").labels)
    new = tmp_path / "new.npz"
    one_line(capsys, ["match", str(a), str(a), "--out", str(new)], "given twice")
    one_line(capsys, ["match", str(a), str(tmp_path / "x.png"), "--out", str(new)], "mix FEATURES files")
    one_line(capsys, ["match", str(a), "--out", str(tmp_path / "e.txt")], "--out", "unknown format .txt")
    one_line(capsys, ["match", str(a), "--out", str(tmp_path / "noext")], "(no suffix)")
    one_line(capsys, ["match", "--out", str(new)], "no input")


def test_features_files_that_cannot_be_right_are_refused_at_load(tmp_path, capsys):
    ds = sift_like(n_images=3, n_points=20, seed=0)
    obj = tmp_path / "obj.npz"
    np.savez(obj, descriptors=np.array([[1, 2], [3]], dtype=object), image_ids=np.array([0, 1]))
    one_line(capsys, ["match", str(obj), "--out", str(tmp_path / "c.npz")], "obj.npz", "'descriptors'",
             "Python objects")
    names = tmp_path / "names.npz"
    ids = np.where(ds.image_ids == 0, 5, 7)  # ids 5 and 7, two names
    np.savez(names, descriptors=ds.descriptors, image_ids=ids, image_names=np.array(["x.png", "y.png"]))
    one_line(capsys, ["match", str(names), "--out", str(tmp_path / "c.npz")], "image_names has 2 name(s)",
             "5, 7")
    fid = tmp_path / "fid.npz"
    np.savez(fid, descriptors=ds.descriptors, image_ids=ds.image_ids,
             feature_ids=np.zeros(len(ds.image_ids), np.int64))
    one_line(capsys, ["match", str(fid), "--out", str(tmp_path / "c.npz")], "feature id 0 appears more than once")


def test_tls_files_are_checked_before_connecting(tmp_path, capsys):
    pem = tmp_path / "ca.pem"
    pem.write_text("-----BEGIN CERTIFICATE-----\nAAAA\n-----END CERTIFICATE-----\n")
    t0 = time.monotonic()
    one_line(capsys, ["coordinator", "--agents", "2", "--connect", "tls/127.0.0.1:1", "--tls-ca", str(pem),
                      "--tls-cert", str(pem), "--tls-key", str(tmp_path / "missing.key"), "--no-clusters"],
             "--tls-key", "missing.key", "no such file")
    (tmp_path / "notpem.key").write_text("hello")
    one_line(capsys, ["router", "--listen", "tls/127.0.0.1:1", "--tls-ca", str(pem), "--tls-cert", str(pem),
                      "--tls-key", str(tmp_path / "notpem.key")], "not a PEM file")
    assert time.monotonic() - t0 < 5  # no connection retries


def test_router_errors_carry_no_rust_source_paths(capsys):
    import socket
    import subprocess
    import sys

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        p = subprocess.run([sys.executable, "-m", "dqm", "router", "--listen", f"tcp/127.0.0.1:{s.getsockname()[1]}"],
                           capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "Address already in use" in p.stderr
    assert ".rs:" not in p.stderr and "Traceback" not in p.stderr


def _option(command: str, dest: str) -> argparse.Action:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return next(a for a in sub.choices[command]._actions if a.dest == dest)


def test_small_option_rules(capsys):
    help_text = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)
                     ).choices["run"].format_help()
    assert "(default: True)" not in help_text.split("--no-cell-weights", 1)[1].split("--", 1)[0]
    assert _option("run", "seed").default == _option("coordinator", "seed").default == DQMConfig(agents=1).seed
    for bad in ("0", "-3", "two"):
        with pytest.raises(SystemExit) as exc:
            main(["match", "x.npz", "--out", "c.npz", "--threads", bad])
        assert exc.value.code == 2
        assert "--threads" in capsys.readouterr().err
