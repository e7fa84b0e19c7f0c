"""Image inputs of dqm extract / dqm match: --image-list files, --recursive folders, ** globs (dqm.vision.features)."""
import os

import numpy as np
import pytest

from dqm import InputError, io
from dqm.cli import main
from dqm.vision import features, scenes


def touch(path):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"not decoded by collect_images")
    return path


@pytest.fixture
def tree(tmp_path):
    """root/top.png, root/b/img10.png, root/b/img2.png, root/a/x.jpg, root/a/deep/y.PNG, root/a/notes.txt."""
    root = tmp_path / "root"
    for rel in ("top.png", "b/img10.png", "b/img2.png", "a/x.jpg", "a/deep/y.PNG", "a/notes.txt"):
        touch(root / rel)
    return root


def rel(paths, root):
    return [p.relative_to(root).as_posix() for p in paths]


def test_folders_are_flat_unless_recursive_and_recursive_order_is_natural_by_folder(tree):
    assert rel(features.collect_images(tree), tree) == ["top.png"]
    assert rel(features.collect_images(tree, recursive=True), tree) == \
        ["a/deep/y.PNG", "a/x.jpg", "b/img2.png", "b/img10.png", "top.png"]
    # a folder whose images all sit in sub-folders: the refusal says how to read them
    for name in ("s1/p.png", "s2/q.png", "s2/deeper/r.png"):
        touch(tree / "nest" / name)
    with pytest.raises(InputError, match=r"sub-folders hold 3 image\(s\) \(--recursive reads them\)"):
        features.collect_images(tree / "nest")
    assert rel(features.collect_images(tree / "a", recursive=True), tree) == ["a/deep/y.PNG", "a/x.jpg"]


def test_double_star_globs_reach_any_depth(tree):
    got = features.collect_images(str(tree / "**" / "*.png"))
    assert rel(got, tree) == ["b/img2.png", "b/img10.png", "top.png"]  # case-sensitive glob: y.PNG not matched


def test_image_list_resolves_from_its_folder_keeps_its_order_and_skips_comments(tree, tmp_path):
    lists = tree / "lists"
    lists.mkdir()
    lst = lists / "train.txt"
    absolute = (tree / "top.png").resolve()
    lst.write_text(f"# training images\n\n../b/img10.png\r\n  ../a/x.jpg  \n{absolute}\n# ../b/img2.png\n")
    cwd = os.getcwd()
    os.chdir(tmp_path)  # the list's folder, not the working folder, anchors relative entries
    try:
        got = features.read_image_list(os.path.relpath(lst))
    finally:
        os.chdir(cwd)
    assert all(p.is_absolute() for p in got)
    assert rel(got, tree) == ["b/img10.png", "a/x.jpg", "top.png"]
    # with other inputs: those first, the list after, an image named twice kept at its first place
    both = features.collect_images([tree / "b"], image_list=lst)
    assert rel([p.resolve() for p in both], tree.resolve()) == ["b/img2.png", "b/img10.png", "a/x.jpg", "top.png"]


def test_image_list_errors_name_the_line(tree):
    lst = tree / "list.txt"
    lst.write_text("top.png\n# comment\nb/img2.png\nb/missing.png\nb\nnope.png\n")
    with pytest.raises(InputError, match=r"list\.txt:5: b is a folder"):
        features.read_image_list(lst)
    lst.write_text("top.png\n\nb/missing.png\nnope.png\n")
    with pytest.raises(InputError) as exc:
        features.read_image_list(lst)
    msg = str(exc.value)
    assert "list.txt:3: image not found: b/missing.png" in msg and "2 of the 3 listed images are missing" in msg
    assert "\n" not in msg
    lst.write_text("# nothing\n\n")
    with pytest.raises(InputError, match="names no image"):
        features.read_image_list(lst)
    with pytest.raises(InputError, match="image list not found"):
        features.read_image_list(tree / "absent.txt")
    lst.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(InputError, match="not a readable UTF-8 text file"):
        features.read_image_list(lst)
    with pytest.raises(InputError, match="no image inputs given"):
        features.collect_images([])


@pytest.fixture(scope="module")
def scene_tree(tmp_path_factory):
    """A generated 3-image scene spread over sub-folders: seq1/img1.png, seq1/img2.png, seq2/img3.png."""
    root = tmp_path_factory.mktemp("scene_tree")
    flat = root / "flat"
    scenes.generate_scene(3, (120, 160), seed=4).write(flat)
    for name, folder in (("img1.png", "seq1"), ("img2.png", "seq1"), ("img3.png", "seq2")):
        (root / "data" / folder).mkdir(parents=True, exist_ok=True)
        os.link(flat / name, root / "data" / folder / name)
    return root


def test_extract_reads_an_image_list_and_recursive_folders_on_the_command_line(scene_tree, tmp_path, capsys):
    data = scene_tree / "data"
    lst = data / "list.txt"
    lst.write_text("seq2/img3.png\nseq1/img1.png\n")
    assert main(["extract", "--image-list", str(lst), "--out", str(tmp_path / "a.npz"), "--quiet"]) == 0
    a = io.load_features(tmp_path / "a.npz")
    assert a.image_names.tolist() == [str(data / "seq2/img3.png"), str(data / "seq1/img1.png")]
    assert set(np.unique(a.image_ids).tolist()) == {0, 1}

    assert main(["extract", str(data), "--recursive", "--out", str(tmp_path / "b.npz"), "--quiet"]) == 0
    b = io.load_features(tmp_path / "b.npz")
    assert [n.split(str(data) + "/")[1] for n in b.image_names.tolist()] == \
        ["seq1/img1.png", "seq1/img2.png", "seq2/img3.png"]
    # the same image gives the same SIFT whichever way it was named (deterministic)
    np.testing.assert_array_equal(a.descriptors[a.image_ids == 0], b.descriptors[b.image_ids == 2])

    capsys.readouterr()
    assert main(["extract", str(data), "--out", str(tmp_path / "c.npz"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--recursive reads them" in err
    assert main(["extract", "--out", str(tmp_path / "c.npz"), "--quiet"]) == 2
    assert "no image inputs given" in capsys.readouterr().err
    lst.write_text("seq1/img1.png\nseq1/gone.png\n")
    assert main(["extract", "--image-list", str(lst), "--out", str(tmp_path / "c.npz"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "list.txt:2: image not found: seq1/gone.png" in err
    assert not (tmp_path / "c.npz").exists()
