"""Replica reader for the NICE-SLAM layout: ``results/frame%06d.jpg``, ``results/depth%06d.png``, ``traj.txt``."""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np

from ggfslam.data.base import ImageFileDataset
from ggfslam.data.paths import read_number_rows, require_dir
from ggfslam.data.types import Camera
from ggfslam.errors import DatasetError
from ggfslam.geometry.se3 import rigidity_error

_COLOUR_RE = re.compile(r"^frame(\d+)\.(jpg|jpeg|png)$", re.IGNORECASE)
_DEPTH_RE = re.compile(r"^depth(\d+)\.png$", re.IGNORECASE)
_CAM_KEYS = ("w", "h", "fx", "fy", "cx", "cy", "scale")


def read_cam_params(path: str | Path) -> Camera:
    """Intrinsics from a NICE-SLAM ``cam_params.json`` (``{"camera": {w, h, fx, fy, cx, cy, scale}}``)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "camera file not found (or set dataset.camera to use other intrinsics)")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise DatasetError(path, f"not valid JSON ({e.msg})", e.lineno) from None
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(path, f"cannot read camera file ({e})") from None
    cam = data.get("camera") if isinstance(data, dict) else None
    if not isinstance(cam, dict):
        raise DatasetError(path, 'expected {"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}}')
    vals = {}
    for key in _CAM_KEYS:
        if key not in cam:
            raise DatasetError(path, f"field 'camera.{key}' is missing (expected {', '.join(_CAM_KEYS)})")
        v = cam[key]
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        if ok and key in ("w", "h"):
            ok = float(v).is_integer() and v > 0
        elif ok and key in ("fx", "fy", "scale"):
            ok = v > 0
        if not ok:
            raise DatasetError(path, f"field 'camera.{key}' has an invalid value {v!r}")
        vals[key] = v
    return Camera(float(vals["fx"]), float(vals["fy"]), float(vals["cx"]), float(vals["cy"]),
                  int(vals["w"]), int(vals["h"]), float(vals["scale"]))


def read_matrix_trajectory(path: str | Path) -> np.ndarray:
    """Camera-to-world poses [N, 4, 4] from a file of 16 row-major numbers per line, each checked rigid."""
    path = Path(path)
    poses = []
    for lineno, values in read_number_rows(path, 16):
        T = values.reshape(4, 4)
        err = rigidity_error(T)
        if err:
            raise DatasetError(path, err, lineno)
        poses.append(T)
    if not poses:
        raise DatasetError(path, "trajectory file holds no poses")
    return np.stack(poses)


def _numbered(folder: Path, pattern: re.Pattern) -> dict[int, Path]:
    out: dict[int, Path] = {}
    for p in folder.iterdir():
        m = pattern.match(p.name)
        if m and p.is_file():
            k = int(m.group(1))
            if k in out:
                raise DatasetError(p, f"frame number {k} is also used by {out[k].name}")
            out[k] = p
    return out


class ReplicaDataset(ImageFileDataset):
    """A Replica sequence as rendered by NICE-SLAM; frame k is ``frame{k:06d}`` with pose on line k of traj.txt.

    ``traj.txt`` may hold more poses than there are images (the extra ones are ignored, but every line
    is checked); fewer is an error. Timestamps are ``k / fps``. ``camera`` overrides ``cam_params.json``.
    """

    def __init__(
        self,
        root: str | Path,
        camera: Camera | None = None,
        fps: float = 30.0,
        start: int = 0,
        stop: int | None = None,
        stride: int = 1,
        resize: tuple[int, int] | None = None,
    ):
        super().__init__(root, start=start, stop=stop, stride=stride, resize=resize)
        if not fps > 0:
            raise DatasetError(self.root, f"fps must be > 0, got {fps}")
        results = require_dir(self.root / "results", "Replica results/")
        colour = _numbered(results, _COLOUR_RE)
        depth = _numbered(results, _DEPTH_RE)
        if not colour:
            raise DatasetError(results, "no colour images frame%06d.jpg found")
        for k in sorted(set(colour) | set(depth)):
            if k not in depth:
                raise DatasetError(results / f"depth{k:06d}.png", f"depth image missing for {colour[k].name} "
                                   f"({len(colour)} colour vs {len(depth)} depth images)")
            if k not in colour:
                raise DatasetError(results / f"frame{k:06d}.jpg", f"colour image missing for {depth[k].name} "
                                   f"({len(colour)} colour vs {len(depth)} depth images)")
        self.frame_numbers = np.array(sorted(colour), dtype=np.int64)  # [N]
        self.rgb_files = [colour[k] for k in self.frame_numbers]
        self.depth_files = [depth[k] for k in self.frame_numbers]
        self._cam = camera if camera is not None else read_cam_params(self.root / "cam_params.json")
        traj_path = self.root / "traj.txt"
        poses = read_matrix_trajectory(traj_path)  # [P, 4, 4]
        need = int(self.frame_numbers[-1]) + 1
        if len(poses) < need:
            raise DatasetError(traj_path, f"holds {len(poses)} poses but the images go up to "
                                          f"{self.rgb_files[-1].name} (needs at least {need})")
        self._gt = poses[self.frame_numbers]  # [N, 4, 4]
        self._stamps = self.frame_numbers / float(fps)  # [N]
