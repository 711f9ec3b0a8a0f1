"""Baseline tracker: Open3D multi-scale RGB-D odometry from each frame to the previous one.

It is a yardstick, not the system's frontend: it drifts, and has no map, keyframes or loop closure.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d

from ggfslam.config import TrackingConfig
from ggfslam.data.types import Camera, Frame
from ggfslam.geometry.se3 import rigidity_error

_METHODS = {
    "hybrid": o3d.t.pipelines.odometry.Method.Hybrid,
    "color": o3d.t.pipelines.odometry.Method.Intensity,
    "point_to_plane": o3d.t.pipelines.odometry.Method.PointToPlane,
}


@dataclass
class TrackResult:
    """Outcome of tracking one frame."""

    T_wc: np.ndarray  # [4, 4] camera-to-world estimate
    ok: bool  # False when the odometry failed and the motion model was used instead
    fitness: float  # fraction of pixels with a correspondence (Open3D's measure)


class OdometryBaselineTracker:
    """Frame-to-frame Open3D RGB-D odometry with a constant-velocity initial guess."""

    name = "o3d_odometry"

    def __init__(self, camera: Camera, cfg: TrackingConfig):
        self.cfg = cfg
        scale = min(1.0, cfg.max_width / camera.width)
        self.size = (max(1, round(camera.width * scale)), max(1, round(camera.height * scale)))
        self.camera = camera.resized(*self.size) if scale < 1.0 else camera
        self.intrinsics = o3d.core.Tensor(self.camera.K, o3d.core.Dtype.Float64)
        self.criteria = [o3d.t.pipelines.odometry.OdometryConvergenceCriteria(int(n)) for n in cfg.iterations]
        self.method = _METHODS[cfg.odometry_term]
        self.prev: o3d.t.geometry.RGBDImage | None = None
        self.T_wc = np.eye(4)
        self.velocity = np.eye(4)  # T_prev_cur of the last step

    def _rgbd(self, frame: Frame) -> o3d.t.geometry.RGBDImage:
        rgb, depth = frame.rgb, frame.depth
        if (frame.width, frame.height) != self.size:
            rgb = cv2.resize(rgb, self.size, interpolation=cv2.INTER_AREA)
            depth = cv2.resize(depth, self.size, interpolation=cv2.INTER_NEAREST)
        color = o3d.t.geometry.Image(np.ascontiguousarray(rgb, dtype=np.float32))
        dimg = o3d.t.geometry.Image(np.ascontiguousarray(depth, dtype=np.float32))
        return o3d.t.geometry.RGBDImage(color, dimg)

    def track(self, frame: Frame) -> TrackResult:
        """Estimate the camera-to-world pose of the next frame (the first frame defines the world)."""
        cur = self._rgbd(frame)
        if self.prev is None:
            self.prev = cur
            return TrackResult(self.T_wc.copy(), True, 1.0)
        init = self.velocity if self.cfg.constant_velocity else np.eye(4)
        ok, fitness = True, 0.0
        try:
            # source = current, target = previous: the result maps current-camera points into the previous camera
            res = o3d.t.pipelines.odometry.rgbd_odometry_multi_scale(
                cur, self.prev, self.intrinsics, o3d.core.Tensor(init),
                1.0, self.cfg.depth_max, self.criteria, self.method,
                o3d.t.pipelines.odometry.OdometryLossParams(depth_outlier_trunc=self.cfg.depth_diff_max),
            )
            T_prev_cur = res.transformation.numpy()
            fitness = float(res.fitness)
            if rigidity_error(T_prev_cur) is not None or fitness <= 0.0:
                ok = False
        except RuntimeError:
            ok = False
        if not ok:
            T_prev_cur = self.velocity
        self.T_wc = self.T_wc @ T_prev_cur
        self.velocity = T_prev_cur
        self.prev = cur
        return TrackResult(self.T_wc.copy(), ok, fitness)
