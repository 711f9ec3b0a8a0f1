"""Removing lens distortion from RGB-D frames, so every later stage sees ideal pinhole images.

Raw Kinect sequences carry their colour camera's distortion: TUM fr1 and fr2 (OpenCV k1 k2 p1 p2 k3 published
with the dataset), a RealSense colour stream (Brown-Conrady). Features, bundle adjustment, the rasterizer and the
metrics all use the pinhole model, so a frame is undistorted once, when it is read. Ignoring it misplaces TUM fr1's
pixels by a median 4.8 px (90th percentile 9.6 px, 37 px in the corners).

The output camera keeps the image size and takes OpenCV's optimal new camera matrix with ``alpha = 0``: every
output pixel has a source pixel (no black border a map would learn), at the price of a slightly narrower view
(TUM fr1: focal length 517 -> 547 px). Colour is sampled bilinearly. Depth registered pixel for pixel to the raw
colour image (TUM: the Kinect driver's registration) goes through the same map (depth is the distance along the
optical axis, which undistortion does not change): bilinearly where the four raw pixels around the sample hold
one surface (all valid, spread under ``DEPTH_SURFACE_SPREAD`` of their depth), so tilted surfaces stay smooth, and
from the nearest raw pixel elsewhere, so depth edges stay sharp and holes stay holes (no depth is invented between
a foreground and a background). Nearest sampling everywhere moved a tilted floor by up to half a pixel's depth step.
"""
from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from ggfslam.data.types import DISTORTION_LENGTHS, Camera

DEPTH_SURFACE_SPREAD = 0.05  # four raw depths within 5% of each other are one surface (interpolated)


class Undistortion:
    """The undistortion maps of one distorted camera and the pinhole camera its output is (see module docstring)."""

    def __init__(self, camera: Camera):
        if not camera.distortion:
            raise ValueError("camera has no distortion to remove")
        if len(camera.distortion) not in DISTORTION_LENGTHS:
            raise ValueError(f"distortion must have {', '.join(map(str, DISTORTION_LENGTHS[1:]))} OpenCV coefficients, "
                             f"got {len(camera.distortion)}")
        size = (camera.width, camera.height)
        dist = np.asarray(camera.distortion, np.float64)
        K_new, _ = cv2.getOptimalNewCameraMatrix(camera.K, dist, size, 0.0, size)
        self.camera = replace(camera, fx=float(K_new[0, 0]), fy=float(K_new[1, 1]), cx=float(K_new[0, 2]),
                              cy=float(K_new[1, 2]), distortion=())
        # float maps: the sampling below rounds and weighs them exactly (fixed-point maps would quantize them)
        self._map_x, self._map_y = cv2.initUndistortRectifyMap(camera.K, dist, None, K_new, size,
                                                               cv2.CV_32FC1)  # [H, W] raw pixel of each output pixel
        self._depth = SurfaceDepthSampler(self._map_x, self._map_y, camera.width, camera.height)

    def rgb(self, rgb: np.ndarray) -> np.ndarray:
        """Undistorted colour [H, W, 3] of raw colour [H, W, 3] (bilinear)."""
        return cv2.remap(rgb, self._map_x, self._map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """Undistorted depth [H, W] of raw depth [H, W] registered to the raw colour image (see module docstring)."""
        return self._depth(depth)


class SurfaceDepthSampler:
    """Samples a depth image at fixed subpixel positions: bilinearly where the four pixels around a position hold
    one surface (all valid, spread under ``DEPTH_SURFACE_SPREAD`` of their depth), else from the nearest pixel;
    0 at positions outside the image. OpenCV remaps (~4 ms at 640x480; bilinear weights in 1/32 px steps)."""

    def __init__(self, map_x: np.ndarray, map_y: np.ndarray, width: int, height: int):
        """map_x, map_y [H', W'] float32: the source pixel (x right, y down) of each output pixel, in a width x height
        image."""
        self._map_x, self._map_y = np.asarray(map_x, np.float32), np.asarray(map_y, np.float32)
        # nearest sampling rounds, so half a pixel less picks the top-left pixel of each position's 2x2 block
        self._block_x, self._block_y = self._map_x - 0.5, self._map_y - 0.5
        self._inside = ((self._map_x >= -0.5) & (self._map_x <= width - 0.5) & (self._map_y >= -0.5)
                        & (self._map_y <= height - 0.5))  # [H', W']
        self._size = (height, width)

    def __call__(self, depth: np.ndarray) -> np.ndarray:
        """Depth [H', W'] float32 sampled from depth [H, W] (metres, 0 = invalid)."""
        if depth.shape != self._size:
            raise ValueError(f"depth image is {depth.shape[1]}x{depth.shape[0]}, expected {self._size[1]}x{self._size[0]}")
        depth = np.ascontiguousarray(depth, np.float32)
        block = np.ones((2, 2), np.uint8)  # anchored top-left: pixel (y, x) holds the min / max of its 2x2 block
        lo = cv2.remap(cv2.erode(depth, block, anchor=(0, 0), borderType=cv2.BORDER_REPLICATE), self._block_x,
                       self._block_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
        hi = cv2.remap(cv2.dilate(depth, block, anchor=(0, 0), borderType=cv2.BORDER_REPLICATE), self._block_x,
                       self._block_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
        smooth = cv2.remap(depth, self._map_x, self._map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        nearest = cv2.remap(depth, self._map_x, self._map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
        surface = (lo > 0) & (hi - lo <= DEPTH_SURFACE_SPREAD * lo)
        return np.where(self._inside, np.where(surface, smooth, nearest), np.float32(0.0)).astype(np.float32)


def undistortion_of(camera: Camera) -> Undistortion | None:
    """The camera's undistortion, or None when its images are already pinhole."""
    return Undistortion(camera) if camera.distortion else None
