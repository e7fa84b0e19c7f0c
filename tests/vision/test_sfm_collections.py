"""dqm sfm on a collection of several scenes: each scene's model as that scene alone (issue 59), on generated
scenes with the size thresholds lowered."""
import json
from pathlib import Path

import numpy as np
import pytest

from dqm.cli import main
from dqm.io import load_clusters

pytest.importorskip("pycolmap", reason="pycolmap is not installed (pip install 'dqm[colmap]')")


def test_each_scene_of_a_collection_is_redone_alone_with_the_choices_of_its_own_size(tmp_path, capsys, monkeypatch):
    """Issue 59: each scene of a collection as good as that scene alone. ``--preset auto`` and ``--mapper auto``
    choose by the number of images; a collection from :data:`GLOBAL_FROM` images gets the large scenes' preset and
    the global mapper, which a scene of fewer images alone would not. With the threshold lowered to 8, two
    generated scenes of 5 and 4 images are such a collection: each model is mapped again from its own images alone
    (the budget preset, the incremental mapper) into scenes/<k>/, with the collection's image names, and replaces
    the collection's model, which stays in sparse/<k>. The collection's images keep their strongest features up to
    the large scenes' cap (lowered to 1,300 here, below most of these images' 1,214-1,505 sfm features), the scenes
    alone all theirs. The same collection with both choices given is neither capped nor redone."""
    import pycolmap
    from generators.scenes3d import generate_scene3d

    from dqm.vision import sfm

    a = generate_scene3d(seed=2, n_images=4).save(tmp_path / "a")
    b = generate_scene3d(seed=5, n_images=5).save(tmp_path / "b")
    monkeypatch.setattr(sfm, "GLOBAL_FROM", 8)
    monkeypatch.setattr(sfm, "LARGE_SCENE_MAX_FEATURES", 1300)
    assert main(["sfm", str(a), str(b), "--out", str(tmp_path / "m"), "--quiet", "--no-triangulate"]) == 0
    out = capsys.readouterr().out
    assert "SIFT preset sfm, at most 1,300 features an image (auto: 9 images" in out and "global mapping" in out
    report = json.loads((tmp_path / "m" / "sfm.json").read_text())
    assert report["options"]["max_features"] == 1300

    def per_image(clusters):
        return np.bincount(load_clusters(clusters)["image_ids"])

    assert per_image(tmp_path / "m" / "clusters.npz").max() == 1300
    alone = report["scenes_alone"]
    assert [(e["images"], e["preset"], e["max_features"], e["mapper"], e["taken"]) for e in alone] == [
        (5, "budget", 0, "incremental", True), (4, "budget", 0, "incremental", True)]
    for k in (0, 1):
        assert per_image(tmp_path / "m" / "scenes" / str(k) / "clusters.npz").min() > 1300
    assert [m["folder"] for m in report["models"]] == ["scenes/0/sparse/0", "scenes/1/sparse/0"]
    db = pycolmap.Database.open(str(tmp_path / "m" / "database.db"))
    names = {image.name for image in db.read_all_images()}
    db.close()
    for e, m in zip(alone, report["models"]):
        kept = pycolmap.Reconstruction(str(tmp_path / "m" / e["collection_folder"]))
        own = pycolmap.Reconstruction(str(tmp_path / "m" / m["folder"]))
        theirs = {image.name for image in kept.images.values() if image.has_pose}
        assert {image.name for image in own.images.values() if image.has_pose} == theirs <= names
        assert len({name.split("/")[0] for name in theirs}) == 1 and own.num_points3D() == m["points"] > 0
        assert e["collection_model"]["points"] == kept.num_points3D()
        assert (tmp_path / "m" / "scenes" / e["collection_folder"].split("/")[-1] / "clusters.npz").exists()
    assert f"{tmp_path / 'm'}/scenes" in out.splitlines()[-1]
    # from the collection's clusters.npz (--clusters: no extraction or matching of the collection), the same: the
    # file says what was asked (auto), so the scenes are made again alone as above, and the models are the same
    assert main(["sfm", "--clusters", str(tmp_path / "m" / "clusters.npz"), "--out", str(tmp_path / "m2"), "--quiet",
                 "--no-triangulate"]) == 0
    again = json.loads((tmp_path / "m2" / "sfm.json").read_text())
    assert [(e["images"], e["preset"], e["taken"]) for e in again["scenes_alone"]] == \
        [(e["images"], e["preset"], e["taken"]) for e in alone]
    assert [(m["folder"], m["points"]) for m in again["models"]] == \
        [(m["folder"], m["points"]) for m in report["models"]]
    for m in report["models"]:
        assert (tmp_path / "m" / m["folder"] / "points3D.bin").read_bytes() == \
            (tmp_path / "m2" / m["folder"] / "points3D.bin").read_bytes()
    argv = ["sfm", str(a), str(b), "--quiet", "--no-triangulate", "--preset", "sfm", "--mapper", "global"]
    assert main([*argv, "--out", str(tmp_path / "given")]) == 0
    given = json.loads((tmp_path / "given" / "sfm.json").read_text())
    assert given["scenes_alone"] == [] and not (tmp_path / "given" / "scenes").exists()
    assert given["options"]["max_features"] == 0 and per_image(tmp_path / "given" / "clusters.npz").max() > 1300
    assert [m["folder"] for m in given["models"]] == ["sparse/0", "sparse/1"]


def test_the_small_models_of_a_collection_are_redone_alone_together(tmp_path, capsys, monkeypatch):
    """Several models a collection's size gave other choices than their own, whose images together would get
    the same choices, are redone together, alone: a scene the collection's mapper cut apart or mixed with
    another's photos is whole again (the 270-photo collection with --cluster-matches auto: 8 of entry-P10's photos
    in sacre_coeur's model, 2 in one of their own). Three generated scenes of 10, 5 and 4 images with the
    threshold at 10: the large one keeps the collection's choices; the two small ones are mapped again together,
    into scenes/<k>+<l>/, and make a model each there; each of these is made again from its own images alone
    (scenes/<k>+<l>/scene-<j>/: as that scene alone), and they replace the collection's two. Where a
    collection model holds two of the models made alone joined by its 3-D points (a scene the collection's
    mapper held together and the mapper alone could not), the models made together are not taken, and each
    collection model is redone alone instead."""
    import pycolmap
    from generators.scenes3d import generate_scene3d

    from dqm.vision import sfm
    from dqm.vision.features import extract_images

    scenes = [generate_scene3d(seed=seed, n_images=n, width=480, height=360).save(tmp_path / name)
              for seed, n, name in ((0, 10, "c"), (2, 4, "a"), (5, 5, "b"))]
    monkeypatch.setattr(sfm, "GLOBAL_FROM", 10)
    from dqm.commands import sfm as command

    extracted = []  # the images of each extraction

    def counted(args, **kw):
        fs = extract(args, **kw)
        extracted.append(len(fs.image_names))
        return fs

    extract = command.extract
    monkeypatch.setattr(command, "extract", counted)
    argv = ["sfm", *map(str, scenes), "--quiet", "--no-triangulate"]
    assert main([*argv, "--out", str(tmp_path / "m")]) == 0
    out = capsys.readouterr().out
    report = json.loads((tmp_path / "m" / "sfm.json").read_text())
    [alone] = report["scenes_alone"]
    assert alone["collection_folders"] == ["sparse/1", "sparse/2"] and alone["images"] == 9 and alone["taken"]
    assert (alone["registered_in_its_models"], alone["models_alone"]) == (9, 2)
    assert "sparse/1 and sparse/2 (9 images) again alone" in out and "(2 models for 2 models)" in out
    assert [(e["images"], e["taken"], e["collection_folder"]) for e in alone["scenes"]] == [
        (5, True, "scenes/1+2/sparse/0"), (4, True, "scenes/1+2/sparse/1")]  # each scene alone again
    # each scene alone has the SIFT choice of the two together: its features are taken from there, not extracted
    # again (each image's features are its own), and its clusters are QuickMatch's on those alone
    assert alone["extracted"] and [e["extracted"] for e in alone["scenes"]] == [False, False]
    assert extracted == [19, 9]
    for e, scene in zip(alone["scenes"], ("b", "a")):
        with np.load(tmp_path / "m" / e["folder"].removesuffix("/sparse/0") / "clusters.npz") as z:
            fresh = extract_images(sorted(str(p) for p in (tmp_path / scene).glob("*.png")), preset=e["preset"])
            assert np.array_equal(z["descriptors"], fresh.descriptors)
            assert np.array_equal(z["keypoints"], fresh.keypoints)
    assert [m["folder"] for m in report["models"]] == ["sparse/0", "scenes/1+2/scene-0/sparse/0",
                                                       "scenes/1+2/scene-1/sparse/0"] == ["sparse/0", *alone["folders"]]
    assert [m["registered"] for m in report["models"]] == [10, 5, 4]
    for m in report["models"][1:]:
        rec = pycolmap.Reconstruction(str(tmp_path / "m" / m["folder"]))
        assert len({image.name.split("/")[0] for image in rec.images.values() if image.has_pose}) == 1

    monkeypatch.setattr(sfm, "linked_across", lambda rec, groups: True)
    assert main([*argv, "--out", str(tmp_path / "held")]) == 0
    out = capsys.readouterr().out
    report = json.loads((tmp_path / "held" / "sfm.json").read_text())
    together, *apart = report["scenes_alone"]
    assert not together["taken"] and "sparse/1 holds images of two of them joined by 3-D points" in out
    # kept together: each collection model is then redone alone, as a model of one scene
    assert [(e["collection_folders"], e["taken"]) for e in apart] == [(["sparse/1"], True), (["sparse/2"], True)]
    assert [m["folder"] for m in report["models"]] == ["sparse/0", "scenes/1/sparse/0", "scenes/2/sparse/0"]


def test_linked_across_asks_whether_a_model_joins_two_groups_of_images_by_its_points():
    """:func:`dqm.vision.sfm.linked_across`: two images of two groups that share 15 3-D points or more."""
    from types import SimpleNamespace as NS

    from dqm.vision.sfm import linked_across

    def model(shared):  # {(image a, image b): points both see}; images 1-4, named "i<k>"
        points = [NS(track=NS(elements=[NS(image_id=a), NS(image_id=b)])) for (a, b), n in shared.items()
                  for _ in range(n)]
        return NS(points3D=dict(enumerate(points)), reg_image_ids=lambda: [1, 2, 3, 4],
                  image=lambda i: NS(name=f"i{i}"))

    rec = model({(1, 2): 40, (3, 4): 40, (2, 3): 14})
    assert not linked_across(rec, [{"i1", "i2"}, {"i3", "i4"}])  # 14 chance points across
    assert linked_across(model({(1, 2): 40, (3, 4): 40, (2, 3): 15}), [{"i1", "i2"}, {"i3", "i4"}])
    assert linked_across(rec, [{"i1"}, {"i2", "i3", "i4"}])  # 1 and 2 see 40 points
    assert not linked_across(rec, [{"i1", "i2", "i3", "i4"}]) and not linked_across(rec, [{"i1", "i2"}, {"x"}])
    assert not linked_across(rec, [{"i1", "i2"}, {"i1", "i3", "i4"}])  # i1 counts in the first group only


def test_a_smaller_model_of_images_a_larger_one_holds_is_left_out():
    """:func:`dqm.vision.sfm.drop_repeats`: COLMAP's incremental mapper started a model of 2 of sacre_coeur's 10
    photos beside the model of all 10 (and one of 2 of cmu_hotel's frames beside all 101): a smaller model whose
    every image one larger model holds, joined there to another image by 15 3-D points or more, is left out and
    recorded in the larger one's repeats; one that adds an image, or whose image the larger one holds by chance
    points only, stays."""
    from types import SimpleNamespace as NS

    from dqm.vision.sfm import Model, drop_repeats

    def model(key, images, shared):  # images: ids named "i<k>"; shared: {(image a, image b): points both see}
        points = [NS(track=NS(elements=[NS(image_id=a), NS(image_id=b)])) for (a, b), n in shared.items()
                  for _ in range(n)]
        rec = NS(points3D=dict(enumerate(points)), reg_image_ids=lambda: list(images),
                 image=lambda i: NS(name=f"i{i}"))
        return Model(key, rec, Path(str(key)))

    large = model(0, [1, 2, 3, 4], {(1, 2): 40, (2, 3): 40, (3, 4): 14})  # image 4: 14 chance points
    kept = drop_repeats([large, model(1, [2, 3], {(2, 3): 30}), model(2, [3, 5], {(3, 5): 30}),
                         model(3, [3, 4], {(3, 4): 30})])
    assert [m.key for m in kept] == [0, 2, 3] and large.repeats == [{"model": 1, "images": 2}]
    assert all(m.repeats == [] for m in kept[1:])
    single = model(4, [1, 2], {(1, 2): 40})
    assert drop_repeats([single]) == [single] and single.repeats == []


def test_a_scene_that_cannot_be_redone_alone_keeps_the_collections_model(tmp_path, capsys, monkeypatch):
    """The fallbacks of the scenes redone alone (the test before): a scene whose run alone stops on bad input,
    and one whose run alone registers fewer of its images, keep the collection's model (in sparse/<k>, from
    database.db), which the last stage then triangulates and sfm.json reports, saying why."""
    from generators.scenes3d import generate_scene3d

    from dqm.commands import sfm as command
    from dqm.validation import InputError
    from dqm.vision import sfm

    a = generate_scene3d(seed=2, n_images=4).save(tmp_path / "a")
    b = generate_scene3d(seed=5, n_images=5).save(tmp_path / "b")
    monkeypatch.setattr(sfm, "GLOBAL_FROM", 8)
    real, calls = command._match_and_map, []

    def match_and_map(args, out, *rest, **kw):
        calls.append(out)
        if len(calls) == 2:
            raise InputError("made to fail")
        done = real(args, out, *rest, **kw)
        return done[:-1] + ([],) if len(calls) == 3 else done  # the third: no model alone

    monkeypatch.setattr(command, "_match_and_map", match_and_map)
    assert main(["sfm", str(a), str(b), "--out", str(tmp_path / "m"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert len(calls) == 3 and "not redone (made to fail)" in out and out.count("model-guided triangulation:") == 2
    report = json.loads((tmp_path / "m" / "sfm.json").read_text())
    alone = report["scenes_alone"]
    assert [e["taken"] for e in alone] == [False, False] and alone[0]["error"] == "made to fail"
    assert alone[1]["registered_alone"] == 0
    models = report["models"]
    assert [m["folder"] for m in models] == ["sparse/0", "sparse/1"] and [m["registered"] for m in models] == [5, 4]
    assert all(m["points"] > m["before_triangulation"]["points"] for m in models)
