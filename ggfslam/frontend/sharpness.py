"""How sharp a frame is: the keyframe choice avoids motion-blurred frames, whose blur the map would learn."""
from __future__ import annotations

import cv2
import numpy as np


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image at half size (higher is sharper; 0 for a flat image).

    rgb: [H, W, 3] float in [0, 1]. Half size keeps sensor noise, which the Laplacian amplifies, from passing
    for detail and costs ~1 ms at 640x480."""
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"sharpness: expected an [H, W, 3] colour image, got shape {rgb.shape}")
    grey = cv2.cvtColor((np.clip(rgb, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)  # [H, W]
    half = cv2.pyrDown(grey)  # [H/2, W/2]
    return float(cv2.Laplacian(half, cv2.CV_32F).var())
