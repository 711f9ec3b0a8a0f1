"""Normals from a rendered depth map (paper eq. 9), differentiable torch.

Same rule as ``ggfslam.geometry.depth.normals_from_depth`` (the numpy version used for sensor depth, so
rendered and sensor normals are comparable): back-project every pixel with the intrinsics
(``P = z K^-1 [u, v, 1]``), take central differences ``P(u+1) - P(u-1)`` and ``P(v+1) - P(v-1)``, cross
them (u first), normalise, and flip to face the camera (``n . P < 0``). Camera frame, OpenCV axes.
Pixels on the image border or with a missing (0) depth among themselves and their four neighbours get
(0, 0, 0). Gradients are finite everywhere (the norm has a tiny floor, masked pixels get zero gradient).
"""
from __future__ import annotations

import torch


def backproject_depth(depth: torch.Tensor, fx: float, fy: float, cx: float, cy: float) -> torch.Tensor:
    """Camera-frame points [H, W, 3] from a depth map [H, W]."""
    H, W = depth.shape
    v, u = torch.meshgrid(torch.arange(H, dtype=depth.dtype, device=depth.device),
                          torch.arange(W, dtype=depth.dtype, device=depth.device), indexing="ij")
    return torch.stack([(u - cx) / fx * depth, (v - cy) / fy * depth, depth], dim=-1)


def normals_from_depth(depth: torch.Tensor, fx: float, fy: float, cx: float, cy: float) -> torch.Tensor:
    """Unit normals [H, W, 3] facing the camera from a depth map [H, W] (0 = no depth)."""
    H, W = depth.shape
    out = torch.zeros(H, W, 3, dtype=depth.dtype, device=depth.device)
    if H < 3 or W < 3:
        return out
    P = backproject_depth(depth, fx, fy, cx, cy)
    du = P[1:-1, 2:] - P[1:-1, :-2]  # [H-2, W-2, 3]
    dv = P[2:, 1:-1] - P[:-2, 1:-1]
    c = torch.cross(du, dv, dim=-1)
    sq = (c * c).sum(-1, keepdim=True)
    valid = depth.detach() > 0
    ok = (valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1] & valid[1:-1, 1:-1]
          & (sq.detach()[..., 0] > 0))
    n = c / torch.sqrt(sq.clamp_min(1e-30))
    sign = torch.where((n.detach() * P[1:-1, 1:-1].detach()).sum(-1, keepdim=True) > 0, -1.0, 1.0).to(n.dtype)
    n = torch.where(ok[..., None], n * sign, torch.zeros_like(n))
    return torch.nn.functional.pad(n.permute(2, 0, 1), (1, 1, 1, 1)).permute(1, 2, 0)
