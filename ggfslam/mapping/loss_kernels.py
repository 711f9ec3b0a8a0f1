"""Compiled forward and backward of the normal-consistency loss, straight from a rendered depth map.

``normal_loss_from_depth(depth, gt_normals, intr)`` equals ``losses.normal_loss(normals_from_depth(depth), gt)``
(render/normals.py: back-project, central differences, cross product u x v, normalise, face the camera; pixels
on the border or next to a missing depth left out), value and gradient, which tests/test_mapping.py checks.
In torch that chain is ~40 small ops a step and their backward (about 30 ms a step at 640x480); here it is one
pass over the pixels forward and two backward (per-pixel gradients of the two difference vectors, then a gather
into each depth pixel from its four neighbours, so no two threads write the same pixel).
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from ggfslam.render.types import Intrinsics

FMA = {"contract"}


@njit(cache=True, nogil=True, inline="always")
def _ray(u, v, fx, fy, cx, cy):
    return (u - cx) / fx, (v - cy) / fy


@njit(cache=True, nogil=True, parallel=True, fastmath=FMA)
def normal_loss_forward(z, gt, fx, fy, cx, cy, wdu, wdv):
    """Sum of (1 - n . gt) over valid pixels and their count; fills wdu, wdv [H, W, 3] with the gradient of the sum
    w.r.t. each pixel's two difference vectors (zero elsewhere)."""
    H, W = z.shape
    row_sum = np.zeros(H)
    row_cnt = np.zeros(H, np.int64)
    for v in prange(1, H - 1):
        for u in range(1, W - 1):
            wdu[v, u, 0] = wdu[v, u, 1] = wdu[v, u, 2] = 0.0
            wdv[v, u, 0] = wdv[v, u, 1] = wdv[v, u, 2] = 0.0
            z0, zl, zr, zt, zb = z[v, u], z[v, u - 1], z[v, u + 1], z[v - 1, u], z[v + 1, u]
            g0, g1, g2 = gt[v, u, 0], gt[v, u, 1], gt[v, u, 2]
            if not (z0 > 0 and zl > 0 and zr > 0 and zt > 0 and zb > 0) or (g0 == 0 and g1 == 0 and g2 == 0):
                continue
            xr, yr = _ray(u + 1, v, fx, fy, cx, cy)
            xl, yl = _ray(u - 1, v, fx, fy, cx, cy)
            xb, yb = _ray(u, v + 1, fx, fy, cx, cy)
            xt, yt = _ray(u, v - 1, fx, fy, cx, cy)
            a0, a1, a2 = zr * xr - zl * xl, zr * yr - zl * yl, zr - zl  # du
            b0, b1, b2 = zb * xb - zt * xt, zb * yb - zt * yt, zb - zt  # dv
            c0, c1, c2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
            sq = c0 * c0 + c1 * c1 + c2 * c2
            if not sq > 0:
                continue
            nrm = np.sqrt(sq)
            n0, n1, n2 = c0 / nrm, c1 / nrm, c2 / nrm
            x0, y0 = _ray(u, v, fx, fy, cx, cy)
            s = -1.0 if (n0 * x0 + n1 * y0 + n2) * z0 > 0 else 1.0  # face the camera
            dot = s * (n0 * g0 + n1 * g1 + n2 * g2)
            row_sum[v] += 1.0 - dot
            row_cnt[v] += 1
            # d(1 - s n . g)/dc = -s (I - n n^T) g / |c|
            ng = n0 * g0 + n1 * g1 + n2 * g2
            w0, w1, w2 = -s * (g0 - ng * n0) / nrm, -s * (g1 - ng * n1) / nrm, -s * (g2 - ng * n2) / nrm
            # c = a x b: d/da = b x w, d/db = w x a
            wdu[v, u, 0], wdu[v, u, 1], wdu[v, u, 2] = b1 * w2 - b2 * w1, b2 * w0 - b0 * w2, b0 * w1 - b1 * w0
            wdv[v, u, 0], wdv[v, u, 1], wdv[v, u, 2] = w1 * a2 - w2 * a1, w2 * a0 - w0 * a2, w0 * a1 - w1 * a0
    return row_sum.sum(), row_cnt.sum()


@njit(cache=True, nogil=True, parallel=True, fastmath=FMA)
def normal_loss_backward(wdu, wdv, scale, fx, fy, cx, cy, g_z):
    """g_z [H, W] = scale * d(sum)/dz: each pixel gathers from the neighbours whose differences it enters."""
    H, W = g_z.shape
    for v in prange(H):
        for u in range(W):
            x, y = _ray(u, v, fx, fy, cx, cy)
            acc = 0.0
            if u >= 1:  # pixel (u - 1, v) has du = P(u) - P(u - 2)
                acc += wdu[v, u - 1, 0] * x + wdu[v, u - 1, 1] * y + wdu[v, u - 1, 2]
            if u + 1 < W:
                acc -= wdu[v, u + 1, 0] * x + wdu[v, u + 1, 1] * y + wdu[v, u + 1, 2]
            if v >= 1:
                acc += wdv[v - 1, u, 0] * x + wdv[v - 1, u, 1] * y + wdv[v - 1, u, 2]
            if v + 1 < H:
                acc -= wdv[v + 1, u, 0] * x + wdv[v + 1, u, 1] * y + wdv[v + 1, u, 2]
            g_z[v, u] = scale * acc


class _NormalLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, depth, gt, intr):
        z = depth.detach().to(torch.float64).contiguous().numpy()
        g = gt.detach().to(torch.float64).contiguous().numpy()
        H, W = z.shape
        wdu, wdv = np.zeros((H, W, 3)), np.zeros((H, W, 3))
        if H >= 3 and W >= 3:
            total, count = normal_loss_forward(z, g, intr.fx, intr.fy, intr.cx, intr.cy, wdu, wdv)
        else:
            total, count = 0.0, 0
        ctx.save = (wdu, wdv, max(int(count), 1), intr, depth.dtype)
        return torch.tensor(total / max(int(count), 1), dtype=depth.dtype)

    @staticmethod
    def backward(ctx, grad):
        wdu, wdv, count, intr, dtype = ctx.save
        g_z = np.zeros(wdu.shape[:2])
        normal_loss_backward(wdu, wdv, float(grad) / count, intr.fx, intr.fy, intr.cx, intr.cy, g_z)
        return torch.from_numpy(g_z).to(dtype), None, None


def normal_loss_from_depth(depth: torch.Tensor, gt_normals: torch.Tensor, intr: Intrinsics) -> torch.Tensor:
    """Mean (1 - n . gt) over pixels where the normal of ``depth`` [H, W] (render/normals.py's rule) and
    ``gt_normals`` [H, W, 3] are both defined; differentiable in depth."""
    return _NormalLoss.apply(depth, gt_normals, intr)
