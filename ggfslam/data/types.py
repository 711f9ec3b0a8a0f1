"""Frame and Camera: the data every stage of ggfslam passes around."""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)  # coefficient counts OpenCV's distortion model accepts (0: none)

NOISE_FREE_DEPTH_DIR = "depth_gt"
"""A folder beside ``depth/`` (same file names) with a simulated noisy sensor's noise-free depth: written from
``Frame.meta['depth_gt']`` (data/writer.py) and read back into it (data/base.py), so that the metrics of a generated
sequence score depth and normals against the surface rather than against the noise."""


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics of an RGB-D camera (OpenCV axes); depth_scale = raw depth units per metre."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    depth_scale: float = 1.0
    distortion: tuple[float, ...] = ()  # OpenCV order k1 k2 p1 p2 [k3]; empty = undistorted

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def resized(self, width: int, height: int) -> "Camera":
        """Intrinsics for the image resized to ``width`` x ``height`` (pixel-centre convention)."""
        sx, sy = width / self.width, height / self.height
        return replace(
            self,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            width=int(width),
            height=int(height),
        )

    def to_dict(self) -> dict:
        """Plain-dict form for JSON/YAML."""
        return {
            "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
            "width": self.width, "height": self.height, "depth_scale": self.depth_scale,
            "distortion": list(self.distortion),
        }


@dataclass
class Frame:
    """One RGB-D frame: rgb float32 [H, W, 3] in [0, 1], depth float32 metres [H, W] (0 = invalid)."""

    index: int  # position in the (selected) sequence
    timestamp: float  # seconds
    rgb: np.ndarray  # [H, W, 3] float32
    depth: np.ndarray  # [H, W] float32 metres
    T_wc: np.ndarray | None = None  # [4, 4] ground-truth camera-to-world, if known
    name: str = ""  # source file of the colour image, for messages
    meta: dict = field(default_factory=dict)

    @property
    def height(self) -> int:
        """Image rows."""
        return int(self.rgb.shape[0])

    @property
    def width(self) -> int:
        """Image columns."""
        return int(self.rgb.shape[1])
