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

# Open3D's legacy odometry: its tensor twin is faster but not repeatable run to run (threaded reductions),
# and the deterministic mode needs the same trajectory every time.
_JACOBIANS = {
    "hybrid": o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm,
    "color": o3d.pipelines.odometry.RGBDOdometryJacobianFromColorTerm,
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
        c = self.camera
        self.intrinsics = o3d.camera.PinholeCameraIntrinsic(c.width, c.height, c.fx, c.fy, c.cx, c.cy)
        self.option = o3d.pipelines.odometry.OdometryOption(
            iteration_number_per_pyramid_level=o3d.utility.IntVector([int(n) for n in cfg.iterations]),
            depth_diff_max=cfg.depth_diff_max, depth_min=0.1, depth_max=cfg.depth_max)
        self.jacobian = _JACOBIANS[cfg.odometry_term]()
        self.prev: o3d.geometry.RGBDImage | None = None
        self.T_wc = np.eye(4)
        self.velocity = np.eye(4)  # T_prev_cur of the last step

    def _rgbd(self, frame: Frame) -> o3d.geometry.RGBDImage:
        rgb, depth = frame.rgb, frame.depth
        if (frame.width, frame.height) != self.size:
            rgb = cv2.resize(rgb, self.size, interpolation=cv2.INTER_AREA)
            depth = cv2.resize(depth, self.size, interpolation=cv2.INTER_NEAREST)
        # the legacy RGBDImage converts 8-bit colour to intensity correctly; float colour it misreads
        color = o3d.geometry.Image(np.ascontiguousarray(np.round(rgb * 255.0), dtype=np.uint8))
        dimg = o3d.geometry.Image(np.ascontiguousarray(depth, dtype=np.float32))
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            color, dimg, depth_scale=1.0, depth_trunc=self.cfg.depth_max, convert_rgb_to_intensity=True)

    def track(self, frame: Frame) -> TrackResult:
        """Estimate the camera-to-world pose of the next frame (the first frame defines the world)."""
        cur = self._rgbd(frame)
        if self.prev is None:
            self.prev = cur
            return TrackResult(self.T_wc.copy(), True, 1.0)
        init = self.velocity if self.cfg.constant_velocity else np.eye(4)
        # source = current, target = previous: the result maps current-camera points into the previous camera
        ok, T_prev_cur, info = o3d.pipelines.odometry.compute_rgbd_odometry(
            cur, self.prev, self.intrinsics, init, self.jacobian, self.option)
        T_prev_cur = np.asarray(T_prev_cur)
        # Open3D's information matrix holds the correspondence count in its translation block
        fitness = float(np.asarray(info)[5, 5]) / (self.size[0] * self.size[1]) if ok else 0.0
        if ok and rigidity_error(T_prev_cur) is not None:
            ok = False
        if not ok:
            T_prev_cur = self.velocity
        self.T_wc = self.T_wc @ T_prev_cur
        self.velocity = T_prev_cur
        self.prev = cur
        return TrackResult(self.T_wc.copy(), ok, fitness)
