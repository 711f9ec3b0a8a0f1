"""ORB features spread evenly over the image, with depth and camera-frame points for RGB-D frames."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ggfslam.config import TrackingConfig
from ggfslam.data.types import Camera


@dataclass
class Features:
    """Keypoints of one frame; row i of every array describes keypoint i."""

    uv: np.ndarray  # [N, 2] float64 pixel coordinates (level-0)
    octave: np.ndarray  # [N] int pyramid level
    descriptors: np.ndarray  # [N, 32] uint8 ORB
    depth: np.ndarray  # [N] float64 metres, 0 where the sensor has no (usable) depth
    points_cam: np.ndarray  # [N, 3] camera-frame points, NaN where depth is 0

    def __len__(self) -> int:
        return len(self.uv)

    @property
    def has_depth(self) -> np.ndarray:
        """[N] bool: keypoints with a usable depth."""
        return self.depth > 0


class OrbExtractor:
    """OpenCV ORB, then bucketing over a grid so keypoints cover the whole image rather than its busiest corner."""

    def __init__(self, camera: Camera, cfg: TrackingConfig, seed: int = 0):
        self.camera, self.cfg, self.seed = camera, cfg, seed
        # ask for more corners than kept, so sparse cells still get their share after bucketing
        self.orb = cv2.ORB_create(nfeatures=2 * cfg.n_features, scaleFactor=cfg.scale_factor, nlevels=cfg.n_levels,
                                  fastThreshold=cfg.fast_threshold, edgeThreshold=19, patchSize=31)
        self.orb_low = cv2.ORB_create(nfeatures=2 * cfg.n_features, scaleFactor=cfg.scale_factor,
                                      nlevels=cfg.n_levels, fastThreshold=max(cfg.fast_threshold // 3, 5),
                                      edgeThreshold=19, patchSize=31)
        self.level_scale = cfg.scale_factor ** np.arange(cfg.n_levels)  # [L]

    def __getstate__(self) -> dict:  # cv2.ORB does not pickle: rebuilt from the settings (checkpoints)
        return {"camera": self.camera, "cfg": self.cfg, "seed": self.seed}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["camera"], state["cfg"], state.get("seed", 0))

    def _bucket(self, kps: list) -> list:
        if len(kps) <= self.cfg.n_features:
            return kps
        cols, rows = self.cfg.grid_cells
        pts = np.array(cv2.KeyPoint_convert(kps))  # [M, 2]
        resp = np.fromiter((k.response for k in kps), dtype=np.float64, count=len(kps))  # [M]
        cx = np.minimum((pts[:, 0] / self.camera.width * cols).astype(int), cols - 1)
        cy = np.minimum((pts[:, 1] / self.camera.height * rows).astype(int), rows - 1)
        cell = cy * cols + cx  # [M]
        # rank within each cell by response; then take rank 0 of every cell, rank 1, ... until full
        order = np.lexsort((-resp, cell))
        sorted_cells = cell[order]
        first = np.searchsorted(sorted_cells, sorted_cells, side="left")
        rank = np.empty(len(kps), dtype=np.int64)
        rank[order] = np.arange(len(kps)) - first
        keep = np.lexsort((-resp, rank))[: self.cfg.n_features]
        return [kps[i] for i in np.sort(keep)]

    def extract(self, rgb: np.ndarray, depth: np.ndarray, frame_index: int = 0) -> Features:
        """ORB keypoints, descriptors and depth of a frame (rgb [H, W, 3] in [0, 1], depth [H, W] metres);
        ``frame_index`` draws the frame's keypoint jitter (``keypoint_jitter_px``), the same on every run."""
        gray = cv2.cvtColor((np.clip(rgb, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
        kps = self.orb.detect(gray, None)
        if len(kps) < self.cfg.n_features // 2:  # low-texture view: lower the FAST threshold, like ORB-SLAM
            kps = self.orb_low.detect(gray, None)
        kps = self._bucket(list(kps))
        kps, desc = self.orb.compute(gray, kps)
        if desc is None or len(kps) == 0:
            return empty_features()
        uv = np.asarray(cv2.KeyPoint_convert(kps), dtype=np.float64)  # [N, 2]
        octave = np.fromiter((k.octave for k in kps), dtype=np.int64, count=len(kps))  # [N]
        ui = np.clip(np.round(uv[:, 0]).astype(int), 0, depth.shape[1] - 1)
        vi = np.clip(np.round(uv[:, 1]).astype(int), 0, depth.shape[0] - 1)
        z = depth[vi, ui].astype(np.float64)  # [N]
        z[(z < self.cfg.depth_min) | (z > self.cfg.depth_max) | ~np.isfinite(z)] = 0.0
        if self.cfg.keypoint_jitter_px > 0:  # after the depth lookup: the jitter moves no keypoint to another pixel
            rng = np.random.default_rng([self.seed, frame_index])
            uv = uv + rng.normal(0.0, self.cfg.keypoint_jitter_px, uv.shape)  # [N, 2]
        return Features(uv, octave, desc, z, backproject_points(uv, z, self.camera))


def backproject_points(uv: np.ndarray, z: np.ndarray, camera: Camera) -> np.ndarray:
    """Camera-frame points [N, 3] of pixels uv [N, 2] at depth z [N]; NaN rows where z == 0."""
    pts = np.stack([(uv[:, 0] - camera.cx) / camera.fx * z, (uv[:, 1] - camera.cy) / camera.fy * z, z], axis=1)
    pts[z <= 0] = np.nan
    return pts


def empty_features() -> Features:
    """A frame with no keypoints (blank or black image)."""
    return Features(np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros((0, 32), np.uint8), np.zeros(0),
                    np.zeros((0, 3)))
