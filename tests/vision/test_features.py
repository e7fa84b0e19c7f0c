"""SIFT extraction from folders / globs / lists (dqm.vision.features) and its errors on bad input."""
import numpy as np
import pytest

from dqm import InputError
from dqm.vision import features, scenes


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("scene")
    scenes.generate_scene(3, (240, 320), seed=2).write(root)
    return root


def test_extract_on_a_generated_scene(scene_dir):
    fs = features.extract_images(scene_dir)
    assert [p.rsplit("/", 1)[-1] for p in fs.image_names.tolist()] == ["img1.png", "img2.png", "img3.png"]
    assert fs.descriptors.dtype == np.uint8 and fs.descriptors.shape[1] == 128
    assert fs.keypoints.shape == (len(fs), 4)
    counts = np.bincount(fs.image_ids, minlength=3)
    assert (counts > 100).all(), counts
    x, y, size, angle = fs.keypoints.T
    assert (x >= 0).all() and (x < 320).all() and (y >= 0).all() and (y < 240).all()
    assert (size > 0).all() and ((angle >= 0) & (angle < 360)).all()
    again = features.extract_images(scene_dir)
    np.testing.assert_array_equal(fs.descriptors, again.descriptors)  # deterministic


def test_max_features_and_presets(scene_dir):
    capped = features.extract_images(scene_dir, max_features=50)
    counts = np.bincount(capped.image_ids)
    assert (counts >= 45).all() and (counts <= 55).all(), counts  # OpenCV may keep ties
    paper = features.extract_images(scene_dir, preset="paper")
    opencv = features.extract_images(scene_dir)
    assert len(paper) != len(opencv)  # the preset really changes SIFT
    with pytest.raises(InputError, match="preset"):
        features.extract_images(scene_dir, preset="fast")
    with pytest.raises(InputError, match="max_features"):
        features.extract_images(scene_dir, max_features=-1)


def test_strongest_locations_keep_every_orientation_of_the_best_locations():
    cv2 = pytest.importorskip("cv2")
    kps = [cv2.KeyPoint(1, 1, 2, 10, 0.5), cv2.KeyPoint(5, 5, 2, 0, 0.9), cv2.KeyPoint(1, 1, 2, 200, 0.2),
           cv2.KeyPoint(7, 3, 2, 0, 0.5), cv2.KeyPoint(9, 9, 2, 0, 0.1)]
    # locations by their best response: (5, 5) 0.9, (1, 1) 0.5 and (7, 3) 0.5 (a tie: the earlier), (9, 9)
    assert features.strongest_locations(kps, 1) == [kps[1]]
    assert features.strongest_locations(kps, 2) == kps[:3]  # (1, 1) with both its orientations
    assert features.strongest_locations(kps, 3) == kps[:4]
    assert features.strongest_locations(kps, 9) == kps and features.strongest_locations([], 3) == []


def test_budget_preset_keeps_the_strongest_locations(scene_dir, monkeypatch):
    """The budget preset: contrast 0.02 (more features than the sfm preset's 0.03), then each image's
    strongest LOCATION_BUDGET locations with every orientation; RootSIFT descriptors."""
    budget = features.extract_images(scene_dir, preset="budget")
    sfm = features.extract_images(scene_dir, preset="sfm")
    assert len(budget) > len(sfm)
    monkeypatch.setitem(features.LOCATION_BUDGET, "budget", 100)
    few = features.extract_images(scene_dir, preset="budget")
    for k in range(3):
        xy = few.keypoints[few.image_ids == k, :2]
        assert len(np.unique(xy, axis=0)) == 100 and len(xy) >= 100
        full = budget.keypoints[budget.image_ids == k, :2]
        assert {tuple(p) for p in xy.tolist()} <= {tuple(p) for p in full.tolist()}
    norms = np.linalg.norm(few.descriptors.astype(float), axis=1)
    assert np.allclose(norms, 512, rtol=0.02)  # RootSIFT: unit L2 x 512


def test_images_are_extracted_in_parallel_with_the_same_features(scene_dir, monkeypatch):
    """One image per core at a time (OpenCV's own threads at 1 meanwhile, restored after): the same arrays as
    one image at a time, an unreadable image in the middle still left out in its place."""
    cv2 = pytest.importorskip("cv2")
    paths = sorted(str(p) for p in scene_dir.glob("img*.png"))
    bad = scene_dir.parent / "broken.png"
    bad.write_bytes(b"not a png")
    images = [paths[0], str(bad), *paths[1:]]
    before = cv2.getNumThreads()
    runs = []
    for threads in ("1", "2", "3"):
        monkeypatch.setenv("DQM_THREADS", threads)
        failed = []
        runs.append((features.extract_many(images, "sfm", failed=failed), failed))
        assert cv2.getNumThreads() == before
    (D, ids, kp), failed = runs[0]
    assert failed == [1] and sorted(set(ids.tolist())) == [0, 1, 2]
    for (D2, ids2, kp2), failed2 in runs[1:]:
        assert failed2 == failed
        np.testing.assert_array_equal(D, D2)
        np.testing.assert_array_equal(ids, ids2)
        np.testing.assert_array_equal(kp, kp2)
    with pytest.raises(InputError):
        features.extract_many(images, "sfm")
    assert cv2.getNumThreads() == before


def test_collect_images_folder_glob_list_natural_order(tmp_path, scene_dir):
    import shutil

    for k in (1, 2, 10):
        shutil.copy(scene_dir / "img1.png", tmp_path / f"view{k}.png")
    (tmp_path / "notes.txt").write_text("not an image")
    names = [p.name for p in features.collect_images(tmp_path)]
    assert names == ["view1.png", "view2.png", "view10.png"]
    assert [p.name for p in features.collect_images(str(tmp_path / "view1*.png"))] == ["view1.png", "view10.png"]
    assert [p.name for p in features.collect_images([tmp_path / "view2.png", tmp_path / "view1.png"])] == \
        ["view2.png", "view1.png"]
    assert len(features.collect_images([tmp_path, tmp_path / "view2.png"])) == 3  # no duplicates


def test_missing_inputs_are_named(tmp_path):
    with pytest.raises(InputError, match="input not found: .*nope.png"):
        features.collect_images([tmp_path / "nope.png"])
    with pytest.raises(InputError, match="no image files match"):
        features.collect_images(str(tmp_path / "*.jpg"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no image files"):
        features.collect_images(tmp_path / "empty")
    with pytest.raises(InputError, match="no image inputs"):
        features.collect_images([])


def test_one_image_is_refused(scene_dir):
    with pytest.raises(InputError, match="at least 2 images"):
        features.extract_images([scene_dir / "img1.png"])


def test_empty_or_broken_image_file(tmp_path, scene_dir):
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(InputError, match="cannot read image.*empty.png"):
        features.extract_images([scene_dir / "img1.png", tmp_path / "empty.png"])
    (tmp_path / "text.png").write_text("hello")
    with pytest.raises(InputError, match="cannot read image.*text.png"):
        features.extract(tmp_path / "text.png")


def test_blank_images_have_no_features(tmp_path, scene_dir):
    import cv2

    cv2.imwrite(str(tmp_path / "blank.png"), np.full((120, 160), 128, np.uint8))
    assert len(features.extract(tmp_path / "blank.png")) == 0
    with pytest.raises(InputError, match="features in only 1 of 2 images"):
        features.extract_images([scene_dir / "img1.png", tmp_path / "blank.png"])
    with pytest.raises(InputError, match="non-empty"):
        features.extract(np.zeros((0, 5), np.uint8))


def test_describe_at_given_keypoints(scene_dir):
    f = features.extract(scene_dir / "img1.png", max_features=100)
    again = features.describe_at(scene_dir / "img1.png", f.keypoints)  # own size and angle per point
    np.testing.assert_allclose(again.keypoints[:, :2], f.keypoints[:, :2], atol=1e-3)
    # not bit-identical (detection also fixes the pyramid octave), but each re-described feature
    # is nearest to its own detected descriptor
    d = np.linalg.norm(again.descriptors[:, None].astype(float) - f.descriptors[None].astype(float), axis=2)
    assert (d.argmin(axis=1) == np.arange(len(f))).mean() > 0.9
    upright = features.describe_at(scene_dir / "img1.png", f.keypoints[:, :2], size=24.0)
    assert upright.descriptors.shape == (len(f), 128)
    assert (upright.keypoints[:, 2] == 24.0).all()
    with pytest.raises(InputError, match=r"\(n, 2\)"):
        features.describe_at(scene_dir / "img1.png", np.zeros((3, 3)))
