"""Image and depth metrics: PSNR, SSIM (the differentiable SSIM the training loss uses), LPIPS, depth L1."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch
from pytorch_msssim import ssim as _ms_ssim

from ggfslam.errors import ConfigError
from ggfslam.eval.base import Metric


def _as_chw(img) -> torch.Tensor:
    """[3, H, W] float tensor from numpy [H, W, 3] or torch [3, H, W]."""
    if isinstance(img, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32)).permute(2, 0, 1)
    return img


def psnr(img: np.ndarray | torch.Tensor, ref: np.ndarray | torch.Tensor, mask=None) -> float:
    """Peak signal-to-noise ratio (dB) of images in [0, 1]; ``mask`` [H, W] restricts the pixels."""
    a = torch.as_tensor(np.asarray(img) if isinstance(img, np.ndarray) else img, dtype=torch.float64)
    b = torch.as_tensor(np.asarray(ref) if isinstance(ref, np.ndarray) else ref, dtype=torch.float64)
    err = (a - b) ** 2
    if mask is not None:
        m = torch.as_tensor(np.asarray(mask) if isinstance(mask, np.ndarray) else mask, dtype=torch.bool)
        err = err[m] if err.shape[:2] == m.shape else err[..., m]
    mse = float(err.mean())
    return float("inf") if mse == 0 else -10.0 * float(np.log10(mse))


_WINDOWS: dict[tuple, torch.Tensor] = {}
_SSIM_SIZE = 11  # SSIM's Gaussian window (sigma 1.5), as pytorch_msssim's default


def _gauss_window(channels: int, dtype, device, size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    key = (channels, dtype, device, size, sigma)
    if key not in _WINDOWS:
        x = torch.arange(size, dtype=dtype, device=device) - size // 2
        g = torch.exp(-(x ** 2) / (2 * sigma ** 2))
        _WINDOWS[key] = (g / g.sum()).view(1, 1, 1, size).repeat(channels, 1, 1, 1)  # [C, 1, 1, size]
    return _WINDOWS[key]


def ssim(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Differentiable SSIM (11x11 Gaussian window, sigma 1.5, 'valid' borders) of [3, H, W] or [B, 3, H, W]
    images in [0, 1]; the mean over pixels and channels.

    The same formula as ``pytorch_msssim.ssim`` (tested against it), but the five filtered maps (means,
    second moments) go through one grouped separable convolution instead of five: the mapping loss calls
    this every step. Images smaller than the window fall back to ``pytorch_msssim``.
    """
    if img.dim() == 3:
        img, ref = img[None], ref[None]
    B, C, H, W = img.shape
    if H < _SSIM_SIZE or W < _SSIM_SIZE:
        return _ms_ssim(img, ref, data_range=1.0, size_average=True)
    z = torch.cat([img, ref, img * img, ref * ref, img * ref], dim=1)  # [B, 5C, H, W]
    win = _gauss_window(5 * C, img.dtype, img.device)
    z = torch.nn.functional.conv2d(z, win, groups=5 * C)  # along W
    z = torch.nn.functional.conv2d(z, win.transpose(2, 3), groups=5 * C)  # along H
    mu1, mu2, e11, e22, e12 = z.split(C, dim=1)
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    cs = (2 * (e12 - mu12) + c2) / ((e11 - mu1_sq) + (e22 - mu2_sq) + c2)
    return (((2 * mu12 + c1) / (mu1_sq + mu2_sq + c1)) * cs).mean()


def ssim_np(img: np.ndarray, ref: np.ndarray) -> float:
    """SSIM of two numpy RGB images [H, W, 3] in [0, 1]: ``ssim``'s formula (11x11 Gaussian window, sigma 1.5, 'valid'
    borders), its five maps filtered by OpenCV (a third of the grouped convolutions' time at 640x480; the same value
    to ~1e-6, tests/test_eval.py)."""
    x = np.asarray(img, np.float32)
    y = np.asarray(ref, np.float32)
    if x.ndim != 3 or x.shape[2] != 3 or y.shape != x.shape:
        raise ValueError(f"ssim_np: expected two RGB images [H, W, 3] of one size, got {x.shape} and {y.shape}")
    r = _SSIM_SIZE // 2
    if x.shape[0] < _SSIM_SIZE or x.shape[1] < _SSIM_SIZE:
        with torch.no_grad():
            return float(ssim(_as_chw(x), _as_chw(y)))
    g = _gauss_window(1, torch.float64, torch.device("cpu")).view(-1).numpy()  # [11]

    def blur(z: np.ndarray) -> np.ndarray:  # [H, W, 3] -> the valid region [H - 10, W - 10, 3]
        return cv2.sepFilter2D(z, cv2.CV_32F, g, g, borderType=cv2.BORDER_REFLECT)[r:-r, r:-r]

    mu1, mu2, e11, e22, e12 = blur(x), blur(y), blur(x * x), blur(y * y), blur(x * y)
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    cs = (2 * (e12 - mu12) + c2) / ((e11 - mu1_sq) + (e22 - mu2_sq) + c2)
    return float((((2 * mu12 + c1) / (mu1_sq + mu2_sq + c1)) * cs).mean(dtype=np.float64))


def depth_l1_cm(depth: np.ndarray, ref: np.ndarray) -> float:
    """Mean |depth - ref| in centimetres over pixels where the reference depth is valid (> 0)."""
    valid = ref > 0
    if not np.any(valid):
        return float("nan")
    return float(100.0 * np.mean(np.abs(depth[valid].astype(np.float64) - ref[valid])))


DEPTH_TAIL_M = 0.05  # an error above this is in the tail of a depth L1
DEPTH_STEP_M = 0.10  # a step between neighbouring reference pixels above this is a depth discontinuity
DEPTH_STEP_PX = 3  # pixels within this distance of a discontinuity are "at" it
DEPTH_SPLIT_KEYS = ("depth_median_cm", "depth_hole_cm", "depth_tail_cm", "depth_tail_step_cm")


def depth_error_split(depth: np.ndarray, ref: np.ndarray) -> dict:
    """Where the depth L1 of ``depth`` [H, W] against ``ref`` [H, W] (m, 0 = none) comes from, in centimetres
    averaged over the valid reference pixels as ``depth_l1_cm`` is, so the parts add up to it:
    ``depth_hole_cm`` (nothing rendered), ``depth_tail_cm`` (rendered, off by more than 5 cm; of which
    ``depth_tail_step_cm`` within 3 px of a reference depth discontinuity, where blended depth mixes
    foreground and background) and the rest; plus ``depth_median_cm``, the median error where rendered."""
    valid = ref > 0
    if not np.any(valid):
        return dict.fromkeys(DEPTH_SPLIT_KEYS, float("nan"))
    err = np.where(valid, np.abs(depth.astype(np.float64) - ref), 0.0)  # [H, W]
    covered = valid & (depth > 0)
    tail = covered & (err > DEPTH_TAIL_M)
    step = np.zeros(ref.shape, bool)
    step[:, 1:] |= np.abs(np.diff(ref, axis=1)) > DEPTH_STEP_M
    step[1:, :] |= np.abs(np.diff(ref, axis=0)) > DEPTH_STEP_M
    size = 2 * DEPTH_STEP_PX + 1
    near_step = cv2.dilate(step.astype(np.uint8), np.ones((size, size), np.uint8)) > 0
    n = valid.sum()
    return {"depth_median_cm": float(100.0 * np.median(err[covered])) if covered.any() else float("nan"),
            "depth_hole_cm": float(100.0 * err[valid & ~covered].sum() / n),
            "depth_tail_cm": float(100.0 * err[tail].sum() / n),
            "depth_tail_step_cm": float(100.0 * err[tail & near_step].sum() / n)}


GROSS_SQ_ERROR = 0.1  # a pixel's mean squared RGB error above this (RMS ~ 81 of 255) is gross
GROSS_MIN_AREA = 0.0013  # ... and counts when its connected region covers this share of the image (400 px at 640x480)
COLOUR_SPLIT_KEYS = ("psnr_without_gross", "gross_area_percent")


def colour_error_split(img: np.ndarray, ref: np.ndarray) -> dict:
    """How much of a frame's PSNR is lost to gross-error regions: connected regions of pixels off by more than
    ``GROSS_SQ_ERROR`` (mean squared over RGB) covering at least ``GROSS_MIN_AREA`` of the image, the signature of
    content that changes while the camera looks at it (a screen playing video, a person walking by) rather than
    of blur or small misalignment. ``psnr_without_gross``: the PSNR of img [H, W, 3] against ref over the other
    pixels; ``gross_area_percent``: the share of the image they cover. A diagnostic beside the PSNR, never
    instead of it."""
    d = np.subtract(img, ref, dtype=np.float64)  # [H, W, 3]
    se = np.einsum("ijk,ijk->ij", d, d) / 3.0  # [H, W] mean over RGB (a quarter of the time of (d ** 2).mean(-1))
    gross = (se > GROSS_SQ_ERROR).astype(np.uint8)
    if not gross.any():  # the common case: no region to label
        mse = float(se.mean())
        return {"psnr_without_gross": float("inf") if mse == 0 else -10.0 * float(np.log10(mse)),
                "gross_area_percent": 0.0}
    _, labels, stats, _ = cv2.connectedComponentsWithStats(gross, connectivity=8)
    big = np.nonzero(stats[1:, cv2.CC_STAT_AREA] >= GROSS_MIN_AREA * se.size)[0] + 1  # [B] labels of big regions
    mask = np.isin(labels, big) if len(big) else np.zeros(se.shape, bool)
    rest = se[~mask]
    mse = float(rest.mean()) if rest.size else 0.0
    return {"psnr_without_gross": float("inf") if mse == 0 else -10.0 * float(np.log10(mse)),
            "gross_area_percent": float(100.0 * mask.mean())}


class LPIPS:
    """LPIPS from a local TorchScript network (``net(x, y)`` on [-1, 1] images); weights are never downloaded."""

    def __init__(self, weights: str | Path | None):
        self.net = None
        if weights is None:
            return
        path = Path(weights)
        if not path.is_file():
            raise ConfigError(f"eval.lpips_weights: {path} not found (a TorchScript LPIPS network file)")
        try:
            self.net = torch.jit.load(str(path), map_location="cpu").eval()
        except Exception as e:  # torch raises many types for a bad archive
            raise ConfigError(f"eval.lpips_weights: {path} is not a TorchScript module ({e.__class__.__name__})") from None

    @property
    def available(self) -> bool:
        """Whether the LPIPS network could be loaded."""
        return self.net is not None

    def __call__(self, img: np.ndarray, ref: np.ndarray) -> float:
        """LPIPS distance of two RGB images [H, W, 3] in [0, 1]."""
        if self.net is None:
            raise RuntimeError("LPIPS: no weights")
        with torch.no_grad():
            a = _as_chw(img)[None] * 2 - 1
            b = _as_chw(ref)[None] * 2 - 1
            return float(self.net(a, b).mean())


def normal_error_deg(normals: np.ndarray, ref: np.ndarray) -> float:
    """Mean angle (degrees) between unit normal maps [H, W, 3] over pixels where both are defined (non-zero)."""
    a = np.asarray(normals, np.float64).reshape(-1, 3)  # [H W, 3]
    b = np.asarray(ref, np.float64).reshape(-1, 3)  # [H W, 3]
    # squared lengths and dot products row by row (einsum: a quarter of the time of norm() and boolean row gathers)
    ok = (np.einsum("ij,ij->i", a, a) > 0.25) & (np.einsum("ij,ij->i", b, b) > 0.25)  # [H W]: both |n| > 0.5
    if not ok.any():
        return float("nan")
    cos = np.clip(np.einsum("ij,ij->i", a, b)[ok], -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)).mean())


class PSNR(Metric):
    """PSNR (dB) per image pair; ``process_data((img, ref))``."""

    name, unit = "PSNR", "dB"

    def process_data(self, data) -> None:
        """Add the PSNR of one (image, reference) pair."""
        self.values.append(psnr(*data))


class SSIM(Metric):
    """SSIM per image pair; ``process_data((img, ref))``."""

    name, unit = "SSIM", ""

    def process_data(self, data) -> None:
        """Add the SSIM of one (image, reference) pair."""
        self.values.append(ssim_np(*data))


class DepthL1(Metric):
    """Depth L1 (cm) per depth pair over valid reference pixels; ``process_data((depth, ref))``."""

    name, unit = "Depth L1", "cm"

    def process_data(self, data) -> None:
        """Add the depth L1 (cm) of one (image, reference) pair."""
        self.values.append(depth_l1_cm(*data))
