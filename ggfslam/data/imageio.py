"""Checked reading and writing of colour and depth images (one clear error per bad file)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ggfslam.atomic import atomic_path
from ggfslam.errors import DatasetError


def read_rgb(path: str | Path) -> np.ndarray:
    """Read a colour image as float32 RGB [H, W, 3] in [0, 1] (8- or 16-bit, grey promoted to RGB)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "colour image not found")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(path, "cannot decode colour image (corrupt or unsupported format)")
    if img.dtype == np.uint8:
        scale = 255.0
    elif img.dtype == np.uint16:
        scale = 65535.0
    else:
        raise DatasetError(path, f"colour image must be 8- or 16-bit, got {img.dtype}")
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    elif img.shape[2] == 4:
        img = img[..., :3]
    elif img.shape[2] != 3:
        raise DatasetError(path, f"colour image must have 1, 3 or 4 channels, got {img.shape[2]}")
    return (img[..., ::-1].astype(np.float32) / scale).copy()


def read_depth(path: str | Path, depth_scale: float) -> np.ndarray:
    """Read a 16-bit single-channel depth PNG as float32 metres [H, W] (0 = invalid)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "depth image not found")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(path, "cannot decode depth image (corrupt or unsupported format)")
    if img.ndim != 2:
        raise DatasetError(path, f"depth image must have one channel, got shape {img.shape}")
    if img.dtype != np.uint16:
        bits = 8 * img.dtype.itemsize
        raise DatasetError(path, f"depth image must be 16-bit unsigned, got {bits}-bit {img.dtype}")
    return img.astype(np.float32) / np.float32(depth_scale)


def write_rgb(path: str | Path, rgb: np.ndarray) -> None:
    """Write float RGB [H, W, 3] in [0, 1] as an 8-bit image (format from the suffix)."""
    img = np.clip(np.round(np.asarray(rgb) * 255.0), 0, 255).astype(np.uint8)[..., ::-1]
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img):
            raise DatasetError(path, "cannot write colour image")


def write_depth(path: str | Path, depth_m: np.ndarray, depth_scale: float) -> None:
    """Write metric depth [H, W] as a 16-bit PNG with ``depth_scale`` units per metre (clipped to range)."""
    raw = np.clip(np.round(np.asarray(depth_m, dtype=np.float64) * depth_scale), 0, 65535).astype(np.uint16)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), raw):
            raise DatasetError(path, "cannot write depth image")
