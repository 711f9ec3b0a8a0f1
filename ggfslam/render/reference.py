"""Reference backend: the rasterizer's math in plain PyTorch autograd (slow; ground truth for the tests).

Same conventions and rules as the compiled backend (see ``projection.py`` and ``kernels_cpu.py``):
Gaussians sorted by view depth; for every pixel, ``alpha_i = min(0.99, o_i exp(power_i))``, set to 0
when below 1/255; ``T_i = prod_{j<i} (1 - alpha_j)``; the pixel stops before the first Gaussian whose
inclusion would bring T below 1e-4 (that and later Gaussians get weight 0); weights ``w_i = alpha_i T_i``;
channels ``sum_i w_i f_i`` with ``f = [r, g, b, z, extras]``; colour gets ``(1 - sum w) * background``.

The work is done per tile (``kernels_cpu.TILE`` pixels square) on the Gaussians whose pixel box touches the tile
(a pure speed measure: outside its box a Gaussian's alpha is below 1/255 anyway). Works in float32 or float64.
"""
from __future__ import annotations

import torch

from ggfslam.render.kernels_cpu import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE
from ggfslam.render.projection import Projected, project_gaussians
from ggfslam.render.types import Intrinsics, RenderSettings


def composite_tile(px: torch.Tensor, py: torch.Tensor, m2d: torch.Tensor, conics: torch.Tensor,
                   opac: torch.Tensor, feat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Blend depth-ordered Gaussians [m] at pixels (px, py) [P]: returns (channels [P, C], sum of weights [P])."""
    dx = m2d[None, :, 0] - px[:, None]  # [P, m]
    dy = m2d[None, :, 1] - py[:, None]
    a, b, c = conics[None, :, 0], conics[None, :, 1], conics[None, :, 2]
    power = -0.5 * a * dx * dx - 0.5 * c * dy * dy - b * dx * dy
    alpha = (opac[None, :] * torch.exp(power)).clamp(max=ALPHA_MAX)
    alpha = torch.where(alpha.detach() >= ALPHA_MIN, alpha, torch.zeros_like(alpha))
    t_incl = torch.cumprod(1.0 - alpha, dim=1)
    t_excl = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], dim=1)
    keep = (t_incl.detach() >= T_MIN).to(alpha.dtype)
    w = alpha * t_excl * keep
    return w @ feat, w.sum(dim=1)


def rasterize_reference(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                        colors: torch.Tensor, extras: torch.Tensor | None, T_cw: torch.Tensor, intr: Intrinsics,
                        settings: RenderSettings, background: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor, Projected, torch.Tensor]:
    """Render. Returns (image [H, W, 4+K] = r, g, b, raw depth, extras; alpha [H, W]; projection;
    means2d [N, 2], a non-leaf tensor whose gradient is retained)."""
    W, H = intr.width, intr.height
    dtype = means.dtype
    n = means.shape[0]
    proj = project_gaussians(means, quats, scales, opacities, T_cw, intr, settings)
    K = 0 if extras is None else extras.shape[1]
    C = 4 + K
    means2d = torch.zeros(n, 2, dtype=dtype).index_put((proj.idx,), proj.means2d)  # [N, 2]
    if means2d.requires_grad:
        means2d.retain_grad()
    order = torch.argsort(proj.depths.detach(), stable=True)
    idx = proj.idx[order]
    m2d = means2d[idx]
    con = proj.conics[order]
    op = opacities[idx]
    parts = [colors[idx], proj.depths[order][:, None]]
    if K:
        parts.append(extras[idx])
    feat = torch.cat([p.to(dtype) for p in parts], dim=1)  # [M, C]
    box = proj.box[order]
    bg = torch.zeros(C, dtype=dtype)
    bg[:3] = background.to(dtype)
    ntx, nty = (W + TILE - 1) // TILE, (H + TILE - 1) // TILE
    outs, accs, pix_ids = [], [], []
    for ty in range(nty):
        y0, y1 = ty * TILE, min(ty * TILE + TILE, H) - 1
        rows = (box[:, 2] <= y1) & (box[:, 3] >= y0)
        for tx in range(ntx):
            x0, x1 = tx * TILE, min(tx * TILE + TILE, W) - 1
            ys, xs = torch.meshgrid(torch.arange(y0, y1 + 1), torch.arange(x0, x1 + 1), indexing="ij")
            ys, xs = ys.reshape(-1), xs.reshape(-1)
            pix_ids.append(ys * W + xs)
            sel = (rows & (box[:, 0] <= x1) & (box[:, 1] >= x0)).nonzero()[:, 0]
            if sel.numel() == 0:
                outs.append(torch.zeros(len(ys), C, dtype=dtype))
                accs.append(torch.zeros(len(ys), dtype=dtype))
                continue
            o, a = composite_tile(xs.to(dtype), ys.to(dtype), m2d[sel], con[sel], op[sel], feat[sel])
            outs.append(o)
            accs.append(a)
    inv = torch.empty(H * W, dtype=torch.int64)
    inv[torch.cat(pix_ids)] = torch.arange(H * W)
    acc = torch.cat(accs)[inv]
    img = torch.cat(outs)[inv] + (1.0 - acc)[:, None] * bg
    # keep the outputs attached to every input that requires grad (zero gradients when nothing is visible),
    # as the compiled backend's outputs are
    link = [t.sum() * 0.0 for t in (means, quats, scales, opacities, colors, extras, T_cw, background)
            if t is not None and t.requires_grad]
    if link:
        z = torch.stack([x.to(dtype) for x in link]).sum()
        img = img + z
        acc = acc + z
    return img.reshape(H, W, C), acc.reshape(H, W), proj, means2d
