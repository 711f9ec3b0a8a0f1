"""Write RGB-D sequences to disk in TUM layout (plus a ``camera.yaml`` with the intrinsics)."""
from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from ggfslam.atomic import write_text_atomic
from ggfslam.data.camera_file import CAMERA_FILE, write_camera_yaml
from ggfslam.data.imageio import write_depth, write_rgb
from ggfslam.data.trajectory_io import write_tum_trajectory
from ggfslam.data.types import Camera, Frame
from ggfslam.errors import RunDirError


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
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise RunDirError(f"{out}: folder exists and is not empty (pass overwrite=True to replace its sequence)")
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    rgb_lines = ["# color images", "# timestamp filename"]
    depth_lines = ["# depth maps", "# timestamp filename"]
    stamps, poses, have_gt = [], [], True
    for f in frames:
        ts = f"{f.timestamp:.6f}"
        write_rgb(out / "rgb" / f"{ts}.png", f.rgb)
        write_depth(out / "depth" / f"{ts}.png", f.depth, depth_scale)
        rgb_lines.append(f"{ts} rgb/{ts}.png")
        depth_lines.append(f"{ts} depth/{ts}.png")
        stamps.append(f.timestamp)
        if f.T_wc is None:
            have_gt = False
        else:
            poses.append(f.T_wc)
    write_text_atomic(out / "rgb.txt", "\n".join(rgb_lines) + "\n")
    write_text_atomic(out / "depth.txt", "\n".join(depth_lines) + "\n")
    if have_gt and poses:
        write_tum_trajectory(out / "groundtruth.txt", np.array(stamps), np.stack(poses), header="ground truth")
    cam = Camera(camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, depth_scale,
                 camera.distortion)
    write_camera_yaml(out / CAMERA_FILE, cam)
    return out
