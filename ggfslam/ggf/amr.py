"""Adaptive Morphological Regularization (METHOD.md §4, §5): planar anchors' children become surfels.

For a child of an anchor with ``P_2D > tau_thresh`` (normal ``n``, surface point ``p``, KNN spacing ``d``):
- rotation ``q = q_n * q_z(theta)``: ``q_n`` turns the local z axis onto ``n``; the decoder keeps the
  in-plane angle ``theta`` (its quaternion projected onto rotations about z);
- scales ``(max(s_x, r), max(s_y, r), eps)``: the local z axis, now the normal, is the shortest with
  thickness ``eps`` (``surfel_eps`` x voxel); tangential radii are at least ``r = surfel_radius * d`` so
  neighbouring surfels overlap and leave no holes;
- mean moved along ``n`` onto the anchor's plane through ``p`` (the decoder keeps the in-plane position).
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


def surfel_shape(quats: torch.Tensor, scales: torch.Tensor, means: torch.Tensor, normals: torch.Tensor,
                 surface: torch.Tensor, min_radius: torch.Tensor, eps: float, align: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """AMR applied to children [N]: quats [N, 4], scales [N, 3], means [N, 3] of the decoder, their anchor's
    normal [N, 3], surface point [N, 3] and smallest tangential radius [N] -> surfel (quats, scales, means).
    ``align`` [N, 4]: ``quat_z_to(normals)`` when the caller has it already."""
    inplane = torch.stack([quats[:, 0], torch.zeros_like(quats[:, 0]), torch.zeros_like(quats[:, 0]), quats[:, 3]], -1)
    norm = inplane.norm(dim=-1, keepdim=True)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype).expand_as(inplane)
    inplane = torch.where(norm > 1e-8, inplane / norm.clamp_min(1e-8), identity)
    q = quat_multiply(quat_z_to(normals) if align is None else align, inplane)
    s = torch.cat([torch.maximum(scales[:, :2], min_radius[:, None]),
                   torch.full_like(scales[:, 2:], eps)], dim=1)
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
