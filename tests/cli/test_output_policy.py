"""The output policy (dqm/outputs.py), command by command: an existing output is refused unless
--overwrite, a wrong suffix is refused, both in one line before any work and with the file untouched;
defaults take the next free name; a refused command leaves no folder; results are whole or absent
(issue 36: dqm extract --out photos/img1.png replaced a photo; dqm scene overwrote an Oxford sequence;
split left a larger earlier split's files behind)."""
import subprocess
import sys

import numpy as np
import pytest

from dqm import io, outputs
from dqm.cli import main
from dqm.synthetic import sized

KEEP = b"the user's file\n"


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A FEATURES file, a CLUSTERS file with keypoints, descriptors and image names, and a scene folder."""
    d = tmp_path_factory.mktemp("policy")
    assert main(["scene", str(d / "scene"), "--images", "3", "--size", "160", "200", "--seed", "4"]) == 0
    assert main(["match", str(d / "scene"), "--out", str(d / "c.npz"), "--quiet", "--max-features", "150"]) == 0
    ds = sized(600, seed=0)
    io.save_features(d / "f.npz", io.FeatureSet(ds.descriptors, ds.image_ids))
    return {"features": str(d / "f.npz"), "clusters": str(d / "c.npz"), "scene": str(d / "scene")}


#: every command that writes one file: (argv with {out} where the output goes, the suffix it needs)
FILE_COMMANDS = {
    "extract": (["extract", "{scene}", "--out", "{out}", "--quiet", "--max-features", "50"], ".npz"),
    "import h5": (["import", "h5", "{h5}", "--out", "{out}"], ".npz"),
    "match": (["match", "{features}", "--out", "{out}", "--quiet"], ".npz"),
    "match --tracks-csv": (["match", "{features}", "--out", "{new}.npz", "--tracks-csv", "{out}", "--quiet"], ".csv"),
    "plot sizes": (["plot", "sizes", "{clusters}", "--out", "{out}"], ".png"),
    "export colmap": (["export", "colmap", "{clusters}", "--database", "{out}", "--no-verify"], ".db"),
    "export hloc --pairs": (["export", "hloc", "{clusters}", "--matches", "{new}.h5", "--pairs", "{out}"], ".txt"),
    "export --tracks": (["export", "hloc", "{clusters}", "--matches", "{new}.h5", "--pairs", "{new}.txt",
                         "--tracks", "{out}"], ".csv"),
    "run --report": (["run", "--agents", "2", "--report", "{out}"], ".json"),
    "coordinator --out": (["coordinator", "--agents", "1", "--connect", "tcp/127.0.0.1:1", "--out", "{out}"],
                          ".json"),
    "stream --out": (["stream", "--connect", "tcp/127.0.0.1:1", "--out", "{out}"], ".npz"),
}


def _argv(template, fill):
    return [a.format(**fill) for a in template]


def _one_line(capsys, argv, *needles):
    assert main(argv) == 2, argv
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for needle in needles:
        assert needle in err[0], err[0]


@pytest.fixture(scope="module")
def h5(tmp_path_factory, inputs):
    pytest.importorskip("h5py")
    d = tmp_path_factory.mktemp("h5")
    from dqm.vision.hloc import write_h5_features

    write_h5_features(d / "feats.h5", _with_keypoints(inputs), names=["a.png", "b.png", "c.png"])
    return str(d / "feats.h5")


def _with_keypoints(inputs):
    c = io.load_clusters(inputs["clusters"])
    return io.FeatureSet(c["descriptors"], c["image_ids"], keypoints=c["keypoints"])


@pytest.mark.parametrize("name", sorted(FILE_COMMANDS))
def test_an_existing_output_and_a_wrong_suffix_are_refused_untouched(tmp_path, capsys, inputs, h5, name):
    template, suffix = FILE_COMMANDS[name]
    fill = dict(inputs, h5=h5, new=str(tmp_path / "new"))
    existing = tmp_path / f"existing{suffix}"
    existing.write_bytes(KEEP)
    _one_line(capsys, _argv(template, dict(fill, out=str(existing))), str(existing), "exists", "--overwrite")
    assert existing.read_bytes() == KEEP
    photo = tmp_path / "img1.png" if suffix != ".png" else tmp_path / "img1.jpg.npz"
    photo.write_bytes(KEEP)
    _one_line(capsys, _argv(template, dict(fill, out=str(photo))), "unknown format", suffix)
    assert photo.read_bytes() == KEEP
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([existing.name, photo.name])


def test_overwrite_replaces_an_output_whole(tmp_path, capsys, inputs):
    out = tmp_path / "c.npz"
    out.write_bytes(KEEP)
    assert main(["match", inputs["features"], "--out", str(out), "--quiet", "--overwrite"]) == 0
    assert len(io.load_clusters(out)["labels"]) == len(io.load_features(inputs["features"]))
    assert [p.name for p in tmp_path.iterdir()] == ["c.npz"]  # no temporary file left


def test_scene_refuses_a_folder_with_a_sequence_and_keeps_it(tmp_path, capsys):
    seq = tmp_path / "graf"
    seq.mkdir()
    (seq / "img1.png").write_bytes(KEEP)
    (seq / "H1to2p").write_bytes(KEEP)
    _one_line(capsys, ["scene", str(seq), "--images", "2"], "already holds H1to2p and 1 more", "--overwrite")
    assert (seq / "img1.png").read_bytes() == KEEP and (seq / "H1to2p").read_bytes() == KEEP
    assert main(["scene", str(seq), "--images", "2", "--size", "120", "160", "--overwrite"]) == 0
    assert (seq / "img1.png").read_bytes() != KEEP
    notes = tmp_path / "notes"  # a folder with other files is fine: nothing there would be replaced
    notes.mkdir()
    (notes / "README.txt").write_bytes(KEEP)
    assert main(["scene", str(notes), "--images", "2", "--size", "120", "160"]) == 0
    assert sorted(p.name for p in notes.iterdir()) == ["H1to2p", "README.txt", "img1.png", "img2.png"]


def test_split_refuses_an_earlier_split_and_overwrite_removes_its_extra_files(tmp_path, capsys, inputs):
    out = tmp_path / "split"
    assert main(["split", inputs["features"], "--agents", "2", "--out", str(out)]) == 0
    _one_line(capsys, ["split", inputs["features"], "--agents", "2", "--out", str(out)], "agent0.npz",
              "--overwrite")
    many = tmp_path / "many"
    ids = np.repeat(np.arange(4), 100)
    fs = io.FeatureSet(np.random.default_rng(0).integers(0, 255, (400, 16), dtype=np.uint8), ids)
    io.save_features(tmp_path / "four.npz", fs)
    assert main(["split", str(tmp_path / "four.npz"), "--agents", "4", "--out", str(many)]) == 0
    assert main(["split", str(tmp_path / "four.npz"), "--agents", "2", "--out", str(many), "--overwrite"]) == 0
    assert sorted(p.name for p in many.iterdir()) == ["agent0.npz", "agent1.npz"]


def test_a_refused_command_leaves_no_folder(tmp_path, capsys, inputs):
    out = tmp_path / "model"
    assert main(["sfm", str(tmp_path / "no-such-photos"), "--out", str(out)]) == 2
    assert main(["split", inputs["features"], "--agents", "99", "--out", str(tmp_path / "split")]) == 2
    assert main(["match", inputs["features"], "--out", str(tmp_path / "deep" / "c.csv")]) == 2
    capsys.readouterr()
    assert list(tmp_path.iterdir()) == []


def test_default_outputs_take_the_next_free_name(tmp_path):
    first = tmp_path / "run" / "clusters.npz"
    assert outputs.check_file(first, "--out", (".npz",), default=True) == first
    first.parent.mkdir()
    first.write_bytes(KEEP)
    second = outputs.check_file(first, "--out", (".npz",), default=True)
    assert second == tmp_path / "run" / "clusters-2.npz"
    second.write_bytes(KEEP)
    assert outputs.check_file(first, "--out", (".npz",), default=True).name == "clusters-3.npz"
    folder = tmp_path / "evaluate"
    folder.mkdir()
    (folder / "evaluation.md").write_bytes(KEEP)
    assert outputs.check_dir(folder, "--out-dir", ("evaluation.md",), default=True) == tmp_path / "evaluate-2"
    # a default folder is taken when checked: a second run checking meanwhile gets the next one
    assert (tmp_path / "evaluate-2").is_dir()
    assert outputs.check_dir(folder, "--out-dir", ("evaluation.md",), default=True) == tmp_path / "evaluate-3"
    outputs.release_unused()  # nothing written in them: given back
    assert sorted(p.name for p in tmp_path.iterdir()) == ["evaluate", "run"]


def test_a_name_taken_while_the_command_ran_is_not_replaced(tmp_path):
    """The check at the start cannot see a file made later: the name is taken at the end, if free."""
    given = outputs.check_file(tmp_path / "c.npz", "--out", (".npz",))
    given.write_bytes(KEEP)  # the user (or another run) puts a file there while the command works
    with pytest.raises(outputs.OutputTaken, match=r"--out .*c\.npz appeared while this command ran.* kept as "
                                                   r".*c-2\.npz"):
        with outputs.atomic_output(given) as tmp, open(tmp, "wb") as fh:
            fh.write(b"result")
    assert given.read_bytes() == KEEP and (tmp_path / "c-2.npz").read_bytes() == b"result"
    default = outputs.check_file(tmp_path / "d.npz", "--out", (".npz",), default=True)
    default.write_bytes(KEEP)
    with outputs.atomic_output(default) as tmp, open(tmp, "wb") as fh:
        fh.write(b"result")
    assert default.read_bytes() == KEEP and outputs.written(default) == tmp_path / "d-2.npz"
    assert (tmp_path / "d-2.npz").read_bytes() == b"result"
    outputs.write_text(default, "again")  # this process's own output is rewritten where it went
    assert (tmp_path / "d-2.npz").read_text() == "again" and default.read_bytes() == KEEP
    told = outputs.check_file(tmp_path / "e.npz", "--out", (".npz",), overwrite=True)
    told.write_bytes(KEEP)
    outputs.write_text(told, "replaced")
    assert told.read_text() == "replaced"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c-2.npz", "c.npz", "d-2.npz", "d.npz", "e.npz"]


def test_a_link_is_written_through_where_the_output_is_replaced(tmp_path):
    target = tmp_path / "real" / "database.db"
    target.parent.mkdir()
    target.write_bytes(KEEP)
    link = tmp_path / "database.db"
    link.symlink_to(target)
    outputs.check_file(link, "--into-database", overwrite=True)
    outputs.write_text(link, "updated")
    assert link.is_symlink() and target.read_text() == "updated"
    assert sorted(p.name for p in target.parent.iterdir()) == ["database.db"]
    other = tmp_path / "other.npz"
    other.symlink_to(tmp_path / "nowhere.npz")  # a dangling link is a name taken too
    with pytest.raises(outputs.InputError, match="exists"):
        outputs.check_file(other, "--out", (".npz",))


def test_a_file_made_at_out_while_match_runs_survives(tmp_path, capsys, inputs, monkeypatch):
    """`dqm match ... --out race.npz & sleep 1; echo precious > race.npz` (issue 60): the file stays, the result is
    kept beside it and the command says so in one line."""
    checked = outputs.check_file

    def check_then_user_writes(path, *args, **kwargs):
        p = checked(path, *args, **kwargs)
        p.write_bytes(KEEP)
        return p

    monkeypatch.setattr(outputs, "check_file", check_then_user_writes)
    out = tmp_path / "race.npz"
    _one_line(capsys, ["match", inputs["features"], "--out", str(out), "--quiet"], "--out", "race.npz appeared",
              "race-2.npz")
    assert out.read_bytes() == KEEP
    n = len(io.load_features(inputs["features"]).image_ids)
    assert len(io.load_clusters(tmp_path / "race-2.npz")["labels"]) == n


@pytest.mark.parametrize("stop", [RuntimeError("disk full"), KeyboardInterrupt()])
def test_a_result_is_whole_or_absent(tmp_path, stop):
    target = tmp_path / "c.npz"
    with pytest.raises(type(stop)):
        with outputs.atomic_output(target) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(b"half")
            raise stop
    assert list(tmp_path.iterdir()) == []
    target.write_bytes(KEEP)
    with pytest.raises(type(stop)):
        with outputs.atomic_output(target) as tmp:
            raise stop
    assert target.read_bytes() == KEEP and [p.name for p in tmp_path.iterdir()] == ["c.npz"]


def test_the_run_command_writes_a_second_result_beside_the_first(tmp_path):
    """The README's main job where an earlier run left its result: the new CLUSTERS file is clusters-2.npz."""
    first = tmp_path / "dqm-out" / "run" / "clusters.npz"
    first.parent.mkdir(parents=True)
    first.write_bytes(KEEP)
    p = subprocess.run([sys.executable, "-m", "dqm", "run", "--agents", "2"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert sorted(p.name for p in first.parent.iterdir()) == ["clusters-2.npz", "clusters.npz"]
    assert first.read_bytes() == KEEP and "wrote dqm-out/run/clusters-2.npz" in p.stdout


def test_two_runs_started_together_keep_both_results(tmp_path):
    """Two `dqm run --agents 2` in one folder at once (issue 60): each checked a free default name at its start;
    both results are kept (clusters.npz and clusters-2.npz) and each run names its own."""
    procs = [subprocess.Popen([sys.executable, "-m", "dqm", "run", "--agents", "2"], cwd=tmp_path,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    said = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], said
    folder = tmp_path / "dqm-out" / "run"
    assert sorted(p.name for p in folder.iterdir()) == ["clusters-2.npz", "clusters.npz"]
    assert sorted(f"wrote dqm-out/run/{name}" in out for out, _ in said for name in ("clusters.npz",
                                                                                    "clusters-2.npz")) == \
        [False, False, True, True]
    first, second = (io.load_clusters(folder / name)["labels"] for name in ("clusters.npz", "clusters-2.npz"))
    assert len(first) > 1000 and np.array_equal(first, second)  # the same job twice: the same clusters


@pytest.mark.parametrize("argv, holds", [
    (["evaluate", "scene:1", "--out-dir", "{d}"], "evaluation.md"),
    (["evaluate", "--clusters", "{clusters}", "--out-dir", "{d}"], "evaluation_c.json"),
    (["experiment", "localization", "--quick", "--out-dir", "{d}"], "camnet.md"),
    (["plot", "pr", "{d}/../evaluation.json", "--out-dir", "{d}"], "pr_graf.png"),
    (["split", "{features}", "--agents", "2", "--out", "{d}"], "agent1.npz"),
    (["scene", "{d}"], "img1.png"),
])
def test_folder_commands_refuse_a_folder_holding_their_files(tmp_path, capsys, inputs, argv, holds):
    d = tmp_path / "out"
    d.mkdir()
    (d / holds).write_bytes(KEEP)
    (tmp_path / "evaluation.json").write_text('{"datasets": {}}')
    _one_line(capsys, [a.format(d=d, **inputs) for a in argv], holds, "--overwrite")
    assert (d / holds).read_bytes() == KEEP and len(list(d.iterdir())) == 1


def test_sfm_refuses_a_folder_that_is_not_empty(tmp_path, capsys, inputs):
    model = tmp_path / "model"
    model.mkdir()
    (model / "notes.txt").write_bytes(KEEP)
    _one_line(capsys, ["sfm", inputs["scene"], "--out", str(model)], "is not empty")
    assert [p.name for p in model.iterdir()] == ["notes.txt"]


def test_npz_outputs_store_what_does_not_deflate_and_are_the_same_bytes_each_time(tmp_path):
    import zipfile

    rng = np.random.default_rng(0)
    arrays = {"descriptors": rng.integers(0, 256, (4000, 128), dtype=np.uint8),  # noise: deflating does not pay
              "labels": np.repeat(np.arange(100, dtype=np.int64), 40),  # runs: it does
              "columns": rng.integers(0, 256, (4000, 128), dtype=np.uint8)[:, ::3],  # not contiguous
              "scalar": np.array(0.5), "none": np.zeros((0, 2))}
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    io._savez_fast(str(a), arrays)
    io._savez_fast(str(b), arrays)
    assert a.read_bytes() == b.read_bytes()
    kinds = {i.filename: i.compress_type for i in zipfile.ZipFile(a).infolist()}
    assert kinds["descriptors.npy"] == kinds["columns.npy"] == zipfile.ZIP_STORED
    assert kinds["labels.npy"] == zipfile.ZIP_DEFLATED
    with np.load(a) as z:
        assert sorted(z.files) == sorted(arrays)
        for k, v in arrays.items():
            assert z[k].dtype == v.dtype and np.array_equal(z[k], v)
