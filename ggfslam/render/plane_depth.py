"""Depth of surfels where each pixel's ray meets their plane (PGSR-style "unbiased" depth), composited with the
renderer's ordinary extra channels.

Every Gaussian carries a plane ``n . X = d`` in the camera frame (OpenCV axes), ``n`` pointing away from the
camera: a surfel its own plane (its normal through its mean), any other Gaussian the fronto-parallel plane
through its mean (``n = e_z``, ``d = z``). The renderer alpha-blends ``(n, d)`` as four extra channels, and a
pixel's depth is ``D / (N . r)`` with ``D``, ``N`` the blended values and ``r = K^-1 [u, v, 1]`` its ray
(z = 1). Over Gaussians that share one plane this is exactly where the ray meets it; over fronto-parallel
planes alone it is the ordinary expected depth ``depth_raw / alpha`` (``N . r = alpha``). The expected depth
gives a whole surfel the depth of its centre, a staircase across tilted surfaces.
"""
from __future__ import annotations

from functools import lru_cache

import torch

from ggfslam.render.types import Intrinsics

PLANE_CHANNELS = 4
"""Extra channels the plane needs: n_x, n_y, n_z, d."""

MIN_COSINE = 0.2
"""Pixels whose blended plane meets the ray at a cosine below this (relative to alpha; grazing, > ~78 deg, or
planes of opposite tilts mixed at an edge) keep the expected depth: ``D / (N . r)`` explodes there."""


def plane_channels(means_c: torch.Tensor, normals_c: torch.Tensor, planar: torch.Tensor) -> torch.Tensor:
    """Per-Gaussian plane [G, 4] = (n, d) from camera-frame means [G, 3], normals [G, 3] (either sign; used where
    ``planar`` [G] bool) and e_z elsewhere. Differentiable in means_c (and normals_c)."""
    n = torch.where((normals_c * means_c.detach()).sum(-1, keepdim=True) < 0, -normals_c, normals_c)
    n = torch.where(planar[:, None], n, torch.tensor([0.0, 0.0, 1.0], dtype=means_c.dtype).expand_as(n))
    return torch.cat([n, (n * means_c).sum(-1, keepdim=True)], 1)


@lru_cache(maxsize=16)  # a few training levels and crops; not modified by callers
def pixel_rays(intr: Intrinsics, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Camera-frame rays [H, W, 3] with z = 1 through every pixel (the renderer's pixel coordinates)."""
    v, u = torch.meshgrid(torch.arange(intr.height, dtype=dtype), torch.arange(intr.width, dtype=dtype),
                          indexing="ij")
    return torch.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, torch.ones_like(u)], -1)


def plane_depth(planes: torch.Tensor, alpha: torch.Tensor, depth: torch.Tensor, intr: Intrinsics,
                min_alpha: float) -> torch.Tensor:
    """Depth [H, W] from the blended plane channels [H, W, 4]; pixels with alpha <= min_alpha get 0 and those
    the plane meets at a grazing angle (``MIN_COSINE``) keep ``depth`` [H, W], the expected depth."""
    den = (planes[..., :3] * pixel_rays(intr, planes.dtype)).sum(-1)  # [H, W] alpha-weighted n . r
    a = alpha.detach()
    ok = (a > min_alpha) & (den.detach() > MIN_COSINE * a)
    z = planes[..., 3] / torch.where(ok, den, torch.ones_like(den))
    return torch.where(ok, z, torch.where(a > min_alpha, depth, torch.zeros_like(depth)))
