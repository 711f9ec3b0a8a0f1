"""Dominant planes of a depth image (floor, walls, box faces), for plane landmarks in the factor graph.

Low-texture indoor scenes give few reliable ORB tracks, but their large planes are measured by every depth pixel
on them. Each keyframe's planes enter bundle adjustment as GTSAM ``OrientedPlane3Factor`` observations of plane
landmarks shared by all keyframes that see the same surface, which holds roll, pitch and the distances to
walls and floor where point tracks are short.

Convention (GTSAM's ``OrientedPlane3``): coefficients ``(n, d)`` with unit normal n and the plane
``n . x + d = 0`` in the camera frame; we orient n towards the camera, so d > 0 is the camera's distance.
Detection is a seeded RANSAC (repeatable runs) on a subsampled back-projection, refined by least squares.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ggfslam.data.types import Camera


@dataclass
class PlaneDetectionConfig:
    """Settings of plane detection in a depth image."""

    stride: int = 4
    """Use every stride-th pixel in x and y."""
    max_planes: int = 5
    """At most this many planes per frame, largest first."""
    min_fraction: float = 0.04
    """A plane must hold at least this fraction of the valid sampled pixels ..."""
    min_points: int = 400
    """... and at least this many sampled pixels."""
    distance_abs: float = 0.01
    """RANSAC inlier distance (m) at 1 m ..."""
    distance_rel: float = 0.004
    """... growing by this much per metre of depth squared (structured-light noise grows with z^2)."""
    iterations: int = 150
    """RANSAC hypotheses per plane."""
    score_points: int = 2000
    """Hypotheses are scored on a random subset of this many points (the winner is refit on all of them)."""
    depth_min: float = 0.2
    """Closest depth used (m)."""
    depth_max: float = 4.0
    """Farthest depth used (m): far depth is too noisy to fit planes on."""
    seed: int = 0
    """RANSAC random seed (detection is repeatable)."""


@dataclass
class Plane:
    """A plane seen in one frame (camera coordinates)."""

    coefficients: np.ndarray  # [4] (nx, ny, nz, d), |n| = 1, d > 0
    n_points: int  # inlier pixels (sampled)
    rms: float  # RMS point-to-plane distance of the inliers (m)


def _fit(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane of points [K, 3]: (unit normal [3], d)."""
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[2]
    return n, -float(n @ c)


def detect_planes(depth: np.ndarray, camera: Camera, cfg: PlaneDetectionConfig | None = None) -> list[Plane]:
    """Dominant planes of a depth image [H, W] (metres, 0 = none) in the camera frame, largest first."""
    cfg = cfg or PlaneDetectionConfig()
    s = cfg.stride
    z = depth[::s, ::s].astype(np.float64)  # [h, w]
    v, u = np.mgrid[0:depth.shape[0]:s, 0:depth.shape[1]:s]
    ok = np.isfinite(z) & (z > cfg.depth_min) & (z < cfg.depth_max)
    z, u, v = z[ok], u[ok], v[ok]
    pts = np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], axis=1)  # [P, 3]
    tol = cfg.distance_abs + cfg.distance_rel * z ** 2  # [P]
    need = max(cfg.min_points, int(cfg.min_fraction * len(pts)))
    rng = np.random.default_rng(cfg.seed)
    planes: list[Plane] = []
    remaining = np.arange(len(pts))
    while len(planes) < cfg.max_planes and len(remaining) >= need:
        P, T = pts[remaining], tol[remaining]
        tri = rng.integers(0, len(P), size=(cfg.iterations, 3))  # [I, 3]
        a, b, c = P[tri[:, 0]], P[tri[:, 1]], P[tri[:, 2]]
        n = np.cross(b - a, c - a)  # [I, 3]
        norm = np.linalg.norm(n, axis=1)
        good = norm > 1e-9
        if not good.any():
            break
        n, a = n[good] / norm[good, None], a[good]
        d = -np.einsum("ij,ij->i", n, a)  # [I]
        sub = rng.choice(len(P), size=min(len(P), cfg.score_points), replace=False)  # [S]
        counts = (np.abs(P[sub] @ n.T + d) < T[sub, None]).sum(axis=0)  # [I] inliers among the subset
        best = int(np.argmax(counts))
        inl = np.abs(P @ n[best] + d[best]) < T
        if inl.sum() < need:
            break
        for _ in range(2):  # least-squares refit, then re-select inliers
            nn, dd = _fit(P[inl])
            inl = np.abs(P @ nn + dd) < T
        if inl.sum() < need:
            break
        nn, dd = _fit(P[inl])
        if dd < 0:  # orient towards the camera
            nn, dd = -nn, -dd
        rms = float(np.sqrt(np.mean((P[inl] @ nn + dd) ** 2)))
        planes.append(Plane(np.r_[nn, dd], int(inl.sum()), rms))
        remaining = remaining[~inl]
    return planes
