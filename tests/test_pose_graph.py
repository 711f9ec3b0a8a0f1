"""Pose-graph optimisation (GTSAM) and moving map points with their keyframes."""
from __future__ import annotations

import numpy as np
import pytest

from ggfslam.backend.pose_graph import PoseEdge, correct_points, optimize_pose_graph, solve_pose_graph
from ggfslam.geometry.se3 import invert, make_pose, se3_exp, so3_exp

SIG_ROT = np.radians(0.5)  # odometry noise model per step
SIG_TRANS = 0.01


def ring_poses(n: int) -> list[np.ndarray]:
    """Ground-truth camera-to-world poses [4, 4] on a closed 2 m-radius ring with some height change."""
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        out.append(make_pose(so3_exp([0.0, 0.0, a]), [2 * np.cos(a) - 2, 2 * np.sin(a), 0.1 * np.sin(3 * a)]))
    return out


def drifting_chain(n: int = 60, seed: int = 0, yaw_bias_deg: float = 0.4):
    """Ground truth, dead-reckoned estimate and odometry edges of a ring walked with a yaw bias plus noise."""
    rng = np.random.default_rng(seed)
    gt = ring_poses(n)
    est = [gt[0].copy()]
    edges = []
    for k in range(n - 1):
        rel = invert(gt[k]) @ gt[k + 1]
        noise = np.concatenate([rng.normal(0, 0.1 * SIG_ROT, 3) + [0, 0, np.radians(yaw_bias_deg)],
                                rng.normal(0, 0.1 * SIG_TRANS, 3)])
        meas = rel @ se3_exp(noise)
        edges.append(PoseEdge(k, k + 1, meas, SIG_ROT, SIG_TRANS, "odometry"))
        est.append(est[-1] @ meas)
    return gt, dict(enumerate(est)), edges


def ate(gt: list[np.ndarray], poses: dict[int, np.ndarray]) -> float:
    """RMS position error (m); pose 0 is fixed at ground truth, so no alignment is needed."""
    return float(np.sqrt(np.mean([np.sum((gt[k][:3, 3] - T[:3, 3]) ** 2) for k, T in poses.items()])))


def loop_edge(gt, i: int, j: int, error: np.ndarray | None = None) -> PoseEdge:
    """Loop edge i -> j from ground truth, optionally corrupted by ``error`` = [omega, v]."""
    T_ij = invert(gt[i]) @ gt[j]
    if error is not None:
        T_ij = T_ij @ se3_exp(np.asarray(error, float))
    return PoseEdge(i, j, T_ij, 0.01, 0.01, "loop")


def test_correct_loop_removes_most_drift():
    gt, est, edges = drifting_chain()
    n = len(gt)
    before = ate(gt, est)
    assert before > 0.3  # the bias makes a clearly open loop
    res = solve_pose_graph(est, edges + [loop_edge(gt, n - 1, 0)], fixed_ids={0})
    after = ate(gt, res.poses)
    assert after < 0.3 * before, (before, after)
    assert res.rejected_loops == []
    assert res.error_after < res.error_before
    # the loop is closed: the last pose sits where the loop edge says, relative to the first
    np.testing.assert_allclose((invert(res.poses[n - 1]) @ res.poses[0])[:3, 3],
                               (invert(gt[n - 1]) @ gt[0])[:3, 3], atol=0.03)


def test_fixed_poses_stay_exactly_fixed():
    gt, est, edges = drifting_chain()
    n = len(gt)
    # plain least squares: with pose 30 held at its drifted estimate the loop disagrees with the chain
    res = optimize_pose_graph(est, edges + [loop_edge(gt, n - 1, 0)], fixed_ids={0, 30}, robust=False)
    assert np.array_equal(res[0], est[0])
    assert np.array_equal(res[30], est[30])
    assert not np.allclose(res[45], est[45])  # the others did move


def test_wrong_loop_does_less_damage_with_robust_kernel():
    gt, est, edges = drifting_chain()
    n = len(gt)
    good = loop_edge(gt, n - 1, 0)
    wrong = loop_edge(gt, n - 1, 20, error=[0.3, 0.0, 0.2, 0.5, 0.3, 0.0])  # aliasing: 0.6 m and 20 deg off
    only_good = ate(gt, optimize_pose_graph(est, edges + [good], {0}))
    l2 = ate(gt, optimize_pose_graph(est, edges + [good, wrong], {0}, robust=False))
    res = solve_pose_graph(est, edges + [good, wrong], {0}, robust=True)
    robust = ate(gt, res.poses)
    assert robust < 0.5 * l2, (robust, l2)
    assert robust == pytest.approx(only_good, abs=0.005)
    assert res.rejected_loops == [len(edges) + 1]  # the wrong loop, not the good one
    # a lone gross wrong loop on a chain with little drift: the kernel keeps it from bending the chain
    gt, est, edges = drifting_chain(yaw_bias_deg=0.05)
    lone_l2 = ate(gt, optimize_pose_graph(est, edges + [wrong], {0}, robust=False))
    lone = solve_pose_graph(est, edges + [wrong], {0}, robust=True)
    assert ate(gt, est) < 0.1 < 0.3 < lone_l2
    assert lone.rejected_loops == [len(edges)]
    assert ate(gt, lone.poses) == pytest.approx(ate(gt, est), abs=1e-6)


def test_huber_kernel_and_covariance_edges():
    gt, est, edges = drifting_chain(n=20)
    good = loop_edge(gt, 19, 0)
    cov = np.diag([0.01 ** 2] * 3 + [0.01 ** 2] * 3)
    as_cov = PoseEdge(good.i, good.j, good.T_ij, kind="loop", covariance=cov)
    a = optimize_pose_graph(est, edges + [good], {0}, robust_kernel="huber")
    b = optimize_pose_graph(est, edges + [as_cov], {0}, robust_kernel="huber")
    for k in a:
        np.testing.assert_allclose(a[k], b[k], atol=1e-9)
    assert ate(gt, a) < ate(gt, est)


def test_edge_convention_and_anchoring():
    T0 = make_pose(so3_exp([0.1, -0.2, 0.3]), [1.0, 2.0, 3.0])
    T_01 = make_pose(so3_exp([0.0, 0.4, 0.0]), [0.5, 0.0, -0.2])
    poses = {0: T0, 1: np.eye(4), 7: T0 @ T_01, 8: np.eye(4)}
    edges = [PoseEdge(0, 1, T_01), PoseEdge(7, 8, T_01)]
    res = solve_pose_graph(poses, edges, fixed_ids={0}, robust=False)
    np.testing.assert_allclose(res.poses[1], T0 @ T_01, atol=1e-9)  # T_ij = inv(T_wi) @ T_wj
    # the second component {7, 8} has no fixed pose: its smallest id is held
    assert res.anchored_ids == {0, 7}
    assert np.array_equal(res.poses[7], poses[7])
    np.testing.assert_allclose(res.poses[8], poses[7] @ T_01, atol=1e-9)


def test_invalid_input():
    poses = {0: np.eye(4), 1: np.eye(4)}
    with pytest.raises(ValueError, match="pose 5 is not in the graph"):
        optimize_pose_graph(poses, [PoseEdge(0, 5, np.eye(4))], {0})
    with pytest.raises(ValueError, match="unknown kind"):
        optimize_pose_graph(poses, [PoseEdge(0, 1, np.eye(4), kind="gps")], {0})
    with pytest.raises(ValueError, match="fixed ids not in the graph"):
        optimize_pose_graph(poses, [PoseEdge(0, 1, np.eye(4))], {3})
    with pytest.raises(ValueError, match="sigmas must be positive"):
        optimize_pose_graph(poses, [PoseEdge(0, 1, np.eye(4), sigmas_rot=0.0)], {0})
    with pytest.raises(ValueError, match="robust kernel"):
        optimize_pose_graph(poses, [PoseEdge(0, 1, np.eye(4), kind="loop")], {0}, robust_kernel="tukey")
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError, match="pose 1: rotation part is not orthonormal"):
        optimize_pose_graph({0: np.eye(4), 1: bad}, [], {0})


def test_correct_points_moves_points_with_their_keyframe():
    old = {3: np.eye(4), 4: make_pose(np.eye(3), [0.0, 0.0, 1.0])}
    Rz90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    new = {3: make_pose(Rz90, [1.0, 2.0, 3.0]), 4: make_pose(np.eye(3), [0.0, 0.0, 2.0])}
    pts = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [5.0, 5.0, 5.0], [9.0, 9.0, 9.0], [1.0, 1.0, 1.0]])
    ref = np.array([3, 3, 4, -1, 99])  # -1: no keyframe; 99: unknown keyframe -> unchanged
    out = correct_points(pts, ref, old, new)
    expected = np.array([[1.0, 3.0, 3.0],  # Rz90 (1, 0, 0) = (0, 1, 0), plus (1, 2, 3)
                         [-1.0, 2.0, 3.0],  # Rz90 (0, 2, 0) = (-2, 0, 0), plus (1, 2, 3)
                         [5.0, 5.0, 6.0],  # keyframe 4 moved up by 1 m
                         [9.0, 9.0, 9.0],
                         [1.0, 1.0, 1.0]])
    np.testing.assert_allclose(out, expected, atol=1e-12)
    # a point moves exactly like its keyframe: same coordinates in that camera before and after
    p_cam_old = (invert(old[3]) @ np.append(pts[0], 1.0))[:3]
    p_cam_new = (invert(new[3]) @ np.append(out[0], 1.0))[:3]
    np.testing.assert_allclose(p_cam_new, p_cam_old, atol=1e-12)
    with pytest.raises(ValueError, match="ref_ids"):
        correct_points(pts, ref[:2], old, new)
