"""Depth back-projection and normals from depth (OpenCV camera axes, metres, 0 = invalid)."""
from __future__ import annotations

import numpy as np


def resize_depth_image(depth: np.ndarray, width: int, height: int, max_spread: float = 0.05) -> np.ndarray:
    """Depth [H, W] resized to [height, width] without shifting it and without inventing surfaces.

    Pixel centres stay where ``Camera.resized`` puts them: for an integer factor k each output pixel is the mean
    of its k x k block when the block is all valid and flat (spread <= ``max_spread`` of its depth); at edges and
    holes it takes the block pixel nearest the centre, so no depth is averaged across a discontinuity. Other
    factors use OpenCV's centre-exact nearest. (Plain ``INTER_NEAREST`` takes the block's first pixel: a shift
    of (k - 1) / 2 input pixels, a systematic rotation between depth and colour / intrinsics.)
    """
    import cv2

    depth = np.asarray(depth, dtype=np.float32)
    H, W = depth.shape
    if (W, H) == (width, height):
        return depth
    nearest = cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST_EXACT)
    k = W // width
    if k < 2 or W != k * width or H != k * height:
        return nearest
    blocks = depth.reshape(height, k, width, k).transpose(0, 2, 1, 3).reshape(height, width, k * k)
    lo, hi = blocks.min(-1), blocks.max(-1)
    mean = blocks.mean(-1, dtype=np.float64).astype(np.float32)
    flat = (lo > 0) & (hi - lo <= max_spread * mean)
    return np.where(flat, mean, nearest)


def pixel_grid(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates u [H, W] and v [H, W] (integer pixel = centre, OpenCV convention)."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return u, v


def backproject(depth: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Camera-frame points [H, W, 3] from a depth map [H, W]; invalid pixels give (0, 0, 0)."""
    h, w = depth.shape
    u, v = pixel_grid(w, h)
    z = depth.astype(np.float64)
    return np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=-1)


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points [..., 3]."""
    return pts @ T[:3, :3].T + T[:3, 3]


def project(pts_cam: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates uv [..., 2] and depth z [...] of camera-frame points [..., 3]."""
    z = pts_cam[..., 2]
    safe = np.where(np.abs(z) > 1e-12, z, 1e-12)
    uv = np.stack([fx * pts_cam[..., 0] / safe + cx, fy * pts_cam[..., 1] / safe + cy], axis=-1)
    return uv, z


def normals_from_depth(depth: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Camera-frame unit normals [H, W, 3] from a depth map by central differences of back-projected points.

    Normals face the camera (n . p < 0); pixels whose neighbours lack depth get (0, 0, 0).
    """
    P = backproject(depth, fx, fy, cx, cy)  # [H, W, 3]
    valid = depth > 0
    n = np.zeros_like(P)
    dx = P[1:-1, 2:] - P[1:-1, :-2]  # [H-2, W-2, 3]
    dy = P[2:, 1:-1] - P[:-2, 1:-1]
    c = np.cross(dx, dy)
    norm = np.linalg.norm(c, axis=-1, keepdims=True)
    ok = (
        valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1] & valid[1:-1, 1:-1]
        & (norm[..., 0] > 0)
    )
    c = np.where(ok[..., None], c / np.maximum(norm, 1e-20), 0.0)
    flip = np.sum(c * P[1:-1, 1:-1], axis=-1) > 0
    c[flip] *= -1
    n[1:-1, 1:-1] = c
    return n
