"""Explicit 3DGS Gaussians read from a PLY file (our bake or any other system's) and rendered by our rasterizer.

Colours are real spherical harmonics of degree 0-3 in the 3DGS convention: ``rgb = max(0, 0.5 + sum_l Y_lm(d)
c_lm)`` with ``d`` the unit direction from the camera centre to the Gaussian (world frame); ``f_rest`` in the
file is channel-major (``f_rest_{c * B + j}``, B coefficients per channel). ``ggfslam render --ply`` and the
fidelity figures in metrics.json render the baked file through this module.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ggfslam.errors import DatasetError
from ggfslam.gaussians.ply import SH_C0, read_gaussians_ply
from ggfslam.geometry.se3 import invert
from ggfslam.render.api import rasterize
from ggfslam.render.types import Intrinsics, RenderOutput, RenderSettings

SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Real SH basis [N, (degree + 1)^2] of unit directions [N, 3] (3DGS's order and signs, DC first)."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * x * z,
                SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * x * y * z, SH_C3[2] * y * (4 * zz - xx - yy),
                SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)


@dataclass
class ExplicitGaussians:
    """Gaussians with SH colours: the renderer's inputs except colour, which depends on the viewpoint."""

    means: torch.Tensor  # [N, 3] world
    quats: torch.Tensor  # [N, 4] w, x, y, z (unit)
    scales: torch.Tensor  # [N, 3] linear
    opacities: torch.Tensor  # [N]
    sh: torch.Tensor  # [N, (degree + 1)^2, 3] SH coefficients, DC first
    degree: int

    @classmethod
    def from_ply(cls, path: str | Path) -> ExplicitGaussians:
        """Read a standard 3DGS PLY (``read_gaussians_ply``; any SH degree 0-3)."""
        d = read_gaussians_ply(path)
        n, n_rest = d["means"].shape[0], d["sh_rest"].shape[1]
        per = n_rest // 3
        degree = int(round(math.sqrt(per + 1))) - 1
        if n_rest % 3 or (degree + 1) ** 2 - 1 != per or degree > 3:
            raise DatasetError(Path(path), f"{n_rest} f_rest_* properties: expected 0, 9, 24 or 45 (SH degree 0-3)")
        dc = (torch.from_numpy(d["colors"]).double() - 0.5) / SH_C0  # [N, 3]
        rest = torch.from_numpy(d["sh_rest"]).double().view(n, 3, per).transpose(1, 2)  # [N, per, 3]
        sh = torch.cat([dc[:, None, :], rest], dim=1).float()
        return cls(torch.from_numpy(d["means"]), torch.from_numpy(d["quats"]), torch.from_numpy(d["scales"]),
                   torch.from_numpy(d["opacities"]), sh, degree)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def colors(self, cam_center: np.ndarray | torch.Tensor) -> torch.Tensor:
        """rgb [N, 3] seen from ``cam_center`` [3] (world)."""
        c = torch.as_tensor(np.asarray(cam_center, np.float32))
        d = self.means - c
        d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)
        basis = sh_basis(d, self.degree)  # [N, B]
        return ((basis[:, :, None] * self.sh).sum(dim=1) + 0.5).clamp_min(0.0)

    def render(self, T_wc: np.ndarray, intr: Intrinsics, settings: RenderSettings | None = None) -> RenderOutput:
        """Render from camera-to-world T_wc [4, 4] with our rasterizer."""
        with torch.no_grad():
            return rasterize(self.means, self.quats, self.scales, self.opacities, self.colors(T_wc[:3, 3]), intr,
                             torch.from_numpy(invert(T_wc)).float(), settings=settings)
