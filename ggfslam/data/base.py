"""The lazily streaming RGB-D dataset interface shared by every reader."""
from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np

from ggfslam.data.imageio import read_depth, read_rgb
from ggfslam.data.types import NOISE_FREE_DEPTH_DIR, Camera, Frame
from ggfslam.data.undistort import Undistortion, undistortion_of
from ggfslam.errors import DatasetError
from ggfslam.geometry.depth import register_depth
from ggfslam.geometry.se3 import invert


class RGBDDataset(ABC):
    """A sequence of RGB-D frames read on demand, with start/stop/stride selection and optional resize.

    Subclasses index raw frames ``0 .. _raw_len()-1`` and implement ``_load``; this class maps the
    selection (``start``, ``stop``, ``stride``) onto them, removes the colour camera's lens distortion
    (``data/undistort.py``: frames and ``camera`` are pinhole from here on) and resizes images (intrinsics scaled
    to match).
    """

    def __init__(
        self,
        root: str | Path,
        start: int = 0,
        stop: int | None = None,
        stride: int = 1,
        resize: tuple[int, int] | None = None,
    ):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(self.root, "dataset folder not found")
        self._start, self._stop, self._stride = start, stop, stride
        self._resize = None if resize is None else (int(resize[0]), int(resize[1]))
        if self._resize is not None and min(self._resize) <= 0:
            raise DatasetError(self.root, f"resize must be two positive integers (width, height), got {resize}")
        if stride < 1:
            raise DatasetError(self.root, f"stride must be >= 1, got {stride}")
        if start < 0:
            raise DatasetError(self.root, f"start must be >= 0, got {start}")
        self._indices: np.ndarray | None = None
        self._registration: tuple[tuple[float, float, float, float], np.ndarray] | None = None
        self._T_depth_color: np.ndarray | None = None  # [4, 4] set when the ground truth is the depth camera's
        self._undistortion: tuple[Camera, Undistortion | None] | None = None  # (raw camera it is for, maps)

    # --- for subclasses -------------------------------------------------------------------------
    @abstractmethod
    def _raw_len(self) -> int:
        """Number of frames in the whole sequence."""

    @abstractmethod
    def _raw_camera(self) -> Camera:
        """Intrinsics at the stored resolution."""

    @abstractmethod
    def _raw_timestamps(self) -> np.ndarray:
        """Timestamps [N_raw] in seconds."""

    def _raw_gt(self) -> np.ndarray | None:
        """Ground-truth camera-to-world poses [N_raw, 4, 4], or None when the sequence has none."""
        return None

    @abstractmethod
    def _load(self, raw_index: int) -> tuple[np.ndarray, np.ndarray, str]:
        """Colour [H, W, 3] float32, depth [H, W] float32 metres, and the colour file name of one raw frame."""

    def _depth_name(self, raw_index: int) -> str | None:
        """The depth file of one raw frame, for error messages (None where depth is not read from its own file)."""
        return None

    # --- public API -----------------------------------------------------------------------------
    def set_depth_registration(self, depth_intrinsics: tuple[float, float, float, float],
                               T_color_depth: np.ndarray, ground_truth_of_depth: bool = False) -> None:
        """Warp every depth image into the colour camera when read: the depth camera's pinhole (fx, fy, cx, cy)
        and T_color_depth [4, 4] (``geometry.depth.register_depth``); with ``ground_truth_of_depth`` the
        ground-truth poses (the depth camera's) are moved to the colour camera. A distorted colour camera's depth is
        warped into its undistorted (pinhole) image."""
        self._registration = (tuple(float(x) for x in depth_intrinsics), np.asarray(T_color_depth, np.float64))
        self._T_depth_color = invert(self._registration[1]) if ground_truth_of_depth else None

    @property
    def indices(self) -> np.ndarray:
        """Raw indices of the selected frames [N]."""
        if self._indices is None:
            n = self._raw_len()
            if n == 0:
                raise DatasetError(self.root, "dataset has no frames")
            if self._start >= n:
                raise DatasetError(self.root, f"start={self._start} is past the last frame (sequence has {n})")
            stop = n if self._stop is None else min(self._stop, n)
            self._indices = np.arange(self._start, stop, self._stride)
            if len(self._indices) == 0:
                raise DatasetError(self.root, f"selection start={self._start} stop={self._stop} is empty")
        return self._indices

    def _pinhole(self) -> tuple[Camera, Undistortion | None]:
        """The colour camera after undistortion (the raw one when it has no distortion) and the maps that make it."""
        raw = self._raw_camera()
        if self._undistortion is None or self._undistortion[0] != raw:
            und = undistortion_of(raw)
            self._undistortion = (raw, und)
        und = self._undistortion[1]
        return (raw if und is None else und.camera), und

    @property
    def raw_camera(self) -> Camera:
        """The camera of the stored images, with its lens distortion (``camera`` is the frames' pinhole one)."""
        return self._raw_camera()

    @property
    def camera(self) -> Camera:
        """Intrinsics of the frames this dataset yields (pinhole: after undistortion, and after resize)."""
        cam = self._pinhole()[0]
        if self._resize is not None:
            cam = cam.resized(*self._resize)
        return cam

    @property
    def timestamps(self) -> np.ndarray:
        """Timestamps [N] of the selected frames."""
        return self._raw_timestamps()[self.indices]

    @property
    def gt_poses(self) -> np.ndarray | None:
        """Ground-truth camera-to-world poses [N, 4, 4] of the selected frames, or None."""
        gt = self._gt_colour()
        return None if gt is None else gt[self.indices]

    def _gt_colour(self) -> np.ndarray | None:
        """Ground-truth colour-camera-to-world poses [N_raw, 4, 4] (see ``set_depth_registration``), or None."""
        gt = self._raw_gt()
        if gt is None or self._T_depth_color is None:
            return gt
        return gt @ self._T_depth_color

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame {i} out of range for a sequence of {n}")
        raw = int(self.indices[i])
        rgb, depth, name = self._load(raw)
        raw_cam = self._raw_camera()
        check_frame_shapes(name, rgb, depth, raw_cam, self._depth_name(raw))
        cam, und = self._pinhole()
        if und is not None:
            rgb = und.rgb(rgb)
            if self._registration is None:  # depth registered to the raw colour image: the same warp
                depth = und.depth(depth)
        if self._registration is not None:  # the depth camera's image, straight into the pinhole colour camera
            depth = register_depth(depth, self._registration[0], (cam.fx, cam.fy, cam.cx, cam.cy),
                                   self._registration[1], cam.width, cam.height)
        # a generated sequence's noise-free depth; never warped: generated sequences need neither warp
        clean = self._noise_free_depth(raw) if und is None and self._registration is None else None
        if self._resize is not None and self._resize != (raw_cam.width, raw_cam.height):
            w, h = self._resize
            rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
            # nearest keeps depth edges sharp: averaging across a discontinuity invents surfaces
            depth = cv2.resize(depth, (w, h), interpolation=cv2.INTER_NEAREST)
            if clean is not None:
                clean = cv2.resize(clean, (w, h), interpolation=cv2.INTER_NEAREST)
        meta = {} if clean is None else {"depth_gt": np.ascontiguousarray(clean, dtype=np.float32)}
        gt = self._raw_gt()
        T_wc = None if gt is None else gt[raw] if self._T_depth_color is None else gt[raw] @ self._T_depth_color
        return Frame(
            index=i,
            timestamp=float(self._raw_timestamps()[raw]),
            rgb=np.ascontiguousarray(rgb, dtype=np.float32),
            depth=np.ascontiguousarray(depth, dtype=np.float32),
            T_wc=None if T_wc is None else T_wc.copy(),
            name=name,
            meta=meta,
        )

    def _noise_free_depth(self, raw_index: int) -> np.ndarray | None:
        """A generated sequence's noise-free depth [H, W] (metres) of one raw frame, else None."""
        return None

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def describe(self) -> str:
        """One line naming the sequence, its size and resolution."""
        cam = self.camera
        return f"{type(self).__name__}({self.root}, {len(self)} frames, {cam.width}x{cam.height})"


def check_frame_shapes(name: str, rgb: np.ndarray, depth: np.ndarray, camera: Camera,
                       depth_name: str | None = None) -> None:
    """Raise DatasetError unless colour [H, W, 3] (file ``name``) has the camera's size and depth [H, W] (file
    ``depth_name``, named in its error when given) colour's."""
    if rgb.shape[:2] != (camera.height, camera.width):
        raise DatasetError(name, f"colour image is {rgb.shape[1]}x{rgb.shape[0]}, expected "
                                 f"{camera.width}x{camera.height} like the rest of the sequence")
    if depth.shape != rgb.shape[:2]:
        colour = f"its colour image {name}" if depth_name else "colour"
        raise DatasetError(depth_name or name, f"depth image is {depth.shape[1]}x{depth.shape[0]} but {colour} is "
                                               f"{rgb.shape[1]}x{rgb.shape[0]}")


class ImageFileDataset(RGBDDataset):
    """A reader whose frames are colour/depth file pairs: subclasses fill the lists in ``__init__``.

    They set ``rgb_files`` and ``depth_files`` (one path per raw frame), ``_stamps`` [N], ``_cam`` and, when
    there is ground truth, ``_gt`` [N, 4, 4].
    """

    rgb_files: list[Path]
    depth_files: list[Path]
    _stamps: np.ndarray
    _cam: Camera
    _gt: np.ndarray | None = None

    def _raw_len(self) -> int:
        return len(self.rgb_files)

    def _raw_camera(self) -> Camera:
        return self._cam

    def _raw_timestamps(self) -> np.ndarray:
        return self._stamps

    def _raw_gt(self) -> np.ndarray | None:
        return self._gt

    @cached_property
    def _noise_free_dir(self) -> Path | None:
        """``depth_gt/`` of a generated sequence, None for any other folder."""
        d = self.root / NOISE_FREE_DEPTH_DIR
        return d if d.is_dir() else None

    def _noise_free_depth(self, raw_index: int) -> np.ndarray | None:
        if self._noise_free_dir is None:
            return None
        path = self._noise_free_dir / self.depth_files[raw_index].name
        return read_depth(path, self._cam.depth_scale) if path.is_file() else None

    def _load(self, raw_index: int) -> tuple[np.ndarray, np.ndarray, str]:
        rgb_path = self.rgb_files[raw_index]
        rgb = read_rgb(rgb_path)  # [H, W, 3]
        depth = read_depth(self.depth_files[raw_index], self._cam.depth_scale)  # [H, W] metres
        return rgb, depth, str(rgb_path)

    def _depth_name(self, raw_index: int) -> str | None:
        return str(self.depth_files[raw_index])
