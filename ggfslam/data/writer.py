"""Write RGB-D sequences to disk in TUM layout (plus a ``camera.yaml`` with the intrinsics)."""
from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from ggfslam.atomic import write_text_atomic
from ggfslam.data.camera_file import CAMERA_FILE, write_camera_yaml
from ggfslam.data.imageio import write_depth, write_rgb
from ggfslam.data.trajectory_io import write_tum_trajectory
from ggfslam.data.types import NOISE_FREE_DEPTH_DIR, Camera, Frame
from ggfslam.errors import RunDirError


class TumSequenceWriter:
    """Writes frames one by one as ``rgb/*.png``, ``depth/*.png`` (16-bit, ``depth_scale`` per metre); ``close`` adds
    the TUM lists, ``camera.yaml`` and, when every frame carried ``T_wc``, ``groundtruth.txt``. Refuses a non-empty
    folder unless ``overwrite``."""

    def __init__(self, out_dir: str | Path, camera: Camera, depth_scale: float = 5000.0, overwrite: bool = False):
        out = Path(out_dir)
        if out.exists() and any(out.iterdir()) and not overwrite:
            raise RunDirError(f"{out}: folder exists and is not empty (pass overwrite=True to replace its sequence)")
        (out / "rgb").mkdir(parents=True, exist_ok=True)
        (out / "depth").mkdir(parents=True, exist_ok=True)
        self.out, self.camera, self.depth_scale = out, camera, depth_scale
        self.rgb_lines = ["# color images", "# timestamp filename"]
        self.depth_lines = ["# depth maps", "# timestamp filename"]
        self.stamps: list[float] = []
        self.poses: list[np.ndarray] = []
        self.have_gt = True

    def add(self, f: Frame) -> tuple[Path, Path]:
        """Write one frame; returns its (colour, depth) file paths."""
        ts = f"{f.timestamp:.6f}"
        rgb, depth = self.out / "rgb" / f"{ts}.png", self.out / "depth" / f"{ts}.png"
        write_rgb(rgb, f.rgb)
        write_depth(depth, f.depth, self.depth_scale)
        clean = f.meta.get("depth_gt") if f.meta else None
        if clean is not None:  # a simulated sensor's noise-free depth, what the metrics score against
            (self.out / NOISE_FREE_DEPTH_DIR).mkdir(exist_ok=True)
            write_depth(self.out / NOISE_FREE_DEPTH_DIR / f"{ts}.png", clean, self.depth_scale)
        self.rgb_lines.append(f"{ts} rgb/{ts}.png")
        self.depth_lines.append(f"{ts} depth/{ts}.png")
        self.stamps.append(f.timestamp)
        if f.T_wc is None:
            self.have_gt = False
        else:
            self.poses.append(f.T_wc)
        return rgb, depth

    def close(self) -> Path:
        """Write the lists and camera.yaml; returns the folder."""
        out = self.out
        write_text_atomic(out / "rgb.txt", "\n".join(self.rgb_lines) + "\n")
        write_text_atomic(out / "depth.txt", "\n".join(self.depth_lines) + "\n")
        if self.have_gt and self.poses:
            write_tum_trajectory(out / "groundtruth.txt", np.array(self.stamps), np.stack(self.poses),
                                 header="ground truth")
        c = self.camera
        write_camera_yaml(out / CAMERA_FILE, Camera(c.fx, c.fy, c.cx, c.cy, c.width, c.height, self.depth_scale,
                                                    c.distortion))
        return out


def write_tum_sequence(
    out_dir: str | Path,
    frames: Iterable[Frame],
    camera: Camera,
    depth_scale: float = 5000.0,
    overwrite: bool = False,
) -> Path:
    """Write frames as ``rgb/*.png``, ``depth/*.png`` (16-bit, ``depth_scale`` per metre), TUM lists and camera.yaml.

    ``groundtruth.txt`` is written when every frame carries ``T_wc``. Refuses a non-empty folder unless
    ``overwrite``.
    """
    writer = TumSequenceWriter(out_dir, camera, depth_scale, overwrite)
    for f in frames:
        writer.add(f)
    return writer.close()
