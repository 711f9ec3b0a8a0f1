"""A run's frames for the viewer's slider: the map rendered at a frame's estimated pose beside the input image.

The map and the dataset are opened on first use (seconds), not when the viewer starts. The render is the
project's own (``Mapper.render`` from checkpoint.pt, with the nearest keyframe's exposure), else the baked
gaussians.ply; the input image comes from the dataset the run's config.yaml names, else the nearest keyframe's
stored image.
"""
from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from ggfslam.errors import ConfigError, DatasetError, RunDirError

RENDER_WIDTH = 320  # slider renders, in pixels: a CPU render at this size takes a fraction of a second

_EXPECTED = (RunDirError, DatasetError, ConfigError, OSError, KeyError, ValueError, RuntimeError)


class FrameViews:
    """Renders and input images of a run's frames (rows of trajectory.txt), each as uint8 [h, w, 3] or a one-line
    reason why there is none."""

    def __init__(self, run_dir: Path, stamps: np.ndarray, poses: np.ndarray, width: int = RENDER_WIDTH):
        self.run_dir, self.stamps, self.poses, self.width = run_dir, stamps, poses, width  # [N], [N, 4, 4]
        self._lock = threading.Lock()
        self._render = None  # callable(T_wc, frame index) -> RenderOutput, or a str: why not
        self._dataset = None  # the dataset, or a str: why not
        self._frames: np.ndarray | None = None  # [N] dataset frame index of each row

    def _open_map(self):
        from ggfslam.mapping.keyframe_store import scaled_intrinsics
        from ggfslam.saved_run import load_mapper, run_camera

        intr = scaled_intrinsics(run_camera(self.run_dir), self.width)
        try:
            from ggfslam.eval.rendering import nearest_keyframes

            _, mapper, ckpt = load_mapper(self.run_dir)
            kf_frames = dict(ckpt["kf_frames"])

            def render(T, frame):
                kf = int(nearest_keyframes(np.array([frame]), kf_frames)[0])
                return mapper.render(T, intr, exposure_kf=kf if kf >= 0 else None, planar=False)
            return render
        except _EXPECTED as e:
            from ggfslam.gaussians.explicit import ExplicitGaussians
            from ggfslam.rundir import GAUSSIANS_FILE

            if not (self.run_dir / GAUSSIANS_FILE).is_file():
                return f"no map to render: {e}"
            baked = ExplicitGaussians.from_ply(self.run_dir / GAUSSIANS_FILE)
            return lambda T, frame: baked.render(T, intr)

    def _open_dataset(self):
        from ggfslam.config import load_config
        from ggfslam.data.sources import open_dataset_from_config
        from ggfslam.rundir import CONFIG_FILE
        from ggfslam.slam import frames_of_stamps

        try:
            ds = open_dataset_from_config(load_config(self.run_dir / CONFIG_FILE).dataset)
            self._frames = frames_of_stamps(np.asarray(ds.timestamps), self.stamps, self.run_dir)
            return ds
        except _EXPECTED as e:
            self._frames = np.arange(len(self.stamps))
            return f"the sequence cannot be read ({e})"

    def _ensure(self) -> None:
        with self._lock:
            if self._dataset is None:
                self._dataset = self._open_dataset()
            if self._render is None:
                self._render = self._open_map()

    def frame_index(self, row: int) -> int:
        """The dataset frame index of trajectory row ``row``."""
        self._ensure()
        return int(self._frames[row])

    def render(self, row: int, T_wc: np.ndarray | None = None) -> np.ndarray | str:
        """The map rendered at row ``row``'s estimated pose (or at ``T_wc`` [4, 4] with that frame's exposure) over
        the viewer's white background, uint8 [h, w, 3]."""
        self._ensure()
        if isinstance(self._render, str):
            return self._render
        out = self._render(self.poses[row] if T_wc is None else T_wc, self.frame_index(row))
        rgb = out.color.clamp(0, 1) + (1 - out.alpha.clamp(0, 1))[..., None]  # [h, w, 3] premultiplied + white
        return (rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8)

    def input_image(self, row: int) -> tuple[np.ndarray | None, str]:
        """The input colour image of row ``row`` (uint8 [h, w, 3], width ``self.width``) and its caption; without
        the dataset, the nearest keyframe's stored image."""
        import cv2

        self._ensure()
        frame = self.frame_index(row)
        if not isinstance(self._dataset, str):
            rgb = (self._dataset[frame].rgb * 255).round().astype(np.uint8)
            caption = f"input frame {frame}"
        else:
            from ggfslam.viewer.layers import keyframe_images

            files = keyframe_images(self.run_dir)
            if not files:
                return None, self._dataset
            near = min(files, key=lambda f: abs(f - frame))
            with np.load(files[near]) as z:
                rgb = z["rgb"]
            caption = f"keyframe image of frame {near} ({self._dataset})"
        h, w = rgb.shape[:2]
        return cv2.resize(rgb, (self.width, round(h * self.width / w)), interpolation=cv2.INTER_AREA), caption
