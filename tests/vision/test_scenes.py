"""Generated multi-view scenes (dqm.vision.scenes): exact ground truth, determinism, Oxford layout."""
import numpy as np
import pytest

from dqm import InputError, evaluation
from dqm.vision import baselines as B
from dqm.vision import datasets, features, scenes


@pytest.fixture(scope="module")
def small():
    return scenes.generate_scene(4, (240, 320), seed=7)


def test_shape_and_types(small):
    assert len(small) == 4 and small.homographies.shape == (4, 3, 3)
    assert all(im.shape == (240, 320) and im.dtype == np.uint8 for im in small.images)
    np.testing.assert_allclose(small.homographies[0], np.eye(3), atol=1e-9)
    chained = small.homography(1, 2) @ small.homography(0, 1)
    np.testing.assert_allclose(chained / chained[2, 2], small.homography(0, 2), rtol=1e-9, atol=1e-9)


def test_deterministic_for_a_seed(small):
    again = scenes.generate_scene(4, (240, 320), seed=7)
    for a, b in zip(small.images, again.images):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(small.homographies, again.homographies)
    other = scenes.generate_scene(4, (240, 320), seed=8)
    assert not np.array_equal(small.images[0], other.images[0])


def test_homographies_map_view_0_onto_each_view(small):
    import cv2

    # without photometric change, blur and noise, warping view 0 by H reproduces view k
    clean = scenes.generate_scene(4, (240, 320), seed=7, photometric=0, blur=0, noise=0)
    for k in range(1, 4):
        H = clean.homography(0, k)
        warped = cv2.warpPerspective(clean.images[0], H, (320, 240), flags=cv2.INTER_LINEAR)
        inside = cv2.warpPerspective(np.full((240, 320), 255, np.uint8), H, (320, 240)) == 255
        inside = cv2.erode(inside.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        assert inside.mean() > 0.5
        err = np.abs(warped[inside].astype(float) - clean.images[k][inside].astype(float))
        assert np.median(err) < 4 and err.mean() < 8, (k, np.median(err), err.mean())


def test_sift_ratio_matches_agree_with_the_ground_truth(small):
    D, ids, kp = features.extract_many(small.images)
    assert set(np.unique(ids).tolist()) == {0, 1, 2, 3}
    a, b = B.pairwise_matches(D, ids, "bf", 0.75)
    truth = evaluation.HomographyTruth(kp, ids, small.homography, tol=5.0)
    good, _ = truth.correct(a, b)
    assert len(a) > 200 and good.mean() > 0.85, (len(a), good.mean())


def test_write_gives_an_oxford_folder(small, tmp_path):
    seq = small.write(tmp_path / "scene")
    assert isinstance(seq, datasets.HomographySequence)
    assert [p.name for p in seq.image_paths] == ["img1.png", "img2.png", "img3.png", "img4.png"]
    np.testing.assert_allclose(seq.homographies, small.homographies, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(features.read_gray(seq.image_paths[2]), small.images[2])


def test_bad_arguments():
    with pytest.raises(InputError, match="at least 2 images"):
        scenes.generate_scene(1)
    with pytest.raises(InputError, match="32x32"):
        scenes.generate_scene(3, (10, 10))
    with pytest.raises(InputError, match="viewpoint"):
        scenes.generate_scene(3, viewpoint=-1)
    with pytest.raises(InputError, match="noise"):
        scenes.generate_scene(3, noise=float("nan"))
