"""SE(3) conventions, pose interpolation and depth geometry against hand-computed values."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ggfslam.geometry.depth import backproject, normals_from_depth, project, transform_points
from ggfslam.geometry.pnp import pnp_ransac
from ggfslam.geometry.se3 import (
    from_gtsam, interpolate_poses, invert, look_at, make_pose, pose_from_tum, pose_to_tum, rigidity_error,
    rotation_angle, se3_exp, to_gtsam,
)


def random_pose(rng):
    return make_pose(Rotation.random(random_state=rng.integers(1 << 30)).as_matrix(), rng.normal(size=3))


def test_tum_round_trip_and_quaternion_order():
    # 90 degrees about z: TUM order qx qy qz qw = 0 0 sin45 cos45
    T = pose_from_tum([1, 2, 3, 0, 0, np.sqrt(0.5), np.sqrt(0.5)])
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [1, 2, 3])
    np.testing.assert_allclose(pose_to_tum(T), [1, 2, 3, 0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)


def test_invert_and_gtsam_conversion():
    rng = np.random.default_rng(0)
    T = random_pose(rng)
    np.testing.assert_allclose(invert(T) @ T, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(from_gtsam(to_gtsam(T)), T, atol=1e-12)


def test_se3_exp_matches_gtsam_right_retract():
    rng = np.random.default_rng(1)
    T0, xi = random_pose(rng), rng.normal(scale=0.3, size=6)
    retracted = from_gtsam(to_gtsam(T0).retract(xi))
    np.testing.assert_allclose(retracted, T0 @ se3_exp(xi), atol=1e-12)
    # rotation first: a pure omega leaves the translation alone
    np.testing.assert_allclose(se3_exp([0.1, 0, 0, 0, 0, 0])[:3, 3], 0, atol=1e-15)


def test_interpolation_midpoint():
    T0 = np.eye(4)
    T1 = make_pose(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [2, 0, 0])
    mid = interpolate_poses(np.array([0.0, 1.0]), np.stack([T0, T1]), np.array([0.5]))[0]
    np.testing.assert_allclose(mid[:3, 3], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(Rotation.from_matrix(mid[:3, :3]).as_euler("zyx", degrees=True), [45, 0, 0], atol=1e-9)


@pytest.mark.parametrize("bad,needle", [
    (np.full((4, 4), np.nan), "non-finite"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "reflection"),
    (np.diag([2.0, 1.0, 1.0, 1.0]), "orthonormal"),
    (np.eye(3), "4x4"),
])
def test_rigidity_error(bad, needle):
    assert needle in rigidity_error(bad)
    assert rigidity_error(np.eye(4)) is None


def test_look_at_uses_opencv_axes():
    T = look_at([0, 0, 0], [1, 0, 0], up=[0, 0, 1])
    np.testing.assert_allclose(T[:3, 2], [1, 0, 0], atol=1e-12)  # z forward
    np.testing.assert_allclose(T[:3, 1], [0, 0, -1], atol=1e-12)  # y down = -up
    assert rigidity_error(T) is None


def test_backproject_project_round_trip_and_plane_normals():
    fx, fy, cx, cy = 100.0, 110.0, 15.5, 11.5
    # a plane z = 2 + 0.5 x seen by the camera
    h, w = 24, 32
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    x_over_z = (u - cx) / fx
    depth = (2.0 / (1 - 0.5 * x_over_z)).astype(np.float32)
    P = backproject(depth, fx, fy, cx, cy)
    np.testing.assert_allclose(P[..., 2], 2 + 0.5 * P[..., 0], atol=1e-5)
    uv, z = project(P, fx, fy, cx, cy)
    np.testing.assert_allclose(uv[..., 0], u, atol=1e-9)
    np.testing.assert_allclose(uv[..., 1], v, atol=1e-9)
    n = normals_from_depth(depth, fx, fy, cx, cy)
    expected = np.array([0.5, 0, -1]) / np.linalg.norm([0.5, 0, -1])  # facing the camera
    np.testing.assert_allclose(n[1:-1, 1:-1].reshape(-1, 3), np.tile(expected, ((h - 2) * (w - 2), 1)), atol=1e-4)
    assert np.all(n[0] == 0) and np.all(n[:, -1] == 0)
    T = make_pose(np.eye(3), [1, 2, 3])
    np.testing.assert_allclose(transform_points(T, P)[0, 0], P[0, 0] + [1, 2, 3])


def test_rotation_angle_and_pnp_ransac_recover_a_known_pose():
    assert abs(rotation_angle(Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()) - np.linalg.norm([0.1, -0.2, 0.3])) < 1e-12
    assert rotation_angle(np.eye(3)) == 0.0
    rng = np.random.default_rng(0)
    T_wc = make_pose(Rotation.from_euler("xyz", [5, -10, 20], degrees=True).as_matrix(), [0.3, -0.1, 0.2])
    p_c = np.column_stack([rng.uniform(-1, 1, 60), rng.uniform(-0.7, 0.7, 60), rng.uniform(2, 4, 60)])
    p_w = p_c @ T_wc[:3, :3].T + T_wc[:3, 3]
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    uv = p_c[:, :2] / p_c[:, 2:] * 500.0 + [320, 240]
    uv[:10] += 40.0  # outliers
    T, inliers = pnp_ransac(p_w, uv, K, iterations=200, reprojection_px=2.0)
    assert set(range(10, 60)) <= set(inliers.tolist()) and not set(range(10)) & set(inliers.tolist())
    d = invert(T_wc) @ T
    assert np.linalg.norm(d[:3, 3]) < 1e-6 and rotation_angle(d[:3, :3]) < 1e-6


def test_resize_depth_keeps_pixel_centres_and_edges():
    from ggfslam.data.types import Camera
    from ggfslam.geometry.depth import resize_depth_image

    W, H = 64, 48
    cam = Camera(fx=50.0, fy=50.0, cx=31.5, cy=23.5, width=W, height=H)
    u = np.arange(W, dtype=np.float32)[None, :].repeat(H, 0)
    tilted = 1.0 + 0.01 * u  # [H, W] depth linear in u
    for k in (2, 4):
        small = cam.resized(W // k, H // k)
        r = resize_depth_image(tilted, small.width, small.height)
        # the resized pixel u' looks where the full-size pixel (u' + 0.5) k - 0.5 did (Camera.resized's rule);
        # plain INTER_NEAREST would take pixel k u', a (k - 1) / 2 pixel shift
        uc = (np.arange(small.width) + 0.5) * k - 0.5
        np.testing.assert_allclose(r, np.broadcast_to(1.0 + 0.01 * uc, r.shape), atol=1e-5)
        assert (small.cx + 0.5) * k - 0.5 == pytest.approx(cam.cx)
    step = np.where(u < 31, 1.0, 3.0).astype(np.float32)  # a depth edge inside a 4x4 block
    step[:, 29] = 0.0  # and a hole
    r = resize_depth_image(step, 16, 12)
    assert set(np.unique(r)) <= {0.0, 1.0, 3.0}  # no averaged depth between the two surfaces
