"""The child head: from the decoder MLPs' raw outputs to the explicit children, with AMR, in one compiled step.

What it computes (per child j of anchor m; the plain-torch reference is ``ChildDecoder.reference`` followed by
``ggf.amr.surfel_shape``, and tests/test_child_head.py checks the two agree in values and gradients):
- opacity ``o = tanh(raw_o)``; the child is kept only where ``o > 0`` (Scaffold-GS's mask, i.e. ``raw_o > 0``);
- colour ``max(0, sigmoid(raw_c[0] + base_color[m, j]) + sum_b Y_b(d) raw_c[b])``: real spherical harmonics of the
  direction d from the camera centre to the child (degree 0-3, 3DGS's basis), i.e. exactly what a 3DGS
  renderer computes from ``f_dc = (sigmoid(.) - 0.5) / C0`` and ``f_rest = raw_c[1:]`` (gaussians/bake.py);
- scale ``s = exp(log_scale[m]) * sigmoid(raw_cov[:3])``, rotation ``q = raw_cov[3:7]`` (w, x, y, z; the
  renderer normalises it), mean ``anchor[m] + offsets[m, j] * exp(log_scale[m])``;
- AMR on the children of planar anchors (ggf/amr.py): ``q' = c0 align + c1 (align * k)`` with ``c`` the unit
  (w, z) part of ``q`` (with ``orient`` off, ``q`` as the decoder made it: its own local z axis is the normal),
  scales ``(max(s_x, r), max(s_y, r), eps)``, and with ``snap`` the mean moved along the normal onto the
  anchor's plane.
The autograd graph of the same math in torch (tanh, sigmoid, exp, products, a cat + index_select gather of the
kept children, AMR's selects) cost ~40 ms of a 130 ms mapping step at 100k children; here it is one forward
and one backward kernel (parallel over anchors, no atomics: an anchor's children are handled by one thread, so
its per-anchor gradient sums need no reduction across threads). The MLPs stay torch matmuls, in one autograd
node of their own (decoder_mlps.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from numba import njit, prange

FMA = {"contract"}


@dataclass
class SurfelSpec:
    """AMR's inputs for M decoded anchors (from the Geometric-Gaussian Field)."""

    planar: torch.Tensor  # [M] bool: children become surfels
    normals: torch.Tensor  # [M, 3] unit normals (world)
    align: torch.Tensor  # [M, 4] w, x, y, z rotation taking the z axis onto the normal
    surface: torch.Tensor  # [M, 3] a point on the anchor's plane (world)
    radius: torch.Tensor  # [M] smallest tangential radius
    eps: float  # surfel thickness
    snap: bool  # move means onto the plane (only with orient, as ``ggf.amr.surfel_shape``)
    orient: bool = True  # turn the surfels onto the normals (else they keep the decoder's rotation)


@njit(cache=True, nogil=True, inline="always")
def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


@njit(cache=True, nogil=True, inline="always")
def _tanh_pos(x):
    """tanh of x > 0 as (1 - e) / (1 + e), e = exp(-2 x), in float64 (4x cheaper than libm's float32 tanh; at
    float32 precision the same value): the cancellation in 1 - e costs 1e-16 absolute, so libm's tanh below 1e-4."""
    if x < 1e-4:
        return np.float64(np.tanh(x))
    e = np.exp(-2.0 * np.float64(x))
    return (1.0 - e) / (1.0 + e)


SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)
CHUNK = 64  # anchors per work item (each gets one scratch buffer for the SH basis)


@njit(cache=True, nogil=True, inline="always")
def _sh_basis(deg, x, y, z, Y):
    """Real SH basis of the unit direction (x, y, z) up to ``deg`` into Y[0 : (deg + 1)^2] (3DGS order and signs)."""
    Y[0] = SH_C0
    if deg >= 1:
        Y[1], Y[2], Y[3] = -SH_C1 * y, SH_C1 * z, -SH_C1 * x
    if deg >= 2:
        xx, yy, zz = x * x, y * y, z * z
        Y[4], Y[5], Y[6] = SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2.0 * zz - xx - yy)
        Y[7], Y[8] = SH_C2[3] * x * z, SH_C2[4] * (xx - yy)
        if deg >= 3:
            Y[9], Y[10] = SH_C3[0] * y * (3.0 * xx - yy), SH_C3[1] * x * y * z
            Y[11], Y[12] = SH_C3[2] * y * (4.0 * zz - xx - yy), SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
            Y[13], Y[14], Y[15] = SH_C3[4] * x * (4.0 * zz - xx - yy), SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3.0 * yy)


@njit(cache=True, nogil=True, inline="always")
def _sh_grad(deg, x, y, z, G):
    """sum_b G[b] grad Y_b at the unit direction (x, y, z) (the derivative of ``_sh_basis``, b >= 1)."""
    gx, gy, gz = -SH_C1 * G[3], -SH_C1 * G[1], SH_C1 * G[2]
    if deg >= 2:
        gx += SH_C2[0] * y * G[4] - 2.0 * SH_C2[2] * x * G[6] + SH_C2[3] * z * G[7] + 2.0 * SH_C2[4] * x * G[8]
        gy += SH_C2[0] * x * G[4] + SH_C2[1] * z * G[5] - 2.0 * SH_C2[2] * y * G[6] - 2.0 * SH_C2[4] * y * G[8]
        gz += SH_C2[1] * y * G[5] + 4.0 * SH_C2[2] * z * G[6] + SH_C2[3] * x * G[7]
        if deg >= 3:
            xx, yy, zz = x * x, y * y, z * z
            gx += (6.0 * SH_C3[0] * x * y * G[9] + SH_C3[1] * y * z * G[10] - 2.0 * SH_C3[2] * x * y * G[11]
                   - 6.0 * SH_C3[3] * x * z * G[12] + SH_C3[4] * (4.0 * zz - 3.0 * xx - yy) * G[13]
                   + 2.0 * SH_C3[5] * x * z * G[14] + SH_C3[6] * (3.0 * xx - 3.0 * yy) * G[15])
            gy += (SH_C3[0] * (3.0 * xx - 3.0 * yy) * G[9] + SH_C3[1] * x * z * G[10]
                   + SH_C3[2] * (4.0 * zz - xx - 3.0 * yy) * G[11] - 6.0 * SH_C3[3] * y * z * G[12]
                   - 2.0 * SH_C3[4] * x * y * G[13] - 2.0 * SH_C3[5] * y * z * G[14] - 6.0 * SH_C3[6] * x * y * G[15])
            gz += (SH_C3[1] * x * y * G[10] + 8.0 * SH_C3[2] * y * z * G[11]
                   + SH_C3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy) * G[12] + 8.0 * SH_C3[4] * x * z * G[13]
                   + SH_C3[5] * (xx - yy) * G[14])
    return gx, gy, gz


@njit(cache=True, nogil=True, inline="always")
def _view_basis(deg, mx, my, mz, cam, Y):
    """SH basis of the direction from the camera centre to a child at (mx, my, mz); returns the unit direction
    and the distance."""
    if deg == 0:
        Y[0] = SH_C0
        return 0.0, 0.0, 1.0, 1.0
    dx, dy, dz = mx - cam[0], my - cam[1], mz - cam[2]
    n = np.sqrt(dx * dx + dy * dy + dz * dz)
    if n > 0.0:
        dx, dy, dz = dx / n, dy / n, dz / n
    _sh_basis(deg, dx, dy, dz, Y)
    return dx, dy, dz, n


@njit(cache=True, nogil=True, inline="always")
def _child_geometry(m, a, j, raw_cov, anchors, offsets, L0, L1, L2, pl, align, surface, normals, radius, eps, snap,
                    orient):
    """Mean, rotation and scales of child j of decoded anchor m (row a of the per-anchor arrays; after AMR when
    ``pl``), then the three scale sigmoids."""
    sg0, sg1, sg2 = _sigmoid(raw_cov[m, j, 0]), _sigmoid(raw_cov[m, j, 1]), _sigmoid(raw_cov[m, j, 2])
    s0 = L0 * sg0
    s1 = L1 * sg1
    s2 = L2 * sg2
    mx = anchors[a, 0] + offsets[a, j, 0] * L0
    my = anchors[a, 1] + offsets[a, j, 1] * L1
    mz = anchors[a, 2] + offsets[a, j, 2] * L2
    qw, qx, qy, qz = raw_cov[m, j, 3], raw_cov[m, j, 4], raw_cov[m, j, 5], raw_cov[m, j, 6]
    if pl:
        if orient:
            nrm = np.sqrt(qw * qw + qz * qz)
            c0, c1 = 1.0, 0.0
            if nrm > 1e-8:
                c0, c1 = qw / nrm, qz / nrm
            aw, ax, ay, az = align[m, 0], align[m, 1], align[m, 2], align[m, 3]
            # align * (c0 + c1 k); align * k = (-az, ay, -ax, aw)
            qw, qx, qy, qz = c0 * aw - c1 * az, c0 * ax + c1 * ay, c0 * ay - c1 * ax, c0 * az + c1 * aw
        r = radius[m]
        s0 = s0 if s0 >= r else r
        s1 = s1 if s1 >= r else r
        s2 = eps
        if snap:
            nx, ny, nz = normals[m, 0], normals[m, 1], normals[m, 2]
            d = (mx - surface[m, 0]) * nx + (my - surface[m, 1]) * ny + (mz - surface[m, 2]) * nz
            mx, my, mz = mx - d * nx, my - d * ny, mz - d * nz
    return mx, my, mz, qw, qx, qy, qz, s0, s1, s2, sg0, sg1, sg2


@njit(cache=True, nogil=True, parallel=True, fastmath=FMA)
def head_forward(raw_o, raw_c, raw_cov, anchors, log_scale, offsets, base_color, anchor_index, planar, normals,
                 align, surface, radius, eps, snap, orient, cam, sh_deg, start, out_means, out_quats, out_scales,
                 out_opac, out_col, out_child, out_anchor, out_local, keep, keep_o):
    """Kept children of M decoded anchors into the compact outputs (anchor m's go to rows start[m]...). Anchor m
    reads row anchor_index[m] of anchors, log_scale, offsets and base_color (the map's whole arrays: no gather
    before the call, no scatter of their gradients after it); the raw MLP outputs and the surfel arrays are per
    decoded anchor. For the backward,
    ``keep`` [G, 9] float64 holds each child's mean, scale sigmoids and colour sigmoids and ``keep_o`` [G] (raw_o's
    dtype) its opacity, exactly as computed here (exps and tanh: recomputing them there was about half of its
    time; each in the type the backward computed it in, so it sees the very values it used to recompute)."""
    m_total, k = raw_o.shape
    nb = (sh_deg + 1) * (sh_deg + 1)
    for ch in prange((m_total + CHUNK - 1) // CHUNK):
        Y = np.empty(16)
        for m in range(ch * CHUNK, min(m_total, (ch + 1) * CHUNK)):
            row = start[m]
            a = anchor_index[m]
            L0, L1, L2 = np.exp(log_scale[a, 0]), np.exp(log_scale[a, 1]), np.exp(log_scale[a, 2])
            pl = planar[m] != 0
            for j in range(k):
                if not raw_o[m, j] > 0.0:
                    continue
                o = _tanh_pos(raw_o[m, j])
                out_opac[row] = o
                keep_o[row] = o
                mx, my, mz, qw, qx, qy, qz, s0, s1, s2, sg0, sg1, sg2 = _child_geometry(
                    m, a, j, raw_cov, anchors, offsets, L0, L1, L2, pl, align, surface, normals, radius, eps, snap,
                    orient)
                _view_basis(sh_deg, mx, my, mz, cam, Y)
                for c in range(3):
                    v = _sigmoid(raw_c[m, j, c] + base_color[a, j, c])
                    keep[row, 6 + c] = v
                    for b in range(1, nb):
                        v += Y[b] * raw_c[m, j, 3 * b + c]
                    out_col[row, c] = v if v > 0.0 else 0.0  # 3DGS clamps SH colour at 0
                out_means[row, 0], out_means[row, 1], out_means[row, 2] = mx, my, mz
                keep[row, 0], keep[row, 1], keep[row, 2] = mx, my, mz
                out_quats[row, 0], out_quats[row, 1], out_quats[row, 2], out_quats[row, 3] = qw, qx, qy, qz
                out_scales[row, 0], out_scales[row, 1], out_scales[row, 2] = s0, s1, s2
                out_child[row] = a * k + j
                out_anchor[row] = a
                out_local[row] = m
                keep[row, 3], keep[row, 4], keep[row, 5] = sg0, sg1, sg2
                row += 1


@njit(cache=True, nogil=True, parallel=True, fastmath=FMA)
def head_backward(raw_o, raw_c, raw_cov, offsets, log_scale, anchor_index, planar, normals, align, radius, snap,
                  orient, cam, sh_deg, start, keep, keep_o, g_means, g_quats, g_scales, g_opac, g_col, gr_o, gr_c,
                  gr_cov, g_offsets, g_log_scale, g_base):
    """Gradients of the raw MLP outputs (per decoded anchor) and of the offsets, log scales and base colours (rows
    anchor_index[m] of the map's arrays, as ``head_forward`` read them; distinct rows, so no two threads write one)
    from those of the kept children. Every element of the raw outputs' gradients is written (children that were not
    kept get zero, so the caller need not clear them, which was ~2.5 ms of a step at 100k children); g_offsets,
    g_log_scale and g_base must come in as zeros: only the kept children's entries and the decoded anchors' log
    scales are written (the arrays cover the whole map, whose other rows stay zero anyway). The SH
    colour's direction is differentiated too (through the child's mean, as 3DGS does). The forward's means,
    opacities and sigmoids are read back from ``keep`` and ``keep_o`` (``head_forward``), not recomputed."""
    m_total, k = raw_o.shape
    nb = (sh_deg + 1) * (sh_deg + 1)
    nrc = gr_c.shape[2]
    for ch in prange((m_total + CHUNK - 1) // CHUNK):
        Y = np.empty(16)
        GY = np.zeros(16)
        for m in range(ch * CHUNK, min(m_total, (ch + 1) * CHUNK)):
            row = start[m]
            a = anchor_index[m]
            L0, L1, L2 = np.exp(log_scale[a, 0]), np.exp(log_scale[a, 1]), np.exp(log_scale[a, 2])
            pl = planar[m] != 0
            gl0 = gl1 = gl2 = 0.0
            for j in range(k):
                if not raw_o[m, j] > 0.0:
                    gr_o[m, j] = 0.0
                    for c in range(nrc):
                        gr_c[m, j, c] = 0.0
                    for c in range(7):
                        gr_cov[m, j, c] = 0.0
                    continue  # its offsets' and base colour's gradients stay the caller's zeros
                for c in range(3 * nb, nrc):  # coefficients beyond the degree in use
                    gr_c[m, j, c] = 0.0
                o = keep_o[row]
                gr_o[m, j] = g_opac[row] * (1.0 - o * o)
                dx = dy = dz = 0.0
                dist = 1.0
                if sh_deg > 0:
                    dx, dy, dz, dist = _view_basis(sh_deg, keep[row, 0], keep[row, 1], keep[row, 2], cam, Y)
                    for b in range(nb):
                        GY[b] = 0.0
                for c in range(3):
                    d0 = keep[row, 6 + c]
                    v = d0
                    for b in range(1, nb):
                        v += Y[b] * raw_c[m, j, 3 * b + c]
                    gc = g_col[row, c] if v > 0.0 else 0.0
                    g = gc * d0 * (1.0 - d0)
                    gr_c[m, j, c] = g
                    for b in range(1, nb):
                        gr_c[m, j, 3 * b + c] = gc * Y[b]
                        GY[b] += gc * raw_c[m, j, 3 * b + c]
                    g_base[a, j, c] = g
                gs0, gs1, gs2 = g_scales[row, 0], g_scales[row, 1], g_scales[row, 2]
                gm0, gm1, gm2 = g_means[row, 0], g_means[row, 1], g_means[row, 2]
                if sh_deg > 0 and dist > 0.0:  # d = (mu - cam) / |mu - cam|: (I - d d^T) / |.| grad_d
                    gx, gy, gz = _sh_grad(sh_deg, dx, dy, dz, GY)
                    dot = gx * dx + gy * dy + gz * dz
                    gm0 += (gx - dot * dx) / dist
                    gm1 += (gy - dot * dy) / dist
                    gm2 += (gz - dot * dz) / dist
                gq0, gq1, gq2, gq3 = g_quats[row, 0], g_quats[row, 1], g_quats[row, 2], g_quats[row, 3]
                sig0, sig1, sig2 = keep[row, 3], keep[row, 4], keep[row, 5]
                if pl and orient:
                    qw, qz = raw_cov[m, j, 3], raw_cov[m, j, 6]
                    nrm = np.sqrt(qw * qw + qz * qz)
                    aw, ax, ay, az = align[m, 0], align[m, 1], align[m, 2], align[m, 3]
                    if nrm > 1e-8:
                        c0, c1 = qw / nrm, qz / nrm
                        ga = gq0 * aw + gq1 * ax + gq2 * ay + gq3 * az  # g_q . align
                        gk = -gq0 * az + gq1 * ay - gq2 * ax + gq3 * aw  # g_q . (align * k)
                        dot = ga * c0 + gk * c1
                        gq0, gq1, gq2, gq3 = (ga - dot * c0) / nrm, 0.0, 0.0, (gk - dot * c1) / nrm
                    else:  # c is the constant (1, 0) there
                        gq0 = gq1 = gq2 = gq3 = 0.0
                if pl:
                    r = radius[m]
                    if not L0 * sig0 >= r:
                        gs0 = 0.0
                    if not L1 * sig1 >= r:
                        gs1 = 0.0
                    gs2 = 0.0
                    if snap:
                        nx, ny, nz = normals[m, 0], normals[m, 1], normals[m, 2]
                        d = gm0 * nx + gm1 * ny + gm2 * nz
                        gm0, gm1, gm2 = gm0 - d * nx, gm1 - d * ny, gm2 - d * nz
                gr_cov[m, j, 0] = gs0 * L0 * sig0 * (1.0 - sig0)
                gr_cov[m, j, 1] = gs1 * L1 * sig1 * (1.0 - sig1)
                gr_cov[m, j, 2] = gs2 * L2 * sig2 * (1.0 - sig2)
                gr_cov[m, j, 3], gr_cov[m, j, 4], gr_cov[m, j, 5], gr_cov[m, j, 6] = gq0, gq1, gq2, gq3
                g_offsets[a, j, 0] = gm0 * L0
                g_offsets[a, j, 1] = gm1 * L1
                g_offsets[a, j, 2] = gm2 * L2
                gl0 += gs0 * L0 * sig0 + gm0 * offsets[a, j, 0] * L0
                gl1 += gs1 * L1 * sig1 + gm1 * offsets[a, j, 1] * L1
                gl2 += gs2 * L2 * sig2 + gm2 * offsets[a, j, 2] * L2
                row += 1
            g_log_scale[a, 0], g_log_scale[a, 1], g_log_scale[a, 2] = gl0, gl1, gl2


def _np(t: torch.Tensor, dtype: torch.dtype = torch.float32) -> np.ndarray:
    return t.detach().to(dtype).contiguous().numpy()


class _ChildHead(torch.autograd.Function):
    @staticmethod
    def forward(ctx, raw_o, raw_c, raw_cov, offsets, log_scale, base_color, anchors, anchor_index, surfels, cam,
                sh_deg, info):
        # float32 in the mapper; float64 works too (the gradient checks run the same kernels in double)
        dt = torch.float64 if raw_o.dtype == torch.float64 else torch.float32
        m, k = raw_o.shape
        ro, rc, rv = _np(raw_o, dt), _np(raw_c, dt).reshape(m, k, int(np.prod(raw_c.shape[2:]))), _np(raw_cov, dt)
        counts = (ro > 0).sum(axis=1)
        start = np.zeros(m, np.int64)
        if m:
            np.cumsum(counts[:-1], out=start[1:])
        g = int(counts.sum())
        f = ro.dtype
        means, quats, scales = np.empty((g, 3), f), np.empty((g, 4), f), np.empty((g, 3), f)
        opac, col, child = np.empty(g, f), np.empty((g, 3), f), np.empty(g, np.int64)
        parent, local = np.empty(g, np.int64), np.empty(g, np.int64)
        keep, keep_o = np.empty((g, 9), np.float64), np.empty(g, f)
        surf = _surfel_arrays(m, surfels, dt)
        ls, bc, off, an = _np(log_scale, dt), _np(base_color, dt), _np(offsets, dt), _np(anchors, dt)
        rows = anchor_index.to(torch.int64).contiguous().numpy()
        cam = np.asarray(cam, np.float64)
        head_forward(ro, rc, rv, an, ls, off, bc, rows, *surf, cam, sh_deg, start, means, quats, scales, opac, col,
                     child, parent, local, keep, keep_o)
        ctx.np = (ro, rc, rv, off, ls, rows, surf, cam, sh_deg, start, g, raw_c.shape, keep, keep_o)
        ctx.dt = dt
        info["child"], info["anchor"], info["local"] = (torch.from_numpy(child), torch.from_numpy(parent),
                                                        torch.from_numpy(local))
        return (torch.from_numpy(means), torch.from_numpy(quats), torch.from_numpy(scales), torch.from_numpy(opac),
                torch.from_numpy(col))

    @staticmethod
    def backward(ctx, g_means, g_quats, g_scales, g_opac, g_col):
        ro, rc, rv, off, ls, rows, surf, cam, sh_deg, start, g, c_shape, keep, keep_o = ctx.np
        dt = ctx.dt

        def z(t, shape):
            return np.zeros(shape, ro.dtype) if t is None else _np(t, dt)

        gm, gq, gs = z(g_means, (g, 3)), z(g_quats, (g, 4)), z(g_scales, (g, 3))
        go, gc = z(g_opac, (g,)), z(g_col, (g, 3))
        gr_o, gr_c, gr_cov = np.empty_like(ro), np.empty_like(rc), np.empty_like(rv)  # the kernel writes all
        # the map's whole arrays: rows of anchors not decoded stay zero
        g_off, g_ls, g_bc = np.zeros_like(off), np.zeros_like(ls), np.zeros((len(off), ro.shape[1], 3), ro.dtype)
        planar, normals, align, _, radius, _, snap, orient = surf
        head_backward(ro, rc, rv, off, ls, rows, planar, normals, align, radius, snap, orient, cam, sh_deg, start,
                      keep, keep_o, gm, gq, gs, go, gc, gr_o, gr_c, gr_cov, g_off, g_ls, g_bc)
        return (torch.from_numpy(gr_o), torch.from_numpy(gr_c).reshape(c_shape), torch.from_numpy(gr_cov),
                torch.from_numpy(g_off), torch.from_numpy(g_ls), torch.from_numpy(g_bc), None, None, None, None, None,
                None)


def _surfel_arrays(m: int, spec: SurfelSpec | None, dt: torch.dtype) -> tuple:
    """(planar, normals, align, surface, radius, eps, snap, orient) as the kernels take them."""
    f = np.float64 if dt == torch.float64 else np.float32
    if spec is None:
        z3 = np.zeros((m, 3), f)
        return np.zeros(m, np.uint8), z3, np.zeros((m, 4), f), z3, np.zeros(m, f), 0.0, False, True
    return (spec.planar.numpy().astype(np.uint8), _np(spec.normals, dt), _np(spec.align, dt), _np(spec.surface, dt),
            _np(spec.radius, dt), float(spec.eps), bool(spec.snap and spec.orient), bool(spec.orient))


def child_head(raw_o: torch.Tensor, raw_c: torch.Tensor, raw_cov: torch.Tensor, anchors: torch.Tensor,
               log_scale: torch.Tensor, offsets: torch.Tensor, base_color: torch.Tensor, anchor_index: torch.Tensor,
               surfels: SurfelSpec | None = None, cam_center=None, sh_degree: int = 0):
    """The kept children of M decoded anchors (see the module docstring): raw_o [M, k], raw_c [M, k, B, 3] or
    [M, k, 3 B] (B = (sh_degree + 1)^2: the DC logit, then the SH coefficients), raw_cov [M, k, 7]; the map's
    per-anchor arrays anchors [A, 3], log_scale [A, 3], offsets [A, k, 3], base_color [A, k, 3] (logits), of which
    decoded anchor m is row anchor_index[m] [M] (its global id; their gradients come back [A, ...], zero in the rows
    not decoded; the rows must be distinct); the camera centre [3] (world; the SH colour's viewpoint, unused for
    degree 0). Returns (means [G, 3], quats [G, 4], scales [G, 3], opacities [G], colours [G, 3], child_index [G] =
    anchor id * k + slot, anchor [G] = each child's anchor id, local [G] = its row m); differentiable in every float
    input but anchors."""
    if not 0 <= sh_degree <= 3:
        raise ValueError(f"sh_degree must be 0-3, got {sh_degree}")
    info: dict = {}
    cam = np.zeros(3) if cam_center is None else np.asarray(torch.as_tensor(cam_center).detach().double().reshape(3))
    means, quats, scales, opac, col = _ChildHead.apply(raw_o, raw_c, raw_cov, offsets, log_scale, base_color,
                                                       anchors, anchor_index, surfels, cam, int(sh_degree), info)
    return means, quats, scales, opac, col, info["child"], info["anchor"], info["local"]
