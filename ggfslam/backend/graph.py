"""Factor-graph vocabulary: variable keys, calibrations, noise models and RGB-D observation factors (GTSAM).

Keyframe poses are ``X(kf_id)`` (gtsam.Pose3, camera-to-world, OpenCV axes as GTSAM's cameras use), landmarks
``L(lm_id)`` (gtsam.Point3, world), plane landmarks ``P(plane_id)`` (gtsam.OrientedPlane3, world). An RGB-D observation is GTSAM's stereo factor on a virtual stereo camera:
the depth z of a keypoint at (u, v) becomes a right-image coordinate u_r = u - f_x b / z (RGB-D ORB-SLAM), so
pixel and depth errors share one whitened 3-vector. Keypoints without depth use a 2-D projection factor.
"""
from __future__ import annotations

import functools

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, P, X

from ggfslam.data.types import Camera

__all__ = ["L", "P", "X", "huber_loss", "observation_errors", "calibrations", "observation_factor", "whitened_chi2",
           "odometry_link_factor", "plane_factor"]


def calibrations(camera: Camera, baseline: float) -> tuple[gtsam.Cal3_S2, gtsam.Cal3_S2Stereo]:
    """Mono and virtual-stereo calibrations of the camera."""
    mono = gtsam.Cal3_S2(camera.fx, camera.fy, 0.0, camera.cx, camera.cy)
    stereo = gtsam.Cal3_S2Stereo(camera.fx, camera.fy, 0.0, camera.cx, camera.cy, baseline)
    return mono, stereo


def observation_factor(
    kf_id: int, lm_id: int, uv: np.ndarray, depth: float, sigma: float, mono: gtsam.Cal3_S2,
    stereo: gtsam.Cal3_S2Stereo, huber_stereo: float, huber_mono: float,
):
    """The robust (Huber) RGB-D factor for one keypoint observation; a projection factor when depth is 0."""
    if depth > 0:
        ur = uv[0] - stereo.fx() * stereo.baseline() / depth
        noise = robust_isotropic(3, float(sigma), huber_stereo)
        return gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(uv[0], ur, uv[1]), noise, X(kf_id), L(lm_id), stereo)
    noise = robust_isotropic(2, float(sigma), huber_mono)
    return gtsam.GenericProjectionFactorCal3_S2(gtsam.Point2(uv[0], uv[1]), noise, X(kf_id), L(lm_id), mono)


@functools.lru_cache(maxsize=1024)
def robust_isotropic(dim: int, sigma: float, huber: float):
    """Huber-robust isotropic noise of ``dim`` rows, made once per (dim, sigma, huber) and shared by the factors
    (GTSAM's noise models are immutable; a local BA late in a long run makes ~13k factors from a few pyramid-level
    sigmas, and building the model took a third of each factor's cost)."""
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber),
                                          gtsam.noiseModel.Isotropic.Sigma(dim, sigma))


def odometry_link_factor(other_id: int, kf_id: int, T_other_kf: np.ndarray, sigmas: tuple[float, float]):
    """Between factor tying keyframe ``kf_id`` to ``other_id`` at the dense-odometry relative pose T_other_kf
    [4, 4]; ``sigmas`` = (rotation rad, translation m), as ``tracking.dense_link_sigmas``."""
    s_rot, s_trans = sigmas
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([s_rot] * 3 + [s_trans] * 3))
    return gtsam.BetweenFactorPose3(X(other_id), X(kf_id), gtsam.Pose3(T_other_kf), noise)


def plane_factor(kf_id: int, plane_id: int, measured: np.ndarray, sigmas: tuple[float, float]):
    """Observation of plane landmark ``plane_id`` by keyframe ``kf_id``: camera-frame coefficients [4] (n, d);
    ``sigmas`` = (normal rad, distance m), as ``backend.plane_sigmas``."""
    s_n, s_d = sigmas
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([s_n, s_n, s_d]))
    return gtsam.OrientedPlane3Factor(np.asarray(measured, np.float64), noise, X(kf_id), P(plane_id))


def whitened_chi2(factor, values: gtsam.Values, sigma: float) -> float:
    """Squared whitened error of an observation factor ignoring its robust kernel (for outlier tests)."""
    e = np.asarray(factor.unwhitenedError(values))
    return float(np.sum(e ** 2) / sigma ** 2)


def huber_loss(norm: np.ndarray, k: float) -> np.ndarray:
    """GTSAM's Huber loss of whitened residual norms: 0.5 n^2 inside k, k n - 0.5 k^2 outside."""
    return np.where(norm <= k, 0.5 * norm ** 2, k * norm - 0.5 * k * k)


def observation_errors(T_wc: np.ndarray, points: np.ndarray, uv: np.ndarray, depth: np.ndarray,
                       sigma: np.ndarray, camera: Camera, baseline: float, huber_stereo: float,
                       huber_mono: float) -> tuple[np.ndarray, np.ndarray]:
    """GTSAM errors [M] and kernel-free chi2 [M] of M observation factors (stereo where depth > 0, else mono).

    T_wc [M, 4, 4] observing poses, points [M, 3] world landmarks, uv [M, 2] keypoints, depth [M], sigma [M].
    """
    R, t = T_wc[:, :3, :3], T_wc[:, :3, 3]
    q = np.einsum("mji,mj->mi", R, points - t)  # [M, 3] R^T (p - t): the point in the camera frame
    behind = q[:, 2] <= 0  # GTSAM's cheirality exception: the factor returns a constant 2 fx residual
    inv_z = 1.0 / np.where(behind, 1.0, q[:, 2])
    u = camera.cx + camera.fx * q[:, 0] * inv_z
    v = camera.cy + camera.fy * q[:, 1] * inv_z
    stereo = depth > 0
    # virtual right-image coordinate of the measurement and of the prediction (graph.observation_factor)
    ur_meas = uv[:, 0] - camera.fx * baseline / np.where(stereo, depth, 1.0)
    ur_pred = u - camera.fx * baseline * inv_z
    sq = (u - uv[:, 0]) ** 2 + (v - uv[:, 1]) ** 2 + np.where(stereo, (ur_pred - ur_meas) ** 2, 0.0)
    sq = np.where(behind, np.where(stereo, 3.0, 2.0) * (2.0 * camera.fx) ** 2, sq)
    chi2 = sq / sigma ** 2
    norm = np.sqrt(chi2)
    error = np.where(stereo, huber_loss(norm, huber_stereo), huber_loss(norm, huber_mono))
    return error, chi2
