"""Baking a view-dependent (Scaffold-GS, ``mapping.view_dependent: true``) map into explicit Gaussians.

The default decoders read no view inputs and give SH colours, so ``Mapper.bake_gaussians`` writes their children
as they are and needs nothing here. A view-dependent decoder also reads the viewing direction and distance, and
was only ever trained on views from the keyframes: decoding it "from nowhere" (zero direction and distance)
feeds it inputs it never saw, and a standard renderer of such a file scored ~10 dB below the project's own
render. Such a map is therefore baked from real viewpoints: each anchor from the centre of the **nearest keyframe
that observed it** (its surface point projects inside that keyframe's image and agrees with that keyframe's
depth), so each part of the map is baked as it looked in the closest training view.

The children's colours are then fitted, per child, over up to ``max_views`` observing keyframes as a degree-1
spherical-harmonic function of the viewing direction (least squares with a small ridge on the degree-1
coefficients), which 3DGS files carry in ``f_rest_*``. Opacity, scale and rotation stay those of the nearest
view (a PLY has no way to make them view-dependent).

Conventions: poses camera-to-world ``T_wc`` [4, 4]; OpenCV camera axes; the view direction of an anchor is
the unit vector from the camera centre to the anchor (world frame), as in the decoder and in 3DGS's SH.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ggfslam.gaussians.explicit import sh_basis
from ggfslam.render.types import Intrinsics


@dataclass
class BakeViews:
    """Per anchor, the keyframes it is baked from."""

    nearest: np.ndarray  # [A] int64 position (in the keyframe list) of the nearest observing keyframe
    observed: np.ndarray  # [A] bool: some keyframe saw it (else ``nearest`` is a frustum/centre fallback)
    views: np.ndarray  # [A, V] int64 positions of up to V observing keyframes, nearest first (-1 = none)


def observing_keyframes(points: np.ndarray, poses: list[np.ndarray], depths: list[np.ndarray], intr: Intrinsics,
                        voxel: float, max_views: int = 1, near: float = 0.05) -> BakeViews:
    """Which keyframes saw each surface point [A, 3] (world), nearest first.

    A keyframe (camera-to-world pose, depth [h, w] at ``intr``) saw a point when it projects inside its image
    in front of the camera and its view depth agrees with the keyframe's depth there (within
    ``max(2 voxel, 3 %)``, the observation rule of the mapper). Points no keyframe saw fall back to the nearest
    keyframe that has them in its frustum, else to the nearest keyframe centre."""
    a = len(points)
    if not poses:
        raise ValueError("baking needs at least one keyframe")
    v = max(1, int(max_views))
    inf = np.float32(np.inf)
    best = np.full((a, v), inf, np.float32)  # distances of the V nearest observing keyframes
    best_kf = np.full((a, v), -1, np.int64)
    frustum_d = np.full(a, inf, np.float32)
    frustum_kf = np.full(a, -1, np.int64)
    centre_d = np.full(a, inf, np.float32)
    centre_kf = np.zeros(a, np.int64)
    pts = np.asarray(points, np.float64)
    for j, (T_wc, depth) in enumerate(zip(poses, depths)):
        R, c = T_wc[:3, :3], T_wc[:3, 3]
        pc = (pts - c) @ R  # [A, 3] camera frame (R^T (p - c))
        dist = np.linalg.norm(pts - c, axis=1).astype(np.float32)  # [A]
        closer = dist < centre_d
        centre_d[closer], centre_kf[closer] = dist[closer], j
        z = pc[:, 2]
        front = np.nonzero(z > near)[0]
        u = np.rint(intr.fx * pc[front, 0] / z[front] + intr.cx).astype(np.int64)
        w = np.rint(intr.fy * pc[front, 1] / z[front] + intr.cy).astype(np.int64)
        inside = (u >= 0) & (u < intr.width) & (w >= 0) & (w < intr.height)
        idx, u, w = front[inside], u[inside], w[inside]
        closer = dist[idx] < frustum_d[idx]
        frustum_d[idx[closer]], frustum_kf[idx[closer]] = dist[idx[closer]], j
        d = depth[w, u]
        seen = (d > 0) & (np.abs(z[idx] - d) < np.maximum(2 * voxel, 0.03 * d))
        idx = idx[seen]
        # insert this keyframe into each point's sorted list of the V nearest
        dd, kk = dist[idx], np.full(len(idx), j, np.int64)
        for slot in range(v):
            cur_d, cur_k = best[idx, slot], best_kf[idx, slot]
            swap = dd < cur_d
            best[idx[swap], slot], best_kf[idx[swap], slot] = dd[swap], kk[swap]
            dd, kk = np.where(swap, cur_d, dd), np.where(swap, cur_k, kk)
    observed = best_kf[:, 0] >= 0
    nearest = np.where(observed, best_kf[:, 0], np.where(frustum_kf >= 0, frustum_kf, centre_kf))
    return BakeViews(nearest=nearest, observed=observed, views=best_kf)


def fit_sh1(colors: torch.Tensor, dirs: torch.Tensor, valid: torch.Tensor, ridge: float = 0.05
            ) -> tuple[torch.Tensor, torch.Tensor]:
    """Per child, rgb(d) ~ c0 + sum_j a_j Y_j(d) fitted by least squares over its views.

    colors [G, V, 3] in [0, 1], dirs [G, V, 3] unit view directions, valid [G, V] bool (view 0 must be valid).
    ``ridge`` (relative to the number of views) keeps the degree-1 part small where the views span few
    directions. Returns (c0 [G, 3], a [G, 3 basis, 3 channels])."""
    w = valid.to(colors.dtype)[..., None]  # [G, V, 1]
    B = torch.cat([torch.ones_like(dirs[..., :1]), sh_basis(dirs, 1)[..., 1:]], dim=-1) * w  # [G, V, 4]
    n = w.sum(dim=1, keepdim=True).clamp_min(1)  # [G, 1, 1]
    reg = torch.diag(torch.tensor([1e-12, ridge, ridge, ridge], dtype=colors.dtype))  # [4, 4]
    A = B.transpose(1, 2) @ B + reg * n  # [G, 4, 4]
    rhs = B.transpose(1, 2) @ (colors * w)  # [G, 4, 3]
    coef = torch.linalg.solve(A, rhs)  # [G, 4, 3]
    return coef[:, 0], coef[:, 1:]
