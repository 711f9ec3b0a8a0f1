"""SE(3) helpers in numpy, and the project's coordinate conventions.

Conventions (used everywhere in ggfslam):
- A pose called ``T_wc`` maps camera coordinates to world coordinates (camera-to-world); ``T_cw`` is its
  inverse. Poses are 4x4 float64 matrices unless a name says otherwise.
- Camera axes follow OpenCV: x right, y down, z forward (depth along +z).
- Quaternions in files (TUM format) are ordered ``qx qy qz qw``; in memory ``quat_xyzw`` says the same.
- GTSAM tangent vectors are ``xi = [omega, v]`` (rotation first) with ``T = T0 * Exp(xi)`` (right,
  body-frame perturbation), as in ``gtsam.Pose3.retract``.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build a 4x4 pose from a rotation [3, 3] and a translation [3]."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def rotation_angle(R: np.ndarray) -> float:
    """Angle (rad) of a rotation matrix [3, 3]."""
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def mean_rotation(Rs: np.ndarray) -> np.ndarray:
    """Chordal mean [3, 3] of rotations [N, 3, 3]: the rotation nearest their sum (SVD projection)."""
    U, _, Vt = np.linalg.svd(np.asarray(Rs, np.float64).sum(axis=0))
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform [4, 4] (or a stack [N, 4, 4])."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def pose_from_tum(values: np.ndarray) -> np.ndarray:
    """Pose [4, 4] from TUM values ``tx ty tz qx qy qz qw`` (quaternion normalised)."""
    values = np.asarray(values, dtype=np.float64)
    q = values[3:7] / np.linalg.norm(values[3:7])
    return make_pose(Rotation.from_quat(q).as_matrix(), values[:3])


def pose_to_tum(T: np.ndarray) -> np.ndarray:
    """TUM values ``tx ty tz qx qy qz qw`` [7] from a pose [4, 4], with qw >= 0."""
    q = Rotation.from_matrix(T[:3, :3]).as_quat()  # [4] xyzw
    if q[3] < 0:
        q = -q
    return np.concatenate([T[:3, 3], q])


def rigidity_error(T: np.ndarray) -> str | None:
    """Describe why a 4x4 matrix is not a finite rigid transform, or return None if it is one."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        return f"expected a 4x4 matrix, got shape {T.shape}"
    if not np.all(np.isfinite(T)):
        return "pose has non-finite values"
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6):
        return f"last row must be [0 0 0 1], got {T[3].tolist()}"
    R = T[:3, :3]
    orth = np.abs(R @ R.T - np.eye(3)).max()
    if orth > 1e-3:
        return f"rotation part is not orthonormal (max |R R^T - I| = {orth:.3g})"
    det = np.linalg.det(R)
    if det < 0:
        return f"rotation part is a reflection (det = {det:.3g})"
    return None


def interpolate_poses(times: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Interpolate poses [N, 4, 4] at sorted ``times`` [N] to ``query`` [M]: slerp rotation, lerp translation."""
    times = np.asarray(times, dtype=np.float64)
    query = np.asarray(query, dtype=np.float64)
    if len(times) == 1:
        return np.repeat(poses[:1], len(query), axis=0)
    q = np.clip(query, times[0], times[-1])
    rots = Slerp(times, Rotation.from_matrix(poses[:, :3, :3]))(q).as_matrix()  # [M, 3, 3]
    trans = np.stack([np.interp(q, times, poses[:, :3, 3][:, k]) for k in range(3)], axis=1)  # [M, 3]
    out = np.tile(np.eye(4), (len(query), 1, 1))
    out[:, :3, :3] = rots
    out[:, :3, 3] = trans
    return out


def so3_exp(omega: np.ndarray) -> np.ndarray:
    """Rotation matrix [3, 3] from an axis-angle vector [3]."""
    return Rotation.from_rotvec(np.asarray(omega, dtype=np.float64)).as_matrix()


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """GTSAM's Pose3 exponential map: 4x4 pose from ``xi = [omega, v]`` [6]."""
    import gtsam

    return gtsam.Pose3.Expmap(np.asarray(xi, dtype=np.float64)).matrix()


def to_gtsam(T: np.ndarray):
    """Convert a 4x4 pose to ``gtsam.Pose3``."""
    import gtsam

    return gtsam.Pose3(np.asarray(T, dtype=np.float64))


def from_gtsam(pose) -> np.ndarray:
    """Convert a ``gtsam.Pose3`` to a 4x4 pose."""
    return np.asarray(pose.matrix(), dtype=np.float64)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) at ``eye`` looking at ``target`` with world ``up`` pointing image-up."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))  # right = forward x up, so y = forward x right is down
    if np.linalg.norm(x) < 1e-9:  # looking straight along up: pick any perpendicular
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_pose(np.stack([x, y, z], axis=1), eye)
