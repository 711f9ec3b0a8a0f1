"""Fitting a depth camera's registration to the colour camera from the sequence itself (no calibration target).

Raw streams of two-camera sensors (Kinect v1, Xtion; 7-Scenes) come with the depth camera's intrinsics only.
Surfaces end at the same places in both images, so the registration that puts depth discontinuities onto
colour edges is the one ``dataset.depth_registration`` needs. With the depth camera's intrinsics held
(published or nominal: only the ratio of the two focal lengths and the baseline are observable this way), this
fits the colour camera's focal length (fx = fy), principal point and the depth camera's position along x and y
in the colour camera's frame, by minimising the median-like truncated distance from the near side of each depth
discontinuity, projected into the colour image, to the nearest colour edge (OpenCV Canny + distance transform).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import minimize

from ggfslam.data.base import RGBDDataset
from ggfslam.errors import DatasetError
from ggfslam.geometry.depth import backproject

CAP_PX = 8.0  # distances are truncated here: edges with no counterpart do not pull the fit


@dataclass
class EdgeFrame:
    """What the fit reads of one frame."""

    edge_distance: np.ndarray  # [H, W] float32 distance (px) to the nearest colour edge
    points: np.ndarray  # [N, 3] depth-camera points at the near side of depth discontinuities (metres)


@dataclass
class RegistrationFit:
    """A fitted registration: the colour camera's intrinsics and the depth camera's position in its frame."""

    fx: float
    fy: float
    cx: float
    cy: float
    translation: tuple[float, float, float]  # depth camera centre in colour-camera coordinates (m)
    distance_before_px: float  # mean truncated edge distance with the identity registration
    distance_after_px: float  # the same after the fit
    frames: int
    edge_points: int

    def as_config(self, depth_intrinsics: tuple[float, float, float, float], width: int, height: int,
                  depth_scale: float) -> dict:
        """The ``dataset.camera`` and ``dataset.depth_registration`` sections that apply this fit."""
        return {"camera": {"fx": round(self.fx, 2), "fy": round(self.fy, 2), "cx": round(self.cx, 2),
                           "cy": round(self.cy, 2), "width": width, "height": height, "depth_scale": depth_scale},
                "depth_registration": {"fx": depth_intrinsics[0], "fy": depth_intrinsics[1],
                                       "cx": depth_intrinsics[2], "cy": depth_intrinsics[3],
                                       "translation": [round(t, 4) for t in self.translation]}}


def colour_edge_distance(rgb: np.ndarray) -> np.ndarray:
    """Distance (px) [H, W] from each pixel to the nearest Canny edge of a colour image [H, W, 3] in [0, 1]."""
    gray = cv2.cvtColor(np.clip(rgb * 255, 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
    edges = cv2.Canny(cv2.GaussianBlur(gray, (5, 5), 1.5), 40, 100) > 0
    return cv2.distanceTransform((~edges).astype(np.uint8), cv2.DIST_L2, 5)


def near_discontinuities(depth: np.ndarray, rel: float = 0.05, min_jump: float = 0.03) -> np.ndarray:
    """Mask [H, W] of pixels on the near side of a depth jump to a 4-neighbour (both valid; the jump larger than
    ``rel`` of the nearer depth and than ``min_jump`` metres)."""
    near = np.zeros(depth.shape, bool)
    for first, second in ((np.s_[:-1], np.s_[1:]), (np.s_[:, :-1], np.s_[:, 1:])):  # vertical, horizontal pairs
        a, b = depth[first], depth[second]
        jump = (a > 0) & (b > 0) & (np.abs(a - b) > np.maximum(rel * np.minimum(a, b), min_jump))
        near[first] |= jump & (a < b)
        near[second] |= jump & (b < a)
    return near


def edge_frame(rgb: np.ndarray, depth: np.ndarray, depth_intrinsics: tuple[float, float, float, float]) -> EdgeFrame:
    """The colour edge distances and the back-projected depth discontinuities of one frame."""
    pts = backproject(depth, *depth_intrinsics)[near_discontinuities(depth)]  # [N, 3]
    return EdgeFrame(colour_edge_distance(rgb), pts)


def edge_distance(frames: list[EdgeFrame], fx: float, fy: float, cx: float, cy: float,
                  t: tuple[float, float, float]) -> float:
    """Mean truncated distance (px) of the discontinuities, moved by ``t`` and projected with (fx, fy, cx, cy),
    to the nearest colour edge (points falling outside the image count as ``CAP_PX``)."""
    total, n = 0.0, 0
    for f in frames:
        h, w = f.edge_distance.shape
        p = f.points + np.asarray(t)
        u = np.rint(fx * p[:, 0] / p[:, 2] + cx).astype(np.int64)
        v = np.rint(fy * p[:, 1] / p[:, 2] + cy).astype(np.int64)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        total += np.minimum(f.edge_distance[v[inside], u[inside]], CAP_PX).sum() + CAP_PX * (~inside).sum()
        n += len(p)
    return total / max(n, 1)


def fit_depth_registration(dataset: RGBDDataset, depth_intrinsics: tuple[float, float, float, float] | None = None,
                           n_frames: int = 20, baseline_guess: float = -0.025) -> RegistrationFit:
    """Fit the colour camera (fx = fy, cx, cy) and the depth camera's x/y offset on ``n_frames`` frames spread
    over an unregistered dataset whose intrinsics (or ``depth_intrinsics``) are the depth camera's.
    ``baseline_guess`` (m) starts the offset: the baseline and the principal point trade off on scenes of a
    narrow depth range, so start it at the sensor's known baseline (Kinect v1: 2.5 cm, colour camera on the
    depth camera's -x side in OpenCV axes)."""
    cam = dataset.camera
    kd = depth_intrinsics or (cam.fx, cam.fy, cam.cx, cam.cy)
    picks = np.unique(np.linspace(0, len(dataset) - 1, min(n_frames, len(dataset))).round().astype(int))
    frames = []
    for i in picks:
        f = dataset[int(i)]
        frames.append(edge_frame(f.rgb, f.depth, kd))
    n_pts = sum(len(f.points) for f in frames)
    if n_pts < 500:
        raise DatasetError(dataset.root, f"only {n_pts} depth discontinuities in {len(frames)} frames; the fit needs "
                                         "scenes with depth edges (objects in front of walls)")
    before = edge_distance(frames, kd[0], kd[1], kd[2], kd[3], (0.0, 0.0, 0.0))

    def cost(x):
        f, cx, cy, tx, ty = x
        return edge_distance(frames, f, f, cx, cy, (tx, ty, 0.0))

    best = None
    for scale in (0.85, 0.9, 0.95, 1.0):  # Nelder-Mead is local: start from a few focal length ratios
        r = minimize(cost, [scale * kd[0], kd[2], kd[3], baseline_guess, 0.0], method="Nelder-Mead",
                     options={"xatol": 1e-3, "fatol": 1e-4, "maxiter": 800})
        if best is None or r.fun < best.fun:
            best = r
    f, cx, cy, tx, ty = (float(x) for x in best.x)
    return RegistrationFit(f, f, cx, cy, (tx, ty, 0.0), before, float(best.fun), len(frames), n_pts)
