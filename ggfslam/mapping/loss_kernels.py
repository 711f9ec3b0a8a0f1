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

from ggfslam.geometry.depth import pixel_differences
from ggfslam.render.types import Intrinsics

FMA = {"contract"}


@njit(cache=True, nogil=True, parallel=True, fastmath=FMA, error_model="numpy")
def normal_loss_forward(z, gt, fx, fy, cx, cy, wdu, wdv):
    """Sum of (1 - n . gt) over valid pixels and their count, for depth z [H, W] and normals gt [3, H, W] (planar);
    fills wdu, wdv [3, H, W + 2] (planar, pixel u at column u + 1, every element written: zero at the padding, the
    border and invalid pixels) with the gradient of the sum w.r.t. each pixel's two difference vectors.
    Branch-free along each row (invalid pixels are masked, not skipped), so the row loop vectorises."""
    H, W = z.shape
    n = W - 2
    row_sum = np.zeros(H)
    row_cnt = np.zeros(H)
    for v in prange(H):
        if v == 0 or v == H - 1:
            for c in range(3):
                wdu[c, v, :] = 0.0
                wdv[c, v, :] = 0.0
            continue
        # row slices (indices computed from u - 1 would be wrapped by numba and read as gathers)
        zc, zl, zr, zt, zb = z[v, 1:W - 1], z[v, 0:W - 2], z[v, 2:W], z[v - 1, 1:W - 1], z[v + 1, 1:W - 1]
        g0s, g1s, g2s = gt[0, v, 1:W - 1], gt[1, v, 1:W - 1], gt[2, v, 1:W - 1]
        u0, u1, u2 = wdu[0, v, 2:W], wdu[1, v, 2:W], wdu[2, v, 2:W]  # pixels 1 .. W - 2
        v0, v1, v2 = wdv[0, v, 2:W], wdv[1, v, 2:W], wdv[2, v, 2:W]
        term = np.empty(n)
        valid = np.empty(n)
        y0 = (v - cy) / fy
        for i in range(n):
            u = i + 1
            # float64 from here on, whatever the inputs' type (float32 inputs give the float64 results exactly)
            z0, g0, g1, g2 = np.float64(zc[i]), np.float64(g0s[i]), np.float64(g1s[i]), np.float64(g2s[i])
            dl, dr, dt, db = np.float64(zl[i]), np.float64(zr[i]), np.float64(zt[i]), np.float64(zb[i])
            a0, a1, a2, b0, b1, b2 = pixel_differences(dl, dr, dt, db, u, v, fx, fy, cx, cy)  # du, dv
            c0, c1, c2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
            sq = c0 * c0 + c1 * c1 + c2 * c2
            ok = (z0 > 0 and dl > 0 and dr > 0 and dt > 0 and db > 0 and sq > 0
                  and not (g0 == 0 and g1 == 0 and g2 == 0))
            nrm = np.sqrt(sq)
            n0, n1, n2 = c0 / nrm, c1 / nrm, c2 / nrm
            x0 = (u - cx) / fx
            s = -1.0 if (n0 * x0 + n1 * y0 + n2) * z0 > 0 else 1.0  # face the camera
            ng = n0 * g0 + n1 * g1 + n2 * g2
            term[i] = 1.0 - s * ng if ok else 0.0
            valid[i] = 1.0 if ok else 0.0
            # d(1 - s n . g)/dc = -s (I - n n^T) g / |c|; c = a x b: d/da = b x w, d/db = w x a
            w0, w1, w2 = -s * (g0 - ng * n0) / nrm, -s * (g1 - ng * n1) / nrm, -s * (g2 - ng * n2) / nrm
            u0[i] = b1 * w2 - b2 * w1 if ok else 0.0
            u1[i] = b2 * w0 - b0 * w2 if ok else 0.0
            u2[i] = b0 * w1 - b1 * w0 if ok else 0.0
            v0[i] = w1 * a2 - w2 * a1 if ok else 0.0
            v1[i] = w2 * a0 - w0 * a2 if ok else 0.0
            v2[i] = w0 * a1 - w1 * a0 if ok else 0.0
        for c in range(3):
            wdu[c, v, 0], wdu[c, v, 1], wdu[c, v, W], wdu[c, v, W + 1] = 0.0, 0.0, 0.0, 0.0
            wdv[c, v, 0], wdv[c, v, 1], wdv[c, v, W], wdv[c, v, W + 1] = 0.0, 0.0, 0.0, 0.0
        acc = 0.0
        cnt = 0.0
        for i in range(n):
            acc += term[i]
            cnt += valid[i]
        row_sum[v] = acc
        row_cnt[v] = cnt
    return row_sum.sum(), row_cnt.sum()


@njit(cache=True, nogil=True, parallel=True, fastmath=FMA, error_model="numpy")
def normal_loss_backward(wdu, wdv, scale, fx, fy, cx, cy, g_z):
    """g_z [H, W] = scale * d(sum)/dz: each pixel gathers from the neighbours whose differences it enters (wdu, wdv
    as ``normal_loss_forward`` wrote them: their zero padding stands in for the neighbours beyond the border)."""
    H, W = g_z.shape
    for v in prange(H):
        y = (v - cy) / fy
        # column u + 1 holds pixel u: pixel u - 1 is column u, pixel u + 1 column u + 2
        ul0, ul1, ul2 = wdu[0, v, 0:W], wdu[1, v, 0:W], wdu[2, v, 0:W]
        ur0, ur1, ur2 = wdu[0, v, 2:W + 2], wdu[1, v, 2:W + 2], wdu[2, v, 2:W + 2]
        # beyond the border the clamped row is the border row itself, which the forward wrote as zeros
        vt = max(np.int64(v) - 1, 0)
        vb = min(np.int64(v) + 1, H - 1)
        vt0, vt1, vt2 = wdv[0, vt, 1:W + 1], wdv[1, vt, 1:W + 1], wdv[2, vt, 1:W + 1]
        vb0, vb1, vb2 = wdv[0, vb, 1:W + 1], wdv[1, vb, 1:W + 1], wdv[2, vb, 1:W + 1]
        out = g_z[v]
        for u in range(W):
            x = (u - cx) / fx
            acc = ul0[u] * x + ul1[u] * y + ul2[u]  # pixel (u - 1, v) has du = P(u) - P(u - 2)
            acc -= ur0[u] * x + ur1[u] * y + ur2[u]
            acc += vt0[u] * x + vt1[u] * y + vt2[u]
            acc -= vb0[u] * x + vb1[u] * y + vb2[u]
            out[u] = scale * acc


class _NormalLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, depth, gt, intr):
        # float32 or float64 as given: the kernel computes in float64 (no float64 copies, ~1 ms a step at 640x480)
        dt = depth.dtype if depth.dtype in (torch.float32, torch.float64) else torch.float64
        z = depth.detach().to(dt).contiguous().numpy()
        g = gt.detach().to(dt).permute(2, 0, 1).contiguous().numpy()  # [3, H, W]
        H, W = z.shape
        wdu, wdv = np.empty((3, H, W + 2)), np.empty((3, H, W + 2))
        if H >= 3 and W >= 3:
            total, count = normal_loss_forward(z, g, intr.fx, intr.fy, intr.cx, intr.cy, wdu, wdv)
        else:
            total, count = 0.0, 0
            wdu[:], wdv[:] = 0.0, 0.0
        ctx.save = (wdu, wdv, max(int(count), 1), intr, depth.dtype)
        return torch.tensor(total / max(int(count), 1), dtype=depth.dtype)

    @staticmethod
    def backward(ctx, grad):
        wdu, wdv, count, intr, dtype = ctx.save
        # written in the depth's type (a float64 sum rounded on the store, as .to(dtype) would)
        g_z = np.empty(wdu.shape[1:2] + (wdu.shape[2] - 2,), np.float32 if dtype == torch.float32 else np.float64)
        normal_loss_backward(wdu, wdv, float(grad) / count, intr.fx, intr.fy, intr.cx, intr.cy, g_z)
        return torch.from_numpy(g_z).to(dtype), None, None


def normal_loss_from_depth(depth: torch.Tensor, gt_normals: torch.Tensor, intr: Intrinsics) -> torch.Tensor:
    """Mean (1 - n . gt) over pixels where the normal of ``depth`` [H, W] (render/normals.py's rule) and
    ``gt_normals`` [H, W, 3] are both defined; differentiable in depth."""
    return _NormalLoss.apply(depth, gt_normals, intr)


# --- photometric loss: (1 - l) L1 + l (1 - SSIM), fused -------------------------------------------------------
# eval/image.py's ssim() is the plain-torch reference of the same math (11x11 Gaussian window, sigma 1.5, 'valid'
# borders, C1 = 0.01^2, C2 = 0.03^2); tests/test_mapping.py checks value and gradient against it. In torch the
# five filtered maps, the SSIM formula and their backward are ~25 ops and ~50 ms a step at 640x480; here one
# separable filter pass each way along contiguous rows, and only the gradient w.r.t. the rendered image is formed.
SSIM_SIZE, SSIM_SIGMA, SSIM_C1, SSIM_C2 = 11, 1.5, 0.01 ** 2, 0.03 ** 2


def _ssim_taps() -> np.ndarray:
    x = np.arange(SSIM_SIZE, dtype=np.float64) - SSIM_SIZE // 2
    g = np.exp(-(x ** 2) / (2 * SSIM_SIGMA ** 2))
    return g / g.sum()  # [11]


@njit(cache=True, nogil=True, parallel=True, fastmath=FMA, error_model="numpy")
def photo_forward(x, y, taps, c1, c2, hz, dS):
    """x (render), y (image) [H, W*C] (rows of interleaved channels): returns (sum |x - y|, sum of the SSIM map over
    the valid [Hv, Wv*C]); hz [5, H, Wv*C] receives the horizontal pass of x, y, xx, yy, xy, and
    dS [3, Hv, Wv*C] dSSIM/d(mu_x, E[xx], E[xy]). Inner loops run along contiguous rows, so they vectorise: numba's
    default ("python") error model tests every division for a zero divisor, which keeps the SSIM loop scalar (its
    denominators hold C1 and C2 > 0)."""
    H, WC = x.shape
    K = taps.shape[0]
    Hv, Q = dS.shape[1], dS.shape[2]
    C = (WC - Q) // (K - 1)
    l1_rows = np.zeros(H)
    for h in prange(H):
        acc = 0.0
        for p in range(WC):
            acc += abs(x[h, p] - y[h, p])
        l1_rows[h] = acc
        k = taps[0]
        for q in range(Q):  # the first tap writes, so hz needs no clearing (4.5 MB at 320x240)
            a, b = x[h, q], y[h, q]
            hz[0, h, q] = k * a
            hz[1, h, q] = k * b
            hz[2, h, q] = k * a * a
            hz[3, h, q] = k * b * b
            hz[4, h, q] = k * a * b
        for t in range(1, K):
            k, off = taps[t], t * C
            # shifted rows as slices: an index q + off could be negative to numba, whose wrap-around test turned
            # these reads into gathers (3x slower)
            xs, ys = x[h, off:off + Q], y[h, off:off + Q]
            for q in range(Q):
                a, b = xs[q], ys[q]
                hz[0, h, q] += k * a
                hz[1, h, q] += k * b
                hz[2, h, q] += k * a * a
                hz[3, h, q] += k * b * b
                hz[4, h, q] += k * a * b
    ssim_rows = np.zeros(Hv)
    for i in prange(Hv):
        z = np.zeros((5, Q), x.dtype)
        ab = np.empty(Q)  # the SSIM map's row, summed after the loop: a running sum would keep the loop scalar
        for t in range(K):
            k = taps[t]
            for f in range(5):
                for q in range(Q):
                    z[f, q] += k * hz[f, i + t, q]
        for q in range(Q):
            m1, m2, e11, e22, e12 = z[0, q], z[1, q], z[2, q], z[3, q], z[4, q]
            an, ad = 2 * m1 * m2 + c1, m1 * m1 + m2 * m2 + c1
            bn, bd = 2 * (e12 - m1 * m2) + c2, (e11 - m1 * m1) + (e22 - m2 * m2) + c2
            A, B = an / ad, bn / bd
            ab[q] = A * B
            dS[0, i, q] = (2 * m2 * ad - an * 2 * m1) / (ad * ad) * B + A * (2 * m1 * bn - 2 * m2 * bd) / (bd * bd)
            dS[1, i, q] = -A * bn / (bd * bd)
            dS[2, i, q] = A * 2 / bd
        acc = 0.0
        for q in range(Q):
            acc += ab[q]
        ssim_rows[i] = acc
    return l1_rows.sum(), ssim_rows.sum()


@njit(cache=True, nogil=True, parallel=True, fastmath=FMA, error_model="numpy")
def photo_backward(x, y, taps, dS, g_l1, g_ssim, vt, g_x):
    """g_x [H, W*C] = g_l1 * sign(x - y) + g_ssim * dSSIM_sum/dx: the filters' adjoints applied to dS (vertical into
    vt [3, H, Wv*C], then horizontal), then the chain through mu_x = f*x, E[xx] = f*x^2, E[xy] = f*xy."""
    H, WC = x.shape
    K = taps.shape[0]
    Hv, Q = dS.shape[1], dS.shape[2]
    C = (WC - Q) // (K - 1)
    for h in prange(H):
        i0 = max(0, h - K + 1)  # every row h < Hv + K - 1 = H has at least one i: its first writes, no clearing
        k = taps[h - i0]
        for f in range(3):
            for q in range(Q):
                vt[f, h, q] = k * dS[f, i0, q]
        for i in range(i0 + 1, min(Hv - 1, h) + 1):
            k = taps[h - i]
            for f in range(3):
                for q in range(Q):
                    vt[f, h, q] += k * dS[f, i, q]
    for h in prange(H):
        G = np.zeros((3, WC), x.dtype)
        for t in range(K):
            k, off = taps[t], t * C
            for f in range(3):
                Gs = G[f, off:off + Q]  # a slice, not G[f, q + off]: see photo_forward
                for q in range(Q):
                    Gs[q] += k * vt[f, h, q]
        for p in range(WC):
            a, b = x[h, p], y[h, p]
            d = a - b
            sgn = 1.0 if d > 0 else (-1.0 if d < 0 else 0.0)
            g_x[h, p] = g_l1 * sgn + g_ssim * (G[0, p] + 2 * a * G[1, p] + b * G[2, p])


_TAPS = _ssim_taps()


class _PhotoLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred, gt, lambda_ssim):
        H, W, C = pred.shape
        x = pred.detach().contiguous().numpy().reshape(H, W * C)
        y = gt.detach().to(pred.dtype).contiguous().numpy().reshape(H, W * C)
        K = SSIM_SIZE
        taps = _TAPS.astype(x.dtype)
        hz = np.empty((5, H, (W - K + 1) * C), x.dtype)
        dS = np.empty((3, H - K + 1, (W - K + 1) * C), x.dtype)
        l1_sum, ssim_sum = photo_forward(x, y, taps, SSIM_C1, SSIM_C2, hz, dS)
        n1, n2 = x.size, dS[0].size
        ctx.save = (x, y, taps, dS, n1, n2, lambda_ssim, pred.shape)
        loss = (1 - lambda_ssim) * l1_sum / n1 + lambda_ssim * (1 - ssim_sum / n2)
        return torch.tensor(loss, dtype=pred.dtype)

    @staticmethod
    def backward(ctx, grad):
        x, y, taps, dS, n1, n2, lam, shape = ctx.save
        g = float(grad)
        vt = np.empty((3, x.shape[0], dS.shape[2]), x.dtype)
        g_x = np.empty_like(x)
        photo_backward(x, y, taps, dS, g * (1 - lam) / n1, -g * lam / n2, vt, g_x)
        return torch.from_numpy(g_x.reshape(shape)), None, None


def photometric_loss_fused(pred: torch.Tensor, gt: torch.Tensor, lambda_ssim: float) -> torch.Tensor:
    """``(1 - l) L1 + l (1 - SSIM)`` of a render ``pred`` [H, W, 3] against ``gt`` [H, W, 3] (both in [0, 1], CPU,
    at least 11x11), compiled; differentiable in ``pred``."""
    return _PhotoLoss.apply(pred, gt, float(lambda_ssim))
