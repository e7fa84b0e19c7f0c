"""Camera poses against ground truth (dqm.vision.poses): readers, the similarity alignment, the pairwise
errors and the AUC, on cameras whose errors are known by construction."""
import math

import numpy as np
import pytest

from dqm.validation import InputError
from dqm.vision import poses


def rotation(axis, degrees):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    a = math.radians(degrees)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K


def ring_of_cameras(n=6, seed=0):
    """n cameras on an arc looking at the origin, in general position."""
    rng = np.random.default_rng(seed)
    out = {}
    for k in range(n):
        C = np.array([4 * math.cos(0.3 * k), 0.5 * rng.standard_normal(), 4 * math.sin(0.3 * k) + 8])
        R = rotation(rng.standard_normal(3), rng.uniform(2, 20))
        out[f"{k:04d}.jpg"] = poses.Pose(R, C)
    return out


def moved(gt, s, Q, T):
    """The same cameras in another frame: x' = s Q x + T (a model's arbitrary gauge)."""
    return {n: poses.Pose(p.R @ Q.T, s * Q @ p.C + T) for n, p in gt.items()}


def test_a_model_in_another_frame_has_no_error():
    gt = ring_of_cameras()
    est = moved(gt, 0.37, rotation([1, 2, 3], 71), np.array([5.0, -2, 9]))
    s = poses.evaluate_poses(est, gt)
    assert s.registered == 6 and s.n_truth == 6
    assert s.median_rotation_deg < 1e-5 and s.median_centre_error < 1e-9
    assert all(v == pytest.approx(1.0) for v in s.auc.values())


def test_umeyama_recovers_the_similarity():
    rng = np.random.default_rng(1)
    X = rng.standard_normal((20, 3))
    Q = rotation([0.3, -1, 0.2], 40)
    s, Qe, T = poses.umeyama(X, 2.5 * X @ Q.T + [1, 2, 3])
    assert s == pytest.approx(2.5) and np.allclose(Qe, Q) and np.allclose(T, [1, 2, 3])


def test_one_rotated_camera_gives_exactly_its_angle_in_its_pairs():
    gt = ring_of_cameras(4)
    est = dict(gt)
    p = gt["0002.jpg"]
    # turn camera 2 about its own centre by 3 degrees: its relative rotations to the others are off by 3
    est["0002.jpg"] = poses.Pose(rotation([0, 1, 0], 3.0) @ p.R, p.C)
    names = sorted(gt)
    e = poses.relative_errors(est, gt, names)
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    for (a, b), err in zip(pairs, e):
        if "0002.jpg" in (a, b):
            assert err >= 3.0 - 1e-9  # the rotation error is 3; the translation direction may be off more
        else:
            assert err < 1e-6


def test_missing_images_count_as_infinite_errors():
    gt = ring_of_cameras(5)
    est = {n: p for n, p in gt.items() if n != "0004.jpg"}
    s = poses.evaluate_poses(est, gt)
    assert s.registered == 4
    # 4 of the 10 pairs involve the missing image: the AUC of every threshold is 6/10
    assert all(v == pytest.approx(0.6) for v in s.auc.values())


def test_auc_is_the_area_under_the_recall_curve():
    # errors 0.5 and 1.5 degrees: the recall curve joins (0, 0), (0.5, 1/2), (1.5, 1) and stays flat after
    # the last error below the threshold. Up to 1 degree: 0.125 (the first segment) + 0.5 x 0.5 = 0.375.
    # Up to 2: 0.125 + (1/2 + 1)/2 x 1 + 1 x 0.5 = 1.375, over 2 = 0.6875.
    assert poses.pose_auc([0.5, 1.5], [1.0, 2.0]) == pytest.approx([0.375, 0.6875])
    assert poses.pose_auc([0.0, 0.0], [1.0]) == pytest.approx([1.0])
    assert poses.pose_auc([math.inf] * 3, [5.0]) == pytest.approx([0.0])


def test_strecha_camera_file_round_trip(tmp_path):
    gt = ring_of_cameras(3)
    K = np.array([[2759.5, 0, 1520.7], [0, 2764.2, 1006.8], [0, 0, 1]])
    for name, p in gt.items():
        rows = [*K.tolist(), [0, 0, 0], *p.R.T.tolist(), p.C.tolist(), [3072, 2048]]
        (tmp_path / f"{name}.camera").write_text("\n".join(" ".join(f"{v:.12g}" for v in r) for r in rows) + "\n")
    back = poses.read_ground_truth(tmp_path)
    assert sorted(back) == sorted(gt)
    for n in gt:
        assert np.allclose(back[n].R, gt[n].R) and np.allclose(back[n].C, gt[n].C)
    pose, K2, size = poses.read_strecha_camera(tmp_path / "0000.jpg.camera")
    assert np.allclose(K2, K) and size == (3072, 2048)


def test_bad_ground_truth_is_one_line(tmp_path):
    with pytest.raises(InputError, match="absent: no such folder"):
        poses.read_ground_truth(tmp_path / "absent")
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="file: not a folder"):
        poses.read_ground_truth(tmp_path / "file")
    with pytest.raises(InputError, match="neither Strecha"):
        poses.read_ground_truth(tmp_path)
    (tmp_path / "a.jpg.camera").write_text("1 0 0\n0 1 0\n0 0 1\n0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(InputError, match=r"a\.jpg\.camera:7: expected 3 numbers"):
        poses.read_ground_truth(tmp_path)
    (tmp_path / "a.jpg.camera").write_text("1 0 0\n0 1 0\n0 0 1\n0 0 0\n2 0 0\n0 1 0\n0 0 1\n0 0 0\n10 10\n")
    with pytest.raises(InputError, match="not a rotation"):
        poses.read_ground_truth(tmp_path)


def test_restrict_matches_by_file_name_and_refuses_no_overlap():
    gt = ring_of_cameras(3)
    sub = poses.restrict(gt, ["photos/0000.jpg", "photos/0002.jpg", "photos/extra.jpg"])
    assert sorted(sub) == ["0000.jpg", "0002.jpg"]
    with pytest.raises(InputError, match="no camera for any of the 2 images"):
        poses.restrict(gt, ["x.jpg", "y.jpg"], "--gt g")
