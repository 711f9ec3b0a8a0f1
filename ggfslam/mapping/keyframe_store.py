"""Keyframe images at training resolution: on disk, with a bounded in-memory cache.

A long sequence keeps thousands of keyframes; holding their images in memory is what makes peer systems
grow until they crash. Each keyframe is written once as ``<dir>/kf_<id>.npz`` (uint8 colour, float32
depth in metres) and read back through an LRU cache of ``cache_size`` entries. Coarse levels (level 1 = half
the training size, for coarse-to-fine training) are made from level 0 on first use and cached beside it.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ggfslam.atomic import atomic_path
from ggfslam.data.types import Camera
from ggfslam.geometry.depth import normals_from_depth, resize_depth_image
from ggfslam.render.types import Intrinsics


def scaled_intrinsics(camera: Camera, width: int | None) -> Intrinsics:
    """Intrinsics of the camera's images resized to ``width`` (aspect kept, never upscaled; None = as they are)."""
    if width is None or width >= camera.width:
        return Intrinsics.of(camera)
    return Intrinsics.of(camera.resized(width, max(1, int(round(camera.height * width / camera.width)))))


def resize_depth(depth: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Depth [H, W] at intr's size (centred; no mixing across edges: ``resize_depth_image``)."""
    return resize_depth_image(depth, intr.width, intr.height)


def resize_rgbd(rgb: np.ndarray, depth: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Colour [H, W, 3] (area average) and depth [H, W] (``resize_depth``) at intr's size."""
    if rgb.shape[1] == intr.width and rgb.shape[0] == intr.height:
        return rgb.astype(np.float32, copy=False), depth.astype(np.float32, copy=False)
    return (cv2.resize(rgb.astype(np.float32, copy=False), (intr.width, intr.height), interpolation=cv2.INTER_AREA),
            resize_depth(depth, intr))


@dataclass
class KeyframeImages:
    """One keyframe's training targets."""

    rgb: np.ndarray  # [h, w, 3] float32 in [0, 1]
    depth: np.ndarray  # [h, w] float32 metres, 0 = invalid
    normals: np.ndarray  # [h, w, 3] float32 camera-frame normals of the depth (0 = undefined)
    frame_index: int
    levels: dict = field(default_factory=dict, repr=False)  # level -> KeyframeImages at half, quarter, ... size


class KeyframeStore:
    """Keyframe images by id, on disk under ``directory`` with an LRU cache of ``cache_size`` entries."""

    def __init__(self, directory: str | Path, intr: Intrinsics, cache_size: int = 32):
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.intr = intr
        self.cache_size = cache_size
        self._cache: OrderedDict[int, KeyframeImages] = OrderedDict()
        self._frames: dict[int, int] = {}  # kf id -> frame index
        self._lock = threading.Lock()
        for f in sorted(self.dir.glob("kf_*.npz")):  # a resumed run finds its keyframes again
            with np.load(f) as z:
                self._frames[int(f.stem[3:])] = int(z["frame_index"])

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._frames

    def __len__(self) -> int:
        return len(self._frames)

    def ids(self) -> list[int]:
        """Stored keyframe ids, ascending."""
        with self._lock:
            return sorted(self._frames)

    def frame_index(self, kf_id: int) -> int:
        """Sequence index of the frame a keyframe was made from."""
        return self._frames[kf_id]

    def path(self, kf_id: int) -> Path:
        """The file of keyframe kf_id's images."""
        return self.dir / f"kf_{kf_id:06d}.npz"

    def add(self, kf_id: int, frame_index: int, rgb: np.ndarray, depth: np.ndarray) -> KeyframeImages:
        """Store a keyframe's full-resolution colour [H, W, 3] and depth [H, W] at training resolution."""
        rgb_s, depth_s = resize_rgbd(rgb, depth, self.intr)
        rgb8 = np.clip(np.rint(rgb_s * 255), 0, 255).astype(np.uint8)
        with atomic_path(self.path(kf_id)) as tmp:
            np.savez(tmp, rgb=rgb8, depth=depth_s, frame_index=frame_index)
        item = self._make(rgb8, depth_s, frame_index)
        with self._lock:
            self._frames[kf_id] = frame_index
            self._put(kf_id, item)
        return item

    def _make(self, rgb8: np.ndarray, depth: np.ndarray, frame_index: int) -> KeyframeImages:
        return self._images(rgb8.astype(np.float32) / 255.0, depth, frame_index, self.intr)

    @staticmethod
    def _images(rgb: np.ndarray, depth: np.ndarray, frame_index: int, i: Intrinsics) -> KeyframeImages:
        n = normals_from_depth(depth.astype(np.float64), i.fx, i.fy, i.cx, i.cy).astype(np.float32)
        return KeyframeImages(rgb, depth, n, frame_index)

    def level_intrinsics(self, level: int) -> Intrinsics:
        """Intrinsics of level ``level`` (0 = the training size, each level half the one before)."""
        intr = self.intr
        for _ in range(level):
            intr = intr.half()
        return intr

    def _put(self, kf_id: int, item: KeyframeImages) -> None:
        self._cache[kf_id] = item
        self._cache.move_to_end(kf_id)
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)

    def get(self, kf_id: int, level: int = 0) -> KeyframeImages:
        """A keyframe's training images (from the cache or disk), at ``level`` (0 = training size)."""
        with self._lock:
            item = self._cache.get(kf_id)
            if item is not None:
                self._cache.move_to_end(kf_id)
        if item is None:
            with np.load(self.path(kf_id)) as z:
                item = self._make(z["rgb"], z["depth"], int(z["frame_index"]))
            with self._lock:
                self._put(kf_id, item)
        for lv in range(1, level + 1):
            if lv not in item.levels:
                prev = item.levels[lv - 1] if lv > 1 else item
                i = self.level_intrinsics(lv)
                rgb, depth = resize_rgbd(prev.rgb, prev.depth, i)
                item.levels[lv] = self._images(rgb, depth, item.frame_index, i)
        return item.levels[level] if level else item

    def retain(self, kf_ids) -> list[int]:
        """Delete the stored keyframes not in ``kf_ids`` (a resumed run re-creates those after its checkpoint);
        returns the removed ids."""
        keep = set(int(k) for k in kf_ids)
        with self._lock:
            gone = [k for k in self._frames if k not in keep]
            for k in gone:
                self.path(k).unlink(missing_ok=True)
                del self._frames[k]
                self._cache.pop(k, None)
        return gone

    @property
    def cached(self) -> int:
        """How many keyframes are held in memory now."""
        return len(self._cache)
