"""Adaptive Morphological Regularization (METHOD.md §4, §5): planar anchors' children become surfels.

For a child of an anchor with ``P_2D > tau_thresh`` (normal ``n``, surface point ``p``, KNN spacing ``d``):
- rotation ``q = q_n * q_z(theta)``: ``q_n`` turns the local z axis onto ``n``; the decoder keeps the
  in-plane angle ``theta`` (its quaternion projected onto rotations about z);
- scales ``(max(s_x, r), max(s_y, r), eps)``: the local z axis, now the normal, is the shortest with
  thickness ``eps`` (``surfel_eps`` x voxel); tangential radii are at least ``r = surfel_radius * d`` so
  neighbouring surfels overlap and leave no holes;
- with ``ggf.snap``, the mean moved along ``n`` onto the anchor's plane through ``p`` (the decoder keeps the
  in-plane position); ``p`` is the anchor's surface point projected onto its patch's plane (``plane_points``
  of ``ggfslam.ggf.features``), so the plane is averaged over the patch rather than one voxel's depth;
- with ``ggf.surfel_orientation: decoder`` (``orient=False``) the rotation is the decoder's own: the surfel is
  flat along its own local z axis, which the images and the normal loss turn, not along ``n`` (no snap then).
This is a hard projection of what the decoder outputs, so the render always sees surfels. ``L_morph``
(``morph_loss``) acts on the decoder's raw output: it pulls the raw shortest axis onto ``n`` and the raw
thickness to ``eps``, so children keep their surfel shape if their anchor later drops below the threshold.
Quaternions are (w, x, y, z).
"""
from __future__ import annotations

import torch

from ggfslam.render.projection import quat_to_rotmat


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product [N, 4] of quaternions a [N, 4] and b [N, 4] (w, x, y, z): rotate by b, then a."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], dim=-1)


def quat_z_to(n: torch.Tensor) -> torch.Tensor:
    """Unit quaternions [N, 4] turning the z axis onto +-n [N, 3] (unit); the sign of n is free for a
    surfel, and choosing n_z >= 0 avoids the singular half-turn."""
    n = torch.where(n[:, 2:3] < 0, -n, n)
    q = torch.stack([1.0 + n[:, 2], -n[:, 1], n[:, 0], torch.zeros_like(n[:, 0])], dim=-1)  # axis z x n
    return q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def _inplane(quats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The decoder quaternion's rotation about local z: unit (w, z) [N, 2] and the norm [N] it was divided by."""
    wz = quats[:, [0, 3]]
    norm = wz.norm(dim=1)
    c = torch.where((norm > 1e-8)[:, None], wz / norm.clamp_min(1e-8)[:, None], torch.tensor([1.0, 0.0], dtype=wz.dtype))
    return c, norm


class _SurfelShape(torch.autograd.Function):
    """``surfel_shape`` on the children selected by a mask, others passed through; a hand-written backward
    (a dozen tensor ops instead of autograd's graph of ~40: about 4x faster at 150k children)."""

    @staticmethod
    def forward(ctx, quats, scales, means, mask, normals, surface, min_radius, eps, align, snap, orient):
        if orient:
            c, norm = _inplane(quats)  # [N, 2]
            qk = quat_multiply(align, torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=align.dtype).expand_as(align))
            q = c[:, :1] * align + c[:, 1:] * qk  # align * (c0 + c1 k)
        else:  # the decoder's own rotation: nothing of the in-plane angle to keep for the backward
            c = norm = qk = None
            q = quats
        tang = scales[:, :2] >= min_radius[:, None]  # [N, 2] tangential scale above the floor
        s = torch.cat([torch.where(tang, scales[:, :2], min_radius[:, None]), torch.full_like(scales[:, :1], eps)], 1)
        m = means - ((means - surface) * normals).sum(-1, keepdim=True) * normals if snap else means
        mk = mask[:, None]
        ctx.snap, ctx.orient = snap, orient
        ctx.save_for_backward(mask, normals, align, qk, c, norm, tang)
        return torch.where(mk, q, quats), torch.where(mk, s, scales), torch.where(mk, m, means)

    @staticmethod
    def backward(ctx, g_q, g_s, g_m):
        mask, normals, align, qk, c, norm, tang = ctx.saved_tensors
        mk = mask[:, None]
        # q = c0 align + c1 qk with c = (w, z) / |(w, z)|
        if ctx.orient:
            g_c = torch.stack([(g_q * align).sum(-1), (g_q * qk).sum(-1)], 1)  # [N, 2]
            g_wz = (g_c - (g_c * c).sum(-1, keepdim=True) * c) / norm.clamp_min(1e-8)[:, None]
            g_quat = torch.zeros_like(g_q)
            g_quat[:, 0], g_quat[:, 3] = g_wz[:, 0], g_wz[:, 1]
        else:
            g_quat = g_q
        g_scale = torch.cat([g_s[:, :2] * tang, torch.zeros_like(g_s[:, :1])], 1)
        g_mean = g_m - (g_m * normals).sum(-1, keepdim=True) * normals if ctx.snap else g_m  # (I - n n^T) g
        return (torch.where(mk, g_quat, g_q), torch.where(mk, g_scale, g_s), torch.where(mk, g_mean, g_m),
                None, None, None, None, None, None, None, None)


def surfel_shape(quats: torch.Tensor, scales: torch.Tensor, means: torch.Tensor, normals: torch.Tensor,
                 surface: torch.Tensor, min_radius: torch.Tensor, eps: float, align: torch.Tensor | None = None,
                 mask: torch.Tensor | None = None, snap: bool = True,
                 orient: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """AMR applied to children [N]: quats [N, 4], scales [N, 3], means [N, 3] of the decoder, their anchor's
    normal [N, 3], surface point [N, 3] and smallest tangential radius [N] -> surfel (quats, scales, means).
    ``align`` [N, 4]: ``quat_z_to(normals)`` when the caller has it already; ``mask`` [N] bool: shape only
    those children and pass the others through (default: all); ``snap=False`` leaves the means where the
    decoder put them; ``orient=False`` leaves the rotations as the decoder made them (and implies no snap).
    Differentiable in quats, scales and means."""
    align = quat_z_to(normals) if align is None else align
    mask = torch.ones(len(quats), dtype=torch.bool) if mask is None else mask
    return _SurfelShape.apply(quats, scales, means, mask, normals, surface, min_radius, float(eps), align,
                              bool(snap and orient), bool(orient))


def surfel_shape_reference(quats, scales, means, normals, surface, min_radius, eps, orient: bool = True):
    """``surfel_shape`` in plain autograd ops (the parity reference of the hand-written backward; with ``orient``
    the means snapped, without it rotations and means as the decoder made them)."""
    s = torch.cat([torch.maximum(scales[:, :2], min_radius[:, None]), torch.full_like(scales[:, 2:], eps)], dim=1)
    if not orient:
        return quats, s, means
    c, _ = _inplane(quats)
    inplane = torch.stack([c[:, 0], torch.zeros_like(c[:, 0]), torch.zeros_like(c[:, 0]), c[:, 1]], -1)
    q = quat_multiply(quat_z_to(normals), inplane)
    m = means - ((means - surface) * normals).sum(-1, keepdim=True) * normals
    return q, s, m


def shortest_axis(quats: torch.Tensor, scales: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World direction [N, 3] and length [N] of each Gaussian's shortest axis (differentiable in both)."""
    R = quat_to_rotmat(quats)  # [N, 3, 3], columns = local axes in the world
    j = scales.detach().argmin(dim=1)  # [N]
    axis = R.gather(2, j[:, None, None].expand(-1, 3, 1))[:, :, 0]
    return axis, scales.gather(1, j[:, None])[:, 0]


def morph_loss(quats: torch.Tensor, scales: torch.Tensor, normals: torch.Tensor, eps: float, unit: float,
               lambda_dir: float = 1.0, lambda_thin: float = 1.0) -> torch.Tensor:
    """L_morph over planar children: mean of lambda_dir (1 - |r_short . n|) + lambda_thin max(0, s_short - eps) / unit."""
    if quats.shape[0] == 0:
        return quats.sum() * 0.0
    axis, s = shortest_axis(quats, scales)
    align = 1.0 - (axis * normals).sum(-1).abs()
    return (lambda_dir * align + lambda_thin * torch.relu(s - eps) / unit).mean()
