"""Compiled forward and backward of the mapping step's pointwise terms: depth L1, the opacity entropy and the
children's mean volume (``losses.depth_loss``, ``losses.opacity_entropy``, ``losses.scale_volume`` dispatch here
on the CPU; their plain-torch forms, kept beside them as ``*_reference``, are what tests/test_mapping.py checks
values and gradients against, with finite differences too).

Each is one pass forward (sums per fixed chunk in float64, then the chunks in order: the value does not depend on
the number of threads) and one backward pass. In torch they were ~25 small operations on [H, W] and [G] tensors
forward and backward, ~1.5 ms of a mapping step at 320x240 with 100k children.
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

CHUNK = 4096  # elements per partial sum


def _chunks(n: int) -> int:
    return max(1, (n + CHUNK - 1) // CHUNK)


@njit(cache=True, nogil=True, parallel=True)
def _depth_l1_forward(pred, gt, sign, part):
    """part[c] = (sum |pred - gt|, count) over chunk c's pixels with gt > 0; sign = d|pred - gt|/dpred there
    (0 elsewhere, and where pred == gt, as torch's abs)."""
    n = pred.shape[0]
    for c in prange(part.shape[0]):
        s = 0.0
        cnt = 0.0
        for i in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            d = np.float64(pred[i]) - np.float64(gt[i])
            if gt[i] > 0:
                s += abs(d)
                cnt += 1.0
                sign[i] = 1.0 if d > 0 else (-1.0 if d < 0 else 0.0)
            else:
                sign[i] = 0.0
        part[c, 0] = s
        part[c, 1] = cnt


@njit(cache=True, nogil=True, parallel=True)
def _entropy_forward(o, eps, dh, part):
    """part[c] = sum over chunk c of the binary entropy of clamp(o, eps, 1 - eps); dh = its derivative
    ln((1 - o) / o) where the clamp passes o (torch's clamp: at and inside the bounds), 0 outside."""
    n = o.shape[0]
    for c in prange(part.shape[0]):
        s = 0.0
        for i in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            x = np.float64(o[i])
            inside = (x >= eps) & (x <= 1.0 - eps)
            x = min(max(x, eps), 1.0 - eps)
            lo, l1 = np.log(x), np.log1p(-x)
            s -= x * lo + (1.0 - x) * l1
            dh[i] = l1 - lo if inside else 0.0
        part[c] = s


@njit(cache=True, nogil=True, parallel=True)
def _volume_forward(s, part):
    """part[c] = sum over chunk c's rows of s0 s1 s2 (scales [G, 3])."""
    n = s.shape[0]
    for c in prange(part.shape[0]):
        acc = 0.0
        for i in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            acc += np.float64(s[i, 0]) * np.float64(s[i, 1]) * np.float64(s[i, 2])
        part[c] = acc


@njit(cache=True, nogil=True, parallel=True)
def _volume_backward(s, scale, g):
    """g[i] = scale * (s1 s2, s0 s2, s0 s1) of row i."""
    for i in prange(s.shape[0]):
        a, b, c = np.float64(s[i, 0]), np.float64(s[i, 1]), np.float64(s[i, 2])
        g[i, 0] = scale * b * c
        g[i, 1] = scale * a * c
        g[i, 2] = scale * a * b


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class _WithGradient(torch.autograd.Function):
    """A scalar ``value`` of x whose gradient ``scale * d`` (d [x.shape], numpy) was formed with it."""

    @staticmethod
    def forward(ctx, x, value, d, scale):
        ctx.save = (d, scale)
        return torch.tensor(value, dtype=x.dtype)

    @staticmethod
    def backward(ctx, grad):
        d, scale = ctx.save
        return torch.from_numpy(d) * (grad * scale), None, None, None


def _depth_l1(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    p, q = _np(pred).reshape(-1), _np(gt.to(pred.dtype)).reshape(-1)
    sign = np.empty(p.shape[0], p.dtype)
    part = np.empty((_chunks(p.shape[0]), 2))
    _depth_l1_forward(p, q, sign, part)
    total, count = part.sum(axis=0)
    count = max(count, 1.0)
    return _WithGradient.apply(pred, total / count, sign.reshape(pred.shape), 1.0 / count)


def _opacity_entropy(opacity: torch.Tensor, eps: float) -> torch.Tensor:
    o = _np(opacity).reshape(-1)
    dh = np.empty(o.shape[0], o.dtype)
    part = np.empty(_chunks(o.shape[0]))
    _entropy_forward(o, float(eps), dh, part)
    n = max(o.shape[0], 1)
    return _WithGradient.apply(opacity, part.sum() / n, dh.reshape(opacity.shape), 1.0 / n)


class _ScaleVolume(torch.autograd.Function):
    @staticmethod
    def forward(ctx, scales):
        s = _np(scales)
        part = np.empty(_chunks(s.shape[0]))
        _volume_forward(s, part)
        ctx.save = s
        return torch.tensor(part.sum() / max(s.shape[0], 1), dtype=scales.dtype)

    @staticmethod
    def backward(ctx, grad):
        s = ctx.save
        g = np.empty_like(s)
        _volume_backward(s, float(grad) / max(s.shape[0], 1), g)
        return torch.from_numpy(g)


def fused_ok(*tensors: torch.Tensor) -> bool:
    """Whether the compiled kernels take these tensors (CPU, float32 or float64, one dtype)."""
    return all(t.device.type == "cpu" and t.dtype == tensors[0].dtype for t in tensors) and tensors[0].dtype in (
        torch.float32, torch.float64)


def depth_l1_fused(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Mean |pred - gt| over the pixels with gt > 0 (depth maps [H, W]); differentiable in pred."""
    if pred.shape != gt.shape:
        raise ValueError(f"depth_loss: prediction {tuple(pred.shape)} and sensor depth {tuple(gt.shape)} differ")
    return _depth_l1(pred, gt)


def opacity_entropy_fused(opacity: torch.Tensor, eps: float) -> torch.Tensor:
    """Mean binary entropy of clamp(opacity [G], eps, 1 - eps); differentiable in opacity."""
    return _opacity_entropy(opacity, eps)


def scale_volume_fused(scales: torch.Tensor) -> torch.Tensor:
    """Mean over rows of s0 s1 s2 (scales [G, 3]); differentiable in scales."""
    return _ScaleVolume.apply(scales)
