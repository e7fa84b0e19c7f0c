"""Camera-network geometry on exact synthetic cases: projection, box -> distance / bearing, homographies."""
import math

import numpy as np
import pytest

from dqm import InputError
from dqm.camnet.geometry import (
    Camera,
    Intrinsics,
    apply_homography,
    bounding_box,
    calibrate_range,
    camera_to_world_ground,
    clip_near,
    estimate_homography,
    localize_from_box,
    plane_homography,
    projected_quad,
    range_bearing_from_box,
)

K = Intrinsics.from_fov(62.0, 48.0, 640, 480)


def cam(x=0.0, y=0.0, yaw=0.0, z=0.35):
    return Camera("c", np.array([x, y, z]), yaw, 0.0, K)


def test_intrinsics_from_fov():
    assert K.fx == pytest.approx(320 / math.tan(math.radians(31)))
    assert K.fy == pytest.approx(240 / math.tan(math.radians(24)))
    assert (K.cx, K.cy) == (319.5, 239.5)
    assert math.degrees(K.hfov) == pytest.approx(62.0)
    with pytest.raises(InputError, match="hfov"):
        Intrinsics.from_fov(0.0, 48.0)
    with pytest.raises(InputError, match="image size"):
        Intrinsics.from_fov(62, 48, 4, 480)


def test_projection_axes_and_bearing():
    c = cam(1.0, 2.0, yaw=math.radians(90))  # looking along +y
    uv, z = c.project([[1.0, 5.0, 0.35]])  # 3 m straight ahead, at camera height
    assert z[0] == pytest.approx(3.0)
    assert uv[0] == pytest.approx([K.cx, K.cy])
    # a point to the right (east when looking north) projects right of centre
    uv, _ = c.project([[2.0, 5.0, 0.35]])
    assert uv[0, 0] > K.cx
    depth, dist, bearing = c.range_bearing(np.array([2.0, 5.0, 0.35]))
    assert depth == pytest.approx(3.0)
    assert dist == pytest.approx(math.hypot(1, 3))
    assert bearing == pytest.approx(math.atan2(1, 3))
    # above the camera -> smaller v (image y grows downwards); behind -> NaN
    uv, _ = c.project([[1.0, 5.0, 1.0], [1.0, 0.0, 0.35]])
    assert uv[0, 1] < K.cy and np.isnan(uv[1]).all()


@pytest.mark.parametrize("yaw_deg,bearing_deg,depth", [(0, 0, 3.0), (30, 10, 2.0), (-120, -20, 5.5), (200, 25, 1.2)])
def test_known_pose_gives_distance_bearing_and_position(yaw_deg, bearing_deg, depth):
    """A fronto-parallel face of known height at a known pose: box -> exact depth, bearing and position."""
    c = cam(0.7, -1.3, yaw=math.radians(yaw_deg))
    H_face, W_face = 0.4, 0.5
    b = math.radians(bearing_deg)
    f = np.array([math.cos(c.yaw), math.sin(c.yaw)])
    r = np.array([math.sin(c.yaw), -math.cos(c.yaw)])
    centre = c.position[:2] + depth * f + depth * math.tan(b) * r  # face centre at this depth and bearing
    corners = []
    for du in (-W_face / 2, W_face / 2):
        for z in (0.12, 0.12 + H_face):
            p = centre + du * r
            corners.append([p[0], p[1], z])
    uv, _ = c.project(corners)
    box = bounding_box(uv)
    k = calibrate_range(box[3] - box[1], depth)  # a known object at a known depth...
    assert k == pytest.approx(K.fy * H_face, rel=1e-9)  # ...gives fy x height (pinhole)
    d_est, b_est = range_bearing_from_box(box, K, K.fy * H_face)
    assert d_est == pytest.approx(depth, rel=1e-9)
    assert b_est == pytest.approx(b, abs=1e-9)
    assert localize_from_box(box, c, K.fy * H_face) == pytest.approx(centre, abs=1e-9)
    # moved along the line of sight by 'behind'
    p = localize_from_box(box, c, K.fy * H_face, behind=0.25)
    ray = centre - c.position[:2]
    assert p == pytest.approx(centre + 0.25 * ray / np.linalg.norm(ray), abs=1e-9)
    assert camera_to_world_ground(c, depth, b) == pytest.approx(centre, abs=1e-9)


def test_range_bearing_bad_input():
    with pytest.raises(InputError, match="height"):
        range_bearing_from_box((0, 10, 5, 10), K, 100.0)
    with pytest.raises(InputError, match="range_constant"):
        range_bearing_from_box((0, 0, 5, 10), K, -1.0)
    with pytest.raises(InputError, match="finite"):
        range_bearing_from_box((0, 0, float("nan"), 10), K, 100.0)
    with pytest.raises(InputError, match="positive"):
        calibrate_range(0.0, 2.0)


def test_plane_homography_matches_projection():
    c = cam(0, 0, yaw=0.3)
    origin, U, V = np.array([3.0, -0.5, 1.0]), np.array([0.0, 0.002, 0.0]), np.array([0.0, 0.0, -0.002])
    H = plane_homography(c, origin, U, V)
    st = np.array([[0, 0], [400, 0], [400, 300], [17, 230]], float)
    world = origin + st[:, :1] * U + st[:, 1:] * V
    uv, _ = c.project(world)
    assert apply_homography(H, st) == pytest.approx(uv, abs=1e-6)
    with pytest.raises(InputError, match="parallel"):
        plane_homography(c, origin, U, 2 * U)


def test_clip_near():
    quad = np.array([[-1, 0, -1.0], [1, 0, -1.0], [1, 0, 3.0], [-1, 0, 3.0]])
    out = clip_near(quad, 0.5)
    assert (out[:, 2] >= 0.5 - 1e-12).all() and len(out) == 4
    assert clip_near(quad - [0, 0, 10], 0.5).shape == (0, 3)


def test_known_homography_is_recovered_from_points():
    rng = np.random.default_rng(0)
    H = np.array([[0.8, 0.1, 40.0], [-0.05, 0.9, 20.0], [2e-4, -1e-4, 1.0]])
    src = rng.uniform(0, 400, (60, 2))
    dst = apply_homography(H, src) + rng.normal(0, 0.5, (60, 2))
    dst[:15] = rng.uniform(0, 600, (15, 2))  # 25% outliers
    H_est, inliers = estimate_homography(src, dst, threshold=10.0)
    assert H_est is not None
    assert inliers[15:].mean() > 0.95 and inliers[:15].mean() < 0.2
    corners = np.array([[0, 0], [400, 0], [400, 300], [0, 300]], float)
    assert np.abs(apply_homography(H_est, corners) - apply_homography(H, corners)).max() < 2.0
    # repeatable
    H2, _ = estimate_homography(src, dst, threshold=10.0)
    assert np.array_equal(H_est, H2)
    # too few points or no consensus -> None
    assert estimate_homography(src[:3], dst[:3])[0] is None
    with pytest.raises(InputError, match="length"):
        estimate_homography(src[:5], dst[:4])
    with pytest.raises(InputError, match="threshold"):
        estimate_homography(src, dst, threshold=0)


def test_known_homography_is_recovered_from_images():
    """SIFT + BF ratio matches between a texture and its warp by a known homography give that homography."""
    import cv2

    from dqm.camnet.pipeline import pairwise_pair_candidates
    from dqm.vision.features import extract
    from dqm.vision.scenes import texture

    ref = texture(320, 400, seed=5, density=1.6)
    H = np.array([[0.55, 0.08, 150.0], [-0.04, 0.6, 110.0], [3e-4, 1e-4, 1.0]])
    img = cv2.warpPerspective(ref, H, (640, 480), borderValue=128)
    fr, fi = extract(ref, "paper"), extract(img, "paper")
    a, b = pairwise_pair_candidates(fr, fi, "bf").select(0.75)
    H_est, inl = estimate_homography(fr.keypoints[a, :2], fi.keypoints[b, :2], 10.0)
    assert H_est is not None and inl.sum() >= 10
    q_true = projected_quad(H, 400, 320)
    q_est = projected_quad(H_est, 400, 320)
    assert np.abs(q_est - q_true).max() < 3.0


def test_projected_quad_rejects_folded_and_behind():
    assert projected_quad(np.eye(3), 10, 5) == pytest.approx(np.array([[0, 0], [10, 0], [10, 5], [0, 5]]))
    fold = np.array([[1.0, 0, 0], [0, 1.0, 0], [-0.15, 0, 1.0]])  # w changes sign inside the rectangle
    assert projected_quad(fold, 10, 5) is None
    mirror = np.array([[-1.0, 0, 10], [0, 1.0, 0], [0, 0, 1.0]])
    assert projected_quad(mirror, 10, 5) is not None  # a mirror image is still a convex quad
    line = np.array([[1.0, 1.0, 0], [1.0, 1.0, 0], [0, 0, 1.0]])  # rank 2: the rectangle collapses to a line
    assert projected_quad(line, 10, 5) is None
    assert projected_quad(np.full((3, 3), np.nan), 10, 5) is None


def test_camera_validation():
    with pytest.raises(InputError, match="position"):
        Camera("c", np.array([0, 0]), 0.0, 0.0, K)
    with pytest.raises(InputError, match="pitch"):
        Camera("c", np.zeros(3), 0.0, math.radians(95), K)
    with pytest.raises(InputError, match="yaw"):
        Camera("c", np.zeros(3), float("inf"), 0.0, K)
