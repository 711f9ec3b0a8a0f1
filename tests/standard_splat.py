"""An independent 3D Gaussian Splatting renderer for checking gaussians.ply as other tools read it.

Written from the formulas of the original 3DGS paper and code (Kerbl et al. 2023), sharing nothing with the
project: its own PLY parser, its own projection and compositing. Conventions it assumes of the file (the
INRIA layout): ``x y z``, ``f_dc_0..2`` and ``f_rest_*`` (channel-major, degree from their count) as real
SH with ``rgb = max(0, 0.5 + SH(dir))``, ``opacity`` a logit, ``scale_*`` natural logs, ``rot_0..3`` a w, x, y, z
quaternion. Rendering: EWA splatting with the 0.3 px low-pass dilation, the Jacobian clamped to 1.3x the
field of view, 3-sigma radii binned to 16x16 tiles, depth-sorted front-to-back compositing with
alpha = min(0.99, o exp(-d^T Sigma^-1 d / 2)), contributions under 1/255 skipped, a pixel stopping before its
transmittance falls under 1e-4. Pinhole camera with OpenCV axes (x right, y down, z forward), pixel centres
at integer coordinates (the datasets' convention).
"""
from __future__ import annotations

import math

import numpy as np
import torch

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435)
TILE = 16

_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "uchar": "u1", "int": "<i4"}


def read_ply(path) -> dict[str, np.ndarray]:
    """The vertex properties of a binary little-endian PLY file, by name."""
    with open(path, "rb") as f:
        assert f.readline().strip() == b"ply"
        props, n = [], None
        while True:
            line = f.readline().decode("ascii").strip()
            if line == "end_header":
                break
            w = line.split()
            if w[0] == "format":
                assert w[1] == "binary_little_endian", line
            elif w[0] == "element":
                assert w[1] == "vertex", "only the vertex element is expected"
                n = int(w[2])
            elif w[0] == "property":
                props.append((w[2], _TYPES[w[1]]))
        data = np.frombuffer(f.read(), dtype=np.dtype(props), count=n)
    return {name: data[name].astype(np.float64) for name, _ in props}


def _sh_colour(v: dict[str, np.ndarray], dirs: torch.Tensor) -> torch.Tensor:
    """rgb [N, 3] of the SH in the file for unit directions [N, 3] (camera centre to Gaussian)."""
    n_rest = len([k for k in v if k.startswith("f_rest_")])
    per = n_rest // 3
    deg = int(round(math.sqrt(per + 1))) - 1
    dc = torch.from_numpy(np.stack([v[f"f_dc_{c}"] for c in range(3)], 1))  # [N, 3]
    rest = torch.from_numpy(np.stack([np.stack([v[f"f_rest_{c * per + j}"] for c in range(3)], 1)
                                      for j in range(per)], 1)) if per else None  # [N, per, 3]
    out = C0 * dc
    x, y, z = (dirs[:, i:i + 1] for i in range(3))
    if deg >= 1:
        out = out - C1 * y * rest[:, 0] + C1 * z * rest[:, 1] - C1 * x * rest[:, 2]
    if deg >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out = (out + C2[0] * xy * rest[:, 3] + C2[1] * yz * rest[:, 4] + C2[2] * (2 * zz - xx - yy) * rest[:, 5]
               + C2[3] * xz * rest[:, 6] + C2[4] * (xx - yy) * rest[:, 7])
    if deg >= 3:
        out = (out + C3[0] * y * (3 * xx - yy) * rest[:, 8] + C3[1] * xy * z * rest[:, 9]
               + C3[2] * y * (4 * zz - xx - yy) * rest[:, 10] + C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * rest[:, 11]
               + C3[4] * x * (4 * zz - xx - yy) * rest[:, 12] + C3[5] * z * (xx - yy) * rest[:, 13]
               + C3[6] * x * (xx - 3 * yy) * rest[:, 14])
    return (out + 0.5).clamp_min(0.0)


def render(ply: dict[str, np.ndarray], fx: float, fy: float, cx: float, cy: float, width: int, height: int,
           T_wc: np.ndarray, background=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Colour [H, W, 3] and accumulated alpha [H, W] of the PLY's Gaussians seen by a camera at T_wc (camera-to-world)."""
    dt = torch.float64
    mean = torch.from_numpy(np.stack([ply["x"], ply["y"], ply["z"]], 1))  # [N, 3]
    q = torch.from_numpy(np.stack([ply[f"rot_{i}"] for i in range(4)], 1))
    q = q / q.norm(dim=1, keepdim=True)
    s = torch.exp(torch.from_numpy(np.stack([ply[f"scale_{i}"] for i in range(3)], 1)))
    o = torch.sigmoid(torch.from_numpy(ply["opacity"]))
    T_wc = torch.from_numpy(np.asarray(T_wc, np.float64))
    R_cw = T_wc[:3, :3].T
    t_cw = -R_cw @ T_wc[:3, 3]
    pc = mean @ R_cw.T + t_cw  # [N, 3]
    keep = pc[:, 2] > 0.2  # 3DGS's near plane
    mean, q, s, o, pc = mean[keep], q[keep], s[keep], o[keep], pc[keep]
    sub = {k: v[keep.numpy()] for k, v in ply.items()}
    d = mean - T_wc[:3, 3]
    rgb = _sh_colour(sub, d / d.norm(dim=1, keepdim=True))  # [N, 3]
    w, x, y, z = q.unbind(1)
    R = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], 1).view(-1, 3, 3)
    M = R * s[:, None, :]
    cov3 = M @ M.transpose(1, 2)  # [N, 3, 3] world
    tz = pc[:, 2]
    limx, limy = 1.3 * (width / 2) / fx, 1.3 * (height / 2) / fy  # the 3DGS clamp of x/z, y/z
    tx = (pc[:, 0] / tz).clamp(-limx, limx) * tz
    ty = (pc[:, 1] / tz).clamp(-limy, limy) * tz
    J = torch.zeros(len(tz), 2, 3, dtype=dt)
    J[:, 0, 0], J[:, 0, 2] = fx / tz, -fx * tx / tz ** 2
    J[:, 1, 1], J[:, 1, 2] = fy / tz, -fy * ty / tz ** 2
    JW = J @ R_cw
    cov2 = JW @ cov3 @ JW.transpose(1, 2) + 0.3 * torch.eye(2, dtype=dt)  # [N, 2, 2]
    a, b, c = cov2[:, 0, 0], cov2[:, 0, 1], cov2[:, 1, 1]
    det = a * c - b * b
    ok = det > 0
    conic = torch.stack([c / det, -b / det, a / det], 1)  # [N, 3]
    mid = 0.5 * (a + c)
    lam = mid + torch.sqrt((mid * mid - det).clamp_min(0.1))
    radius = torch.ceil(3 * torch.sqrt(lam))
    u = fx * pc[:, 0] / tz + cx
    v = fy * pc[:, 1] / tz + cy
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    x0 = ((u - radius) / TILE).floor().clamp(0, tiles_x).long()
    x1 = ((u + radius + TILE - 1) / TILE).floor().clamp(0, tiles_x).long()
    y0 = ((v - radius) / TILE).floor().clamp(0, tiles_y).long()
    y1 = ((v + radius + TILE - 1) / TILE).floor().clamp(0, tiles_y).long()
    ok &= (x1 > x0) & (y1 > y0) & (radius > 0)
    order = torch.argsort(tz)
    order = order[ok[order]]
    color = torch.zeros(height, width, 3, dtype=dt)
    alpha_acc = torch.zeros(height, width, dtype=dt)
    bg = torch.tensor(background, dtype=dt)
    for ty_ in range(tiles_y):
        for tx_ in range(tiles_x):
            sel = order[(x0[order] <= tx_) & (x1[order] > tx_) & (y0[order] <= ty_) & (y1[order] > ty_)]
            px0, py0 = tx_ * TILE, ty_ * TILE
            px1, py1 = min(px0 + TILE, width), min(py0 + TILE, height)
            gy, gx = torch.meshgrid(torch.arange(py0, py1, dtype=dt), torch.arange(px0, px1, dtype=dt), indexing="ij")
            if len(sel) == 0:
                color[py0:py1, px0:px1] = bg
                continue
            dx = gx.reshape(-1, 1) - u[sel][None, :]  # [P, G]
            dy = gy.reshape(-1, 1) - v[sel][None, :]
            cc = conic[sel]
            power = -0.5 * (cc[:, 0] * dx * dx + cc[:, 2] * dy * dy) - cc[:, 1] * dx * dy
            alpha = torch.clamp(o[sel] * torch.exp(power), max=0.99)
            alpha = torch.where((power <= 0) & (alpha >= 1 / 255), alpha, torch.zeros_like(alpha))
            t_incl = torch.cumprod(1 - alpha, dim=1)  # transmittance after each Gaussian
            alive = t_incl >= 1e-4  # a pixel stops before T would fall under 1e-4 (monotone: a prefix)
            alpha = alpha * alive
            t_incl = torch.cumprod(1 - alpha, dim=1)
            t_before = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], 1)
            wgt = alpha * t_before  # [P, G]
            t_final = t_incl[:, -1]
            img = wgt @ rgb[sel] + t_final[:, None] * bg
            color[py0:py1, px0:px1] = img.view(py1 - py0, px1 - px0, 3)
            alpha_acc[py0:py1, px0:px1] = (1 - t_final).view(py1 - py0, px1 - px0)
    return color.float().numpy(), alpha_acc.float().numpy()
