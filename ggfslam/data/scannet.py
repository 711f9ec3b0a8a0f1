"""ScanNet reader for exported frames: ``color/<i>.jpg``, ``depth/<i>.png``, ``pose/<i>.txt``, ``intrinsic/``."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ggfslam.data.base import ImageFileDataset
from ggfslam.data.imageio import read_depth, read_rgb
from ggfslam.data.paths import list_files, read_matrix, require_dir
from ggfslam.data.types import Camera
from ggfslam.errors import DatasetError
from ggfslam.geometry.se3 import rigidity_error

SCANNET_DEPTH_SCALE = 1000.0  # depth PNGs hold millimetres


def _numbered_files(folder: Path, suffixes: tuple[str, ...]) -> dict[int, Path]:
    out: dict[int, Path] = {}
    for p in list_files(folder, suffixes):
        if not p.stem.isdigit():
            raise DatasetError(p, "expected a frame-number file name such as 0.jpg or 000120.png")
        k = int(p.stem)
        if k in out:
            raise DatasetError(p, f"frame number {k} is also used by {out[k].name}")
        out[k] = p
    return out


def read_intrinsic_matrix(path: str | Path) -> np.ndarray:
    """3x3 K from a ScanNet intrinsic file (a 4x4 matrix, one row per line), checked fx, fy > 0."""
    M = read_matrix(path, 4, 4)  # [4, 4]
    K = M[:3, :3]
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DatasetError(path, f"expected finite intrinsics with fx, fy > 0, got fx={K[0, 0]} fy={K[1, 1]}")
    return K


def read_scannet_pose(path: str | Path) -> np.ndarray | None:
    """Camera-to-world pose [4, 4] from a ScanNet pose file, or None if ScanNet marked it invalid (all inf/nan)."""
    T = read_matrix(path, 4, 4)  # [4, 4]
    finite = np.isfinite(T)
    if not finite.any():
        return None
    if not finite.all():  # ScanNet's invalid marker fills the whole matrix; a partial one is corruption
        raise DatasetError(path, "pose is partly non-finite (ScanNet marks invalid poses with a fully -inf matrix)")
    err = rigidity_error(T)
    if err:
        raise DatasetError(path, err)
    return T


class ScanNetDataset(ImageFileDataset):
    """A ScanNet scene exported by ScanNet's SensReader; frame numbers come from the file names.

    Frames whose pose file is entirely non-finite (ScanNet's marker for a lost track) are skipped and listed
    in ``skipped_invalid_pose``; partly non-finite or non-rigid poses raise. Without a ``pose/`` folder the
    sequence has no ground truth. Colour is resized to the depth size (ScanNet: 1296x968 -> 640x480) and
    the intrinsics are those of ``intrinsic/intrinsic_depth.txt`` (else ``intrinsic_color.txt`` scaled);
    ``camera`` overrides both. Timestamps are ``frame number / fps``.
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
        colour_dir = require_dir(self.root / "color", "ScanNet color/")
        depth_dir = require_dir(self.root / "depth", "ScanNet depth/")
        colour = _numbered_files(colour_dir, (".jpg", ".jpeg", ".png"))
        depth = _numbered_files(depth_dir, (".png",))
        if not colour:
            raise DatasetError(colour_dir, "no colour images <i>.jpg found")
        for k in sorted(set(colour) | set(depth)):
            if k not in depth:
                raise DatasetError(depth_dir / f"{k}.png", f"depth image missing for {colour[k].name} "
                                   f"({len(colour)} colour vs {len(depth)} depth images)")
            if k not in colour:
                raise DatasetError(colour_dir / f"{k}.jpg", f"colour image missing for {depth[k].name} "
                                   f"({len(colour)} colour vs {len(depth)} depth images)")
        numbers = sorted(colour)
        self.skipped_invalid_pose: list[int] = []  # frame numbers dropped for a fully non-finite pose
        self._gt: np.ndarray | None = None
        pose_dir = self.root / "pose"
        if pose_dir.is_dir():
            poses, kept = [], []
            for k in numbers:
                pose_file = pose_dir / f"{k}.txt"
                if not pose_file.is_file():
                    raise DatasetError(pose_file, f"pose file missing for {colour[k].name}")
                T = read_scannet_pose(pose_file)
                if T is None:
                    self.skipped_invalid_pose.append(k)
                else:
                    poses.append(T)
                    kept.append(k)
            if not kept:
                raise DatasetError(pose_dir, "every pose is invalid (non-finite): no frame can be used")
            numbers = kept
            self._gt = np.stack(poses)  # [N, 4, 4]
        self.frame_numbers = np.array(numbers, dtype=np.int64)  # [N]
        self.rgb_files = [colour[k] for k in numbers]
        self.depth_files = [depth[k] for k in numbers]
        self._stamps = self.frame_numbers / float(fps)  # [N]
        self._cam = camera if camera is not None else self._camera_from_files()  # now: fail before a run starts

    def _camera_from_files(self) -> Camera:
        # the depth grid is the output grid, so its size comes from the first depth image
        depth_h, depth_w = read_depth(self.depth_files[0], SCANNET_DEPTH_SCALE).shape
        intr = self.root / "intrinsic"
        depth_file, colour_file = intr / "intrinsic_depth.txt", intr / "intrinsic_color.txt"
        if depth_file.is_file():
            K = read_intrinsic_matrix(depth_file)
            return Camera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], depth_w, depth_h, SCANNET_DEPTH_SCALE)
        if colour_file.is_file():
            K = read_intrinsic_matrix(colour_file)
            h, w = read_rgb(self.rgb_files[0]).shape[:2]
            cam = Camera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h, SCANNET_DEPTH_SCALE)
            return cam.resized(depth_w, depth_h)
        raise DatasetError(depth_file, "intrinsics not found (nor intrinsic_color.txt): set dataset.camera (fx, fy, "
                                       "cx, cy, width, height, depth_scale)")

    def _load(self, raw_index: int) -> tuple[np.ndarray, np.ndarray, str]:
        cam = self._raw_camera()
        rgb_path = self.rgb_files[raw_index]
        rgb = read_rgb(rgb_path)  # [Hc, Wc, 3]
        depth = read_depth(self.depth_files[raw_index], cam.depth_scale)  # [H, W] metres
        if rgb.shape[:2] != depth.shape:
            # ScanNet's colour camera has more pixels than its depth camera: bring colour to the depth grid
            rgb = cv2.resize(rgb, (depth.shape[1], depth.shape[0]), interpolation=cv2.INTER_AREA)
        return rgb, depth, str(rgb_path)
