"""What a new user meets around the happy path (issue 12): output paths checked before any
work in one line naming the path, no default writes into the committed docs, result files
that follow the umask, CLUSTERS usable from any folder, plain messages for bad inputs."""
import os
import subprocess
import sys

import pytest

from dqm import io, outputs
from dqm.cli import main
from dqm.synthetic import sized

#: an existing folder where no file can be created, and a folder that cannot be created
#: (/proc refuses both, even to root, for whom permission bits do not apply)
UNWRITABLE_DIR = "/proc/self"
UNCREATABLE_DIR = "/proc/dqm-no-such-folder"


@pytest.fixture(scope="module")
def features(tmp_path_factory):
    path = tmp_path_factory.mktemp("outputs") / "f.npz"
    ds = sized(1500, seed=0)
    io.save_features(path, io.FeatureSet(ds.descriptors, ds.image_ids))
    return path


def one_error_line(capsys, argv, *needles):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for needle in needles:
        assert needle in err[0], err[0]
    return err[0]


def test_match_refuses_a_folder_a_read_only_place_and_an_uncreatable_folder(tmp_path, features, capsys):
    one_error_line(capsys, ["match", str(features), "--out", str(tmp_path)], str(tmp_path), "is a folder")
    one_error_line(capsys, ["match", str(features), "--out", f"{UNWRITABLE_DIR}/c.npz"], "cannot write in /proc/self")
    one_error_line(capsys, ["match", str(features), "--out", f"{UNCREATABLE_DIR}/c.npz"], "cannot create the folder")
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    one_error_line(capsys, ["match", str(features), "--out", str(blocker / "c.npz")], "is not a folder")
    one_error_line(capsys, ["match", str(features), "--out", str(tmp_path / "c.npz"), "--tracks-csv",
                            str(tmp_path)], "--tracks-csv", "is a folder")
    assert not (tmp_path / "c.npz").exists()  # refused before the work, nothing half-written


def test_match_creates_missing_parent_folders(tmp_path, features, capsys):
    out = tmp_path / "new" / "deeper" / "c.npz"
    assert main(["match", str(features), "--out", str(out), "--quiet"]) == 0
    assert out.exists()


def test_plot_checks_the_image_format_and_folder_before_reading_anything(tmp_path, capsys):
    missing = str(tmp_path / "no-such-clusters.npz")
    one_error_line(capsys, ["plot", "pair", missing, "--out", str(tmp_path / "p.xyz")], "unknown format .xyz",
                   ".png")
    one_error_line(capsys, ["plot", "sizes", missing, "--out", str(tmp_path / "p")], "(no suffix)")
    one_error_line(capsys, ["plot", "pr", missing, "--out-dir", f"{UNCREATABLE_DIR}/pr"], "cannot create")


def test_run_report_and_evaluate_out_dir_are_checked_first(tmp_path, capsys):
    one_error_line(capsys, ["run", "--agents", "2", "--report", str(tmp_path)], "--report", "is a folder")
    one_error_line(capsys, ["evaluate", "scene", "--out-dir", f"{UNWRITABLE_DIR}"], "--out-dir", "cannot write")
    one_error_line(capsys, ["experiment", "localization", "--quick", "--out-dir", f"{UNCREATABLE_DIR}/x"],
                   "--out-dir", "cannot create")


def test_evaluate_and_experiment_default_to_dqm_out_not_docs(tmp_path):
    """Run from an empty folder: the default output goes to ./dqm-out/<command>, never ./docs."""
    assert outputs.default_dir("evaluate").as_posix() == "dqm-out/evaluate"
    env = dict(os.environ, MPLBACKEND="Agg")
    p = subprocess.run([sys.executable, "-m", "dqm", "evaluate", "scene:1", "--methods", "quickmatch", "--rhos",
                        "0.9", "--ratios", "0.75", "--max-features", "300", "--quiet"],
                       cwd=tmp_path, capture_output=True, text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "dqm-out" / "evaluate" / "evaluation.md").exists()
    assert not (tmp_path / "docs").exists()


def test_check_file_accepts_a_writable_path(tmp_path):
    assert outputs.check_file(tmp_path / "a" / "b.png", "--out", outputs.IMAGE_SUFFIXES) == tmp_path / "a" / "b.png"
    assert not (tmp_path / "a").exists()  # checked, not created: a refused command leaves no folder
    assert list(tmp_path.iterdir()) == []  # and the probe file is gone


def test_npz_results_follow_the_umask(tmp_path, features):
    old = os.umask(0o022)
    try:
        io.save_features(tmp_path / "f.npz", io.load_features(features))
        assert main(["match", str(features), "--out", str(tmp_path / "c.npz"), "--quiet"]) == 0
    finally:
        os.umask(old)
    for name in ("f.npz", "c.npz"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o644


def test_clusters_name_images_by_absolute_path(tmp_path):
    assert main(["scene", str(tmp_path / "scene"), "--images", "2", "--size", "160", "200", "--seed", "2"]) == 0
    p = subprocess.run([sys.executable, "-m", "dqm", "match", "scene", "--out", "c.npz", "--quiet",
                        "--max-features", "200"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    names = io.load_clusters(tmp_path / "c.npz")["image_names"].tolist()
    assert len(names) == 2 and all(os.path.isabs(n) and os.path.isfile(n) for n in names)
    other = tmp_path / "elsewhere"
    other.mkdir()
    p = subprocess.run([sys.executable, "-m", "dqm", "plot", "pair", str(tmp_path / "c.npz"), "--out", "p.png"],
                       cwd=other, capture_output=True, text=True, timeout=300, env=dict(os.environ, MPLBACKEND="Agg"))
    assert p.returncode == 0, p.stderr
    assert (other / "p.png").exists()


def test_a_text_file_given_as_npz_gets_one_plain_line(tmp_path, capsys):
    bad = tmp_path / "f.npz"
    bad.write_text("descriptors,image_ids\n1,2\n")
    line = one_error_line(capsys, ["match", str(bad), "--out", str(tmp_path / "c.npz")], "not an .npz features file")
    assert "pickle" not in line


def test_every_option_has_help_and_shows_its_default():
    import argparse

    from dqm.cli import build_parser

    missing, undefaulted = [], []

    def walk(parser, path):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, path + [name])
            elif action.option_strings and action.dest not in ("help", "version"):
                if not action.help:
                    missing.append((path, action.option_strings))
                elif not any(action.default is v for v in (None, False, True)):
                    shown = parser.formatter_class(prog="x")._get_help_string(action)
                    if "default" not in shown.lower():
                        undefaulted.append((path, action.option_strings))

    walk(build_parser(), ["dqm"])
    assert not missing, missing
    assert not undefaulted, undefaulted


def test_demo_messages_are_plain(capsys):
    assert main(["demo", "--images", "1", "--points", "20"]) == 0
    out = capsys.readouterr()
    assert "note: all features come from one image" in out.out
    assert "UserWarning" not in out.out + out.err and "recall" not in out.out
    assert main(["demo", "--points", "0", "--images", "3"]) == 0
    out = capsys.readouterr()
    assert "no true pairs to find" in out.out and "RuntimeWarning" not in out.err


def test_extract_makes_a_features_file_that_match_and_run_take(tmp_path, capsys):
    assert main(["scene", str(tmp_path / "scene"), "--images", "3", "--size", "160", "200", "--seed", "4"]) == 0
    out = tmp_path / "f.npz"
    assert main(["extract", str(tmp_path / "scene"), "--out", str(out), "--max-features", "150", "--quiet"]) == 0
    fs = io.load_features(out)
    assert len(fs.image_names) == 3 and len(fs) > 100 and fs.keypoints.shape == (len(fs), 4)
    assert main(["match", str(out), "--out", str(tmp_path / "c.npz"), "--quiet"]) == 0


def test_bad_images_are_refused_before_sift_or_skipped_on_request(tmp_path, capsys):
    assert main(["scene", str(tmp_path / "scene"), "--images", "3", "--size", "160", "200", "--seed", "4"]) == 0
    (tmp_path / "scene" / "img9.png").write_text("not a picture")
    line = one_error_line(capsys, ["extract", str(tmp_path / "scene"), "--out", str(tmp_path / "f.npz"), "--quiet"],
                          "cannot read image", "img9.png", "--skip-bad-images")
    assert not (tmp_path / "f.npz").exists() and "sift" not in line
    assert main(["match", str(tmp_path / "scene"), "--out", str(tmp_path / "c.npz"), "--quiet",
                 "--skip-bad-images", "--max-features", "150"]) == 0
    captured = capsys.readouterr()
    assert "warning: skipped 1 unreadable image:" in captured.err and "img9.png" in captured.err
    assert "skipped" not in captured.out  # warnings go to standard error, results to standard output
    assert len(io.load_clusters(tmp_path / "c.npz")["image_names"]) == 3


def test_plot_pair_refuses_a_truth_folder_that_does_not_fit(tmp_path, capsys):
    for name, size in (("a", ("160", "200")), ("b", ("120", "160"))):
        assert main(["scene", str(tmp_path / name), "--images", "2", "--size", *size, "--seed", "4"]) == 0
    assert main(["match", str(tmp_path / "a"), "--out", str(tmp_path / "c.npz"), "--quiet"]) == 0
    capsys.readouterr()
    one_error_line(capsys, ["plot", "pair", str(tmp_path / "c.npz"), "--out", str(tmp_path / "p.png"),
                            "--truth", str(tmp_path / "b")], "does not fit these images", "200x160", "160x120")
    assert main(["plot", "pair", str(tmp_path / "c.npz"), "--out", str(tmp_path / "p.png"),
                 "--truth", str(tmp_path / "a")]) == 0


def test_version_and_doctor_say_which_kernel_runs(capsys):
    from dqm.core import native

    with pytest.raises(SystemExit):
        main(["--version"])
    assert "tile kernel: " + native.kernel_description() in capsys.readouterr().out
    assert main(["doctor"]) == 0
    out = capsys.readouterr().out
    assert "tile kernel: " in out and "eclipse-zenoh" in out and "OpenCV" in out and "shared data" in out


def test_the_numpy_fallback_warns_once_on_a_large_input(monkeypatch):
    import warnings

    from dqm.core import native

    monkeypatch.setattr(native, "_LIB", None)
    monkeypatch.setattr(native, "_WARNED_FALLBACK", False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        native.warn_if_fallback(1000)
        native.warn_if_fallback(50_000)
        native.warn_if_fallback(50_000)
    assert len(caught) == 1 and "numpy fallback" in str(caught[0].message) and "dqm doctor" in str(caught[0].message)


def test_doctor_piped_into_head_is_not_an_error(tmp_path):
    p = subprocess.run(f"{sys.executable} -m dqm doctor | head -1", shell=True, capture_output=True, text=True,
                       timeout=120)
    assert "BrokenPipe" not in p.stderr and "error" not in p.stderr


def test_runtime_messages_are_plain(tmp_path, capsys):
    from dqm.runtime.bus import zenoh_message

    one_error_line(capsys, ["agent", "--id", "0", "--agents", "0", "--connect", "tcp/127.0.0.1:1", "x.npz"],
                   "--agents must be at least 1")
    one_error_line(capsys, ["agent", "--id", "0", "--agents", "1", "--connect", "127.0.0.1:7447", "x.npz"],
                   "is not a zenoh endpoint", "did you mean tcp/127.0.0.1:7447")
    one_error_line(capsys, ["coordinator", "--agents", "2", "--connect", "localhost"], "is not a zenoh endpoint")
    rust = Exception("Unable to connect to any of [tcp/127.0.0.1:1]! at /root/.cargo/registry/src/"
                     "index.crates.io-6f17d22bba15001f/zenoh-1.4.0/src/net/runtime/orchestrator.rs:417.")
    assert zenoh_message(rust) == "Unable to connect to any of [tcp/127.0.0.1:1]!"


def test_run_check_says_what_it_does_and_keeps_the_report_first(tmp_path):
    report = tmp_path / "r.json"
    p = subprocess.run([sys.executable, "-m", "dqm", "run", "--agents", "2", "--check", "--report", str(report)],
                       capture_output=True, text=True, timeout=300, cwd=tmp_path)  # its ./dqm-out there
    assert p.returncode == 0, p.stderr
    assert "Checking: the same job" in p.stderr
    assert "identical clusters" in p.stdout
    assert p.stdout.index(f"wrote {report}") < p.stdout.index("In-process simulator")
    assert report.exists()
