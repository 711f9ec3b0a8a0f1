"""L_morph on the decoder's raw output in one compiled forward and backward (``morph_loss_raw``).

Same math as ``ggf.amr.morph_loss`` (the plain-torch reference; tests/test_ggf.py checks values and gradients
against it), for S sampled children read straight from the covariance MLP's output: child (m, j) has rotation
``q = raw_cov[m, j, 3:7]`` (w, x, y, z, normalised here) and scales ``s = exp(log_scale[m]) * sigmoid(raw_cov[m, j,
:3])``. With a the index of its smallest scale and e_a that local axis,
``L = mean(lambda_dir (1 - |n . R(q) e_a|) + lambda_thin max(0, s_a - eps) / unit)``.
For a unit quaternion (w, u): ``n . R e = n.e + 2 w u.(e x n) + 2 (u.n)(u.e) - 2 (n.e) |u|^2``, whose gradient is
``d/dw = 2 u.(e x n)``, ``d/du = 2 w (e x n) + 2 n (u.e) + 2 (u.n) e - 4 (n.e) u``.
In torch the gather, the rotation matrix and the column pick were ~60 small ops and their backward ~40 nodes:
3.7 ms of a mapping step at 100k children (8192 sampled); here ~0.5 ms forward and backward, ~0.8 ms with the
sample's selection.
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange


@njit(cache=True, nogil=True, inline="always")
def _child(raw_cov, log_scale, m, j, n0, n1, n2):
    """(v = n . R(q) e_a, the gradient of v wrt the unit quaternion (w, x, y, z), |q|, the unit q, the axis a,
    s_a, and sigmoid of raw_cov at a) of child (m, j)."""
    best = 0
    sb = np.inf
    sig_b = 0.0
    for c in range(3):
        sg = 1.0 / (1.0 + np.exp(-np.float64(raw_cov[m, j, c])))
        s = np.exp(np.float64(log_scale[m, c])) * sg
        if s < sb:  # first minimum, as torch.argmin
            best, sb, sig_b = c, s, sg
    w, x, y, z = (np.float64(raw_cov[m, j, 3]), np.float64(raw_cov[m, j, 4]), np.float64(raw_cov[m, j, 5]),
                  np.float64(raw_cov[m, j, 6]))
    qn = max(np.sqrt(w * w + x * x + y * y + z * z), 1e-12)
    w, x, y, z = w / qn, x / qn, y / qn, z / qn
    # e = e_a; c = e x n; ue = u . e; ne = n . e
    if best == 0:
        c0, c1, c2, ue, ne = 0.0, -n2, n1, x, n0
    elif best == 1:
        c0, c1, c2, ue, ne = n2, 0.0, -n0, y, n1
    else:
        c0, c1, c2, ue, ne = -n1, n0, 0.0, z, n2
    uc = x * c0 + y * c1 + z * c2
    un = x * n0 + y * n1 + z * n2
    uu = x * x + y * y + z * z
    v = ne + 2.0 * w * uc + 2.0 * un * ue - 2.0 * ne * uu
    gw = 2.0 * uc
    gx = 2.0 * w * c0 + 2.0 * n0 * ue - 4.0 * ne * x
    gy = 2.0 * w * c1 + 2.0 * n1 * ue - 4.0 * ne * y
    gz = 2.0 * w * c2 + 2.0 * n2 * ue - 4.0 * ne * z
    if best == 0:
        gx += 2.0 * un
    elif best == 1:
        gy += 2.0 * un
    else:
        gz += 2.0 * un
    return v, gw, gx, gy, gz, qn, w, x, y, z, best, sb, sig_b


@njit(cache=True, nogil=True, parallel=True)
def _morph_forward(raw_cov, log_scale, m_idx, j_idx, normals, eps, unit, lam_dir, lam_thin, terms, grads, axis):
    """Per child i: its term ``lambda_dir (1 - |v|) + lambda_thin max(0, s_a - eps) / unit`` (terms [S], float64),
    the term's gradient wrt raw_cov[m, j, :7] and log_scale[m, a] (grads [S, 8]) and its axis a (axis [S])."""
    for i in prange(m_idx.shape[0]):
        v, gw, gx, gy, gz, qn, w, x, y, z, a, sa, sig = _child(raw_cov, log_scale, m_idx[i], j_idx[i], np.float64(
            normals[i, 0]), np.float64(normals[i, 1]), np.float64(normals[i, 2]))
        terms[i] = lam_dir * (1.0 - abs(v)) + lam_thin * max(sa - eps, 0.0) / unit
        gv = -lam_dir * (1.0 if v > 0.0 else (-1.0 if v < 0.0 else 0.0))  # d|v| = sign(v), 0 at 0 (torch)
        gw, gx, gy, gz = gv * gw, gv * gx, gv * gy, gv * gz
        dot = gw * w + gx * x + gy * y + gz * z  # through q / |q|: (I - q q^T) / |q|
        grads[i, 0] = 0.0
        grads[i, 1] = 0.0
        grads[i, 2] = 0.0
        grads[i, 3] = (gw - dot * w) / qn
        grads[i, 4] = (gx - dot * x) / qn
        grads[i, 5] = (gy - dot * y) / qn
        grads[i, 6] = (gz - dot * z) / qn
        grads[i, 7] = 0.0
        if sa - eps > 0.0:  # relu's gradient, 0 at 0 (torch)
            gs = lam_thin / unit
            grads[i, a] = gs * sa * (1.0 - sig)  # s = L sigmoid(r): ds/dr = s (1 - sigmoid(r))
            grads[i, 7] = gs * sa  # ds/dlog L = s
        axis[i] = a


@njit(cache=True, nogil=True)
def _morph_backward(m_idx, j_idx, grads, axis, g, g_cov, g_ls):
    """Scatter g times the children's gradients into g_cov [M, k, 7] and g_ls [M, 3] (serial: children share
    anchors, and the sums keep one order)."""
    for i in range(m_idx.shape[0]):
        m, j = m_idx[i], j_idx[i]
        for c in range(7):
            g_cov[m, j, c] += g * grads[i, c]
        g_ls[m, axis[i]] += g * grads[i, 7]


class _MorphLossRaw(torch.autograd.Function):
    @staticmethod
    def forward(ctx, raw_cov, log_scale, m_idx, j_idx, normals, eps, unit, lam_dir, lam_thin):
        dt = torch.float64 if raw_cov.dtype == torch.float64 else torch.float32
        rc, ls = raw_cov.detach().to(dt).contiguous().numpy(), log_scale.detach().to(dt).contiguous().numpy()
        mi, ji = m_idx.to(torch.int64).contiguous().numpy(), j_idx.to(torch.int64).contiguous().numpy()
        s = len(mi)
        terms, grads, axis = np.empty(s), np.empty((s, 8)), np.empty(s, np.int64)
        _morph_forward(rc, ls, mi, ji, normals.detach().to(torch.float64).contiguous().numpy(), float(eps),
                       float(unit), float(lam_dir), float(lam_thin), terms, grads, axis)
        ctx.np = (mi, ji, grads, axis, rc.shape, ls.shape, rc.dtype)
        return torch.tensor(terms.sum() / s, dtype=raw_cov.dtype)

    @staticmethod
    def backward(ctx, g):
        mi, ji, grads, axis, cov_shape, ls_shape, dt = ctx.np
        g_cov, g_ls = np.zeros(cov_shape, dt), np.zeros(ls_shape, dt)
        _morph_backward(mi, ji, grads, axis, float(g) / len(mi), g_cov, g_ls)
        return torch.from_numpy(g_cov), torch.from_numpy(g_ls), None, None, None, None, None, None, None


def morph_loss_raw(raw_cov: torch.Tensor, log_scale: torch.Tensor, m_idx: torch.Tensor, j_idx: torch.Tensor,
                   normals: torch.Tensor, eps: float, unit: float, lambda_dir: float = 1.0,
                   lambda_thin: float = 1.0) -> torch.Tensor:
    """``amr.morph_loss`` of children (m_idx [S], j_idx [S]) of the covariance MLP's output raw_cov [M, k, 7] with
    their anchors' log_scale [M, 3] and normals [S, 3]; differentiable in raw_cov and log_scale."""
    if len(m_idx) == 0:
        return raw_cov.sum() * 0.0
    return _MorphLossRaw.apply(raw_cov, log_scale, m_idx, j_idx, normals, eps, unit, lambda_dir, lambda_thin)
