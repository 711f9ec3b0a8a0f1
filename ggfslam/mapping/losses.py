"""Mapping losses (METHOD.md §5): photometric L1 + SSIM, depth L1 and normal consistency."""
from __future__ import annotations

import torch

from ggfslam.eval.image import ssim
from ggfslam.mapping.loss_kernels import SSIM_SIZE, photometric_loss_fused
from ggfslam.mapping.pointwise_losses import depth_l1_fused, fused_ok, opacity_entropy_fused, scale_volume_fused


def photometric_loss(pred: torch.Tensor, gt: torch.Tensor, lambda_ssim: float = 0.2) -> torch.Tensor:
    """``(1 - l) L1 + l (1 - SSIM)`` of images [H, W, 3] in [0, 1] (l = 0.2: the paper's 0.8 / 0.2); the compiled
    kernel on CPU, ``photometric_loss_reference`` elsewhere (and for images smaller than the SSIM window)."""
    if (lambda_ssim > 0 and pred.device.type == "cpu" and pred.dtype in (torch.float32, torch.float64)
            and min(pred.shape[0], pred.shape[1]) >= SSIM_SIZE):
        return photometric_loss_fused(pred, gt, lambda_ssim)
    return photometric_loss_reference(pred, gt, lambda_ssim)


def photometric_loss_reference(pred: torch.Tensor, gt: torch.Tensor, lambda_ssim: float = 0.2) -> torch.Tensor:
    """Plain-torch ``photometric_loss``: L1 and eval/image.py's differentiable SSIM."""
    l1 = (pred - gt).abs().mean()
    if lambda_ssim == 0:
        return l1
    return (1 - lambda_ssim) * l1 + lambda_ssim * (1 - ssim(pred.permute(2, 0, 1), gt.permute(2, 0, 1)))


def depth_loss(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Mean |pred - gt| (m) over pixels with valid sensor depth (gt > 0); depth maps [H, W]. Compiled on the CPU
    (pointwise_losses.py), ``depth_loss_reference`` elsewhere."""
    return depth_l1_fused(pred, gt) if fused_ok(pred, gt) else depth_loss_reference(pred, gt)


def depth_loss_reference(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Plain-torch ``depth_loss``."""
    valid = (gt > 0).to(pred.dtype)
    # a masked sum, not boolean indexing: no nonzero() forward and no index_put backward per step
    return ((pred - gt).abs() * valid).sum() / valid.sum().clamp_min(1)


def normal_loss(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Mean (1 - pred . gt) over pixels where both normal maps [H, W, 3] are defined (non-zero)."""
    valid = ((gt.abs().sum(-1) > 0) & (pred.detach().abs().sum(-1) > 0)).to(pred.dtype)
    return ((1 - (pred * gt).sum(-1)) * valid).sum() / valid.sum().clamp_min(1)


def depth_spread_loss(depth_raw: torch.Tensor, depth_sq: torch.Tensor, alpha: torch.Tensor,
                      valid: torch.Tensor | None = None, min_alpha: float = 0.01) -> torch.Tensor:
    """Mean, over the pixels ``valid`` [H, W] bool (default all) with alpha > min_alpha, of the blending weights'
    relative variance of the Gaussians' view depths along each ray, ``alpha * sum w z^2 / (sum w z)^2 - 1``, from
    depth_raw = sum w z, depth_sq = sum w z^2 and alpha = sum w, all [H, W] (2DGS's depth distortion, squared and
    scale-free). Scaling every weight of a pixel leaves it unchanged, so turning transparent does not lower it (short
    of alpha <= min_alpha); ``valid`` should not depend on the render either (the sensor's depth, not its alpha)."""
    a = alpha.double()
    ok = (a.detach() > min_alpha) & (depth_raw.detach() > 0)
    if valid is not None:
        ok &= valid
    # float64: the ratio is 1 + O(1e-5) on a surface, float32 would cancel it to noise
    ratio = a * depth_sq.double() / torch.where(ok, depth_raw.double(), torch.ones_like(a)) ** 2
    spread = torch.where(ok, ratio - 1, torch.zeros_like(a))
    return (spread.sum() / ok.sum().clamp_min(1)).to(alpha.dtype)


def opacity_entropy(opacity: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Mean binary entropy -o ln o - (1 - o) ln(1 - o) of opacities [G] in (0, 1) (clamped to [eps, 1 - eps]):
    smallest where each Gaussian is either opaque or gone (o -> 0 sends its child below the decoder's mask).
    Compiled on the CPU, ``opacity_entropy_reference`` elsewhere."""
    return opacity_entropy_fused(opacity, eps) if fused_ok(opacity) else opacity_entropy_reference(opacity, eps)


def opacity_entropy_reference(opacity: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Plain-torch ``opacity_entropy``."""
    o = opacity.clamp(eps, 1.0 - eps)
    return -(o * torch.log(o) + (1.0 - o) * torch.log1p(-o)).mean()


def scale_volume(scales: torch.Tensor) -> torch.Tensor:
    """Mean product of the three scales [G, 3] (the children's mean volume up to 4/3 pi). Compiled on the CPU,
    ``scale_volume_reference`` elsewhere."""
    return scale_volume_fused(scales) if fused_ok(scales) else scale_volume_reference(scales)


def scale_volume_reference(scales: torch.Tensor) -> torch.Tensor:
    """Plain-torch ``scale_volume`` (``prod(dim=1)``'s backward was 1.1 ms at 100k children, this form's 0.4)."""
    s0, s1, s2 = scales.unbind(1)
    return (s0 * s1 * s2).mean()
