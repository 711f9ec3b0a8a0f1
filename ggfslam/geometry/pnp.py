"""Camera pose from 3D-2D correspondences: OpenCV's RANSAC PnP, returned in the project's pose convention."""
from __future__ import annotations

import cv2
import numpy as np

from ggfslam.geometry.se3 import invert, make_pose


def pnp_ransac(points: np.ndarray, uv: np.ndarray, K: np.ndarray, iterations: int, reprojection_px: float,
               confidence: float = 0.999) -> tuple[np.ndarray, np.ndarray] | None:
    """Pose T_wc [4, 4] of the camera in the frame of ``points`` [N, 3] seeing them at pixels ``uv`` [N, 2]
    (undistorted, intrinsics ``K`` [3, 3]) and the RANSAC inlier indices [I]; None if RANSAC fails (EPnP)."""
    ok, rvec, tvec, inl = cv2.solvePnPRansac(np.ascontiguousarray(points, np.float64),
                                             np.ascontiguousarray(uv, np.float64), K, None,
                                             iterationsCount=int(iterations), reprojectionError=float(reprojection_px),
                                             confidence=float(confidence), flags=cv2.SOLVEPNP_EPNP)
    if not ok or inl is None:
        return None
    return invert(make_pose(cv2.Rodrigues(rvec)[0], tvec.reshape(3))), inl.reshape(-1)
