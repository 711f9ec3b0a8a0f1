"""Factor-graph vocabulary: variable keys, calibrations, noise models and RGB-D observation factors (GTSAM).

Keyframe poses are ``X(kf_id)`` (gtsam.Pose3, camera-to-world, OpenCV axes as GTSAM's cameras use), landmarks
``L(lm_id)`` (gtsam.Point3, world), plane landmarks ``P(plane_id)`` (gtsam.OrientedPlane3, world). An RGB-D observation is GTSAM's stereo factor on a virtual stereo camera:
the depth z of a keypoint at (u, v) becomes a right-image coordinate u_r = u - f_x b / z (RGB-D ORB-SLAM), so
pixel and depth errors share one whitened 3-vector. Keypoints without depth use a 2-D projection factor.
"""
from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, P, X

from ggfslam.data.types import Camera

__all__ = ["L", "P", "X", "calibrations", "observation_factor", "is_stereo_factor", "whitened_chi2"]


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
        noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(huber_stereo), gtsam.noiseModel.Isotropic.Sigma(3, sigma))
        return gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(uv[0], ur, uv[1]), noise, X(kf_id), L(lm_id), stereo)
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(huber_mono), gtsam.noiseModel.Isotropic.Sigma(2, sigma))
    return gtsam.GenericProjectionFactorCal3_S2(gtsam.Point2(uv[0], uv[1]), noise, X(kf_id), L(lm_id), mono)


def is_stereo_factor(factor) -> bool:
    """True for an RGB-D (virtual stereo) observation factor."""
    return isinstance(factor, gtsam.GenericStereoFactor3D)


def whitened_chi2(factor, values: gtsam.Values, sigma: float) -> float:
    """Squared whitened error of an observation factor ignoring its robust kernel (for outlier tests)."""
    e = np.asarray(factor.unwhitenedError(values))
    return float(np.sum(e ** 2) / sigma ** 2)
