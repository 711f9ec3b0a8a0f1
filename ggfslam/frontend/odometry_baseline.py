"""Baseline tracker: Open3D RGB-D odometry from each frame to the previous one.

It is a yardstick, not the system's frontend: it drifts, and has no map, keyframes or loop closure.
"""
from __future__ import annotations

import numpy as np

from ggfslam.config import TrackingConfig
from ggfslam.data.types import Camera, Frame
from ggfslam.frontend.dense_odometry import DenseOdometry
from ggfslam.frontend.types import TrackingState, TrackResult


class OdometryBaselineTracker:
    """Frame-to-frame Open3D RGB-D odometry with an optional constant-velocity initial guess."""

    name = "o3d_odometry"

    def __init__(self, camera: Camera, cfg: TrackingConfig):
        self.cfg = cfg
        self.odometry = DenseOdometry(camera, cfg)
        self.prev = None
        self.T_wc = np.eye(4)
        self.velocity = np.eye(4)  # T_prev_cur of the last step
        self.stamps: list[float] = []
        self.poses: list[np.ndarray] = []
        self.lost: list[bool] = []

    def track(self, frame: Frame) -> TrackResult:
        """Estimate the camera-to-world pose of the next frame (the first frame defines the world)."""
        cur = self.odometry.rgbd(frame)
        if self.prev is None:
            self.prev = cur
            return self._record(frame, TrackResult(self.T_wc.copy(), True, 1.0))
        init = self.velocity if self.cfg.constant_velocity else np.eye(4)
        ok, T_prev_cur, fitness = self.odometry.relative(cur, self.prev, init)
        if not ok:
            T_prev_cur = self.velocity
        self.T_wc = self.T_wc @ T_prev_cur
        self.velocity = T_prev_cur
        self.prev = cur
        state = TrackingState.OK if ok else TrackingState.LOST
        return self._record(frame, TrackResult(self.T_wc.copy(), ok, fitness, state))

    def _record(self, frame: Frame, res: TrackResult) -> TrackResult:
        self.stamps.append(frame.timestamp)
        self.poses.append(res.T_wc)
        self.lost.append(not res.ok)
        return res

    def promote_last_frame(self) -> None:
        """The baseline has no keyframes."""
        return None

    def finish(self) -> None:
        """Nothing runs in the background."""

    def trajectory(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Timestamps [N], camera-to-world poses [N, 4, 4] and lost flags [N] of every frame."""
        return np.array(self.stamps), np.stack(self.poses), np.array(self.lost)

    def keyframe_trajectory(self) -> None:
        """The baseline has no keyframes."""
        return None

    def summary(self) -> dict:
        """No backend figures."""
        return {}
