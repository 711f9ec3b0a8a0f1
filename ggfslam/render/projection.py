"""3D -> 2D projection of Gaussians in plain torch (differentiable; used by the reference backend).

The math is the standard 3DGS / gsplat EWA splatting, written elementwise (no batched 3x3 products):
- ``p = R_cw mu + t_cw``; pixel centre ``(fx x/z + cx, fy y/z + cy)``; view depth ``z``.
- ``Sigma = M M^T`` with ``M = R(q) diag(s)``, quaternion (w, x, y, z) normalised with a 1e-12 floor.
- ``Sigma2 = J R_cw Sigma R_cw^T J^T + eps2d I`` with the projection Jacobian ``J`` evaluated at x/z, y/z
  clamped to 1.15x the field of view (gsplat's limits for an off-centre principal point).
- ``conic = Sigma2^-1`` stored as (a, b, c): ``power = -0.5 (a dx^2 + c dy^2) - b dx dy``, ``dx = mu_x - u``.
- Pixel box: every pixel where ``opacity * exp(power) >= 1/255``, i.e. ``d^T conic d <= 2 ln(255 o)``,
  whose half-extents are ``sqrt(2 ln(255 o) Sigma2_xx)`` and ``sqrt(2 ln(255 o) Sigma2_yy)`` (enlarged by a
  tiny margin; the rasterizers still test alpha exactly). Boxes are clipped to the image.
- Culled (not visible): depth outside [near, far], opacity < 1/255, non-finite values, empty box.
``kernels_cpu.project_forward`` implements the same formulas in numba.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ggfslam.render.kernels_cpu import ALPHA_MIN, BOX_ABS_MARGIN, BOX_REL_MARGIN
from ggfslam.render.types import Intrinsics, RenderSettings


@dataclass
class Projected:
    """Projection of the Gaussians that survive culling (``idx`` are their indices into the inputs)."""

    idx: torch.Tensor  # [M] int64, indices of the visible Gaussians
    means2d: torch.Tensor  # [M, 2] pixel centres
    conics: torch.Tensor  # [M, 3] (a, b, c)
    depths: torch.Tensor  # [M] view depth z
    box: torch.Tensor  # [M, 4] int64 x0, x1, y0, y1 (inclusive, clipped), detached
    radii: torch.Tensor  # [M] int32 3-sigma radius
    all_depths: torch.Tensor  # [N] view depth of every Gaussian (detached)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N, 3, 3] from quaternions [N, 4] ordered (w, x, y, z) (normalised here)."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(q.shape[:-1] + (3, 3))


def project_gaussians(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                      T_cw: torch.Tensor, intr: Intrinsics, settings: RenderSettings) -> Projected:
    """Project Gaussians (see module docstring). ``T_cw`` [4, 4] may require grad; computes in means' dtype."""
    dtype = means.dtype
    T = T_cw.to(dtype)
    R, t = T[:3, :3], T[:3, 3]
    fx, fy, cx, cy, W, H = intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height
    # camera coordinates of all Gaussians
    x = R[0, 0] * means[:, 0] + R[0, 1] * means[:, 1] + R[0, 2] * means[:, 2] + t[0]
    y = R[1, 0] * means[:, 0] + R[1, 1] * means[:, 1] + R[1, 2] * means[:, 2] + t[1]
    z = R[2, 0] * means[:, 0] + R[2, 1] * means[:, 1] + R[2, 2] * means[:, 2] + t[2]
    with torch.no_grad():
        zd = z.detach()
        keep = (zd >= settings.near_plane) & (zd <= settings.far_plane) & (opacities.detach() >= ALPHA_MIN)
        all_depths = torch.where(torch.isfinite(zd), zd, torch.zeros_like(zd))
    idx = keep.nonzero()[:, 0]
    x, y, z = x[idx], y[idx], z[idx]
    Rq = quat_to_rotmat(quats[idx])  # [M, 3, 3]
    M = Rq * scales[idx][:, None, :]  # M[i, r, c] = Rq[r, c] s[c]
    S = M @ M.transpose(1, 2)  # [M, 3, 3]
    tanx, tany = 0.5 * W / fx, 0.5 * H / fy
    limxp, limxn = (W - cx) / fx + 0.3 * tanx, cx / fx + 0.3 * tanx
    limyp, limyn = (H - cy) / fy + 0.3 * tany, cy / fy + 0.3 * tany
    rx, ry = x / z, y / z
    tx = z * rx.clamp(-limxn, limxp)
    ty = z * ry.clamp(-limyn, limyp)
    zero = torch.zeros_like(z)
    J = torch.stack([fx / z, zero, -fx * tx / (z * z), zero, fy / z, -fy * ty / (z * z)], -1).reshape(-1, 2, 3)
    T2 = J @ R  # [M, 2, 3]
    cov2 = T2 @ S @ T2.transpose(1, 2)  # [M, 2, 2]
    a = cov2[:, 0, 0] + settings.eps2d
    b = cov2[:, 0, 1]
    c = cov2[:, 1, 1] + settings.eps2d
    det = a * c - b * b
    mx = fx * rx + cx
    my = fy * ry + cy
    with torch.no_grad():
        o = opacities.detach()[idx].to(torch.float64)
        ad, cd, detd = a.detach().double(), c.detach().double(), det.detach().double()
        mxd, myd = mx.detach().double(), my.detach().double()
        ok = torch.isfinite(detd) & (detd > 0) & torch.isfinite(mxd) & torch.isfinite(myd)
        k2 = 2.0 * torch.log(255.0 * o)
        ex = torch.sqrt((k2 * ad).clamp_min(0)) * (1 + BOX_REL_MARGIN) + BOX_ABS_MARGIN
        ey = torch.sqrt((k2 * cd).clamp_min(0)) * (1 + BOX_REL_MARGIN) + BOX_ABS_MARGIN
        x0 = torch.ceil(mxd - ex).clamp_min(0)
        x1 = torch.floor(mxd + ex).clamp_max(W - 1)
        y0 = torch.ceil(myd - ey).clamp_min(0)
        y1 = torch.floor(myd + ey).clamp_max(H - 1)
        ok &= (x0 <= x1) & (y0 <= y1)
        mid = 0.5 * (ad + cd)
        lam = mid + torch.sqrt(torch.clamp_min(mid * mid - detd, 0.1))
        sel = ok.nonzero()[:, 0]
        box = torch.stack([x0, x1, y0, y1], -1)[sel].to(torch.int64)
        radii = torch.ceil(3.0 * torch.sqrt(lam[sel])).to(torch.int32)
    a, b, c, det, mx, my, z = a[sel], b[sel], c[sel], det[sel], mx[sel], my[sel], z[sel]
    conics = torch.stack([c / det, -b / det, a / det], -1)
    return Projected(idx=idx[sel], means2d=torch.stack([mx, my], -1), conics=conics, depths=z, box=box,
                     radii=radii, all_depths=all_depths)

