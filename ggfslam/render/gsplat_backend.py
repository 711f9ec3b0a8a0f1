"""CUDA backend: an adapter to ``gsplat.rasterization`` (optional extra ``pip install ggfslam[cuda]``).

Written against gsplat's documented ``rasterization`` API (1.x): ``means [N,3]``, ``quats [N,4]`` (wxyz,
normalised inside), ``scales [N,3]``, ``opacities [N]``, ``colors [N,D]`` (post-activation when
``sh_degree=None``), ``viewmats [C,4,4]`` world-to-camera, ``Ks [C,3,3]``, ``backgrounds [C,D]``,
``render_mode="RGB+D"`` (accumulated depth ``sum w z`` appended as the last channel), returning
``(colors [C,H,W,D+1], alphas [C,H,W,1], meta)`` with ``meta["means2d"]`` [C,N,2] (non-packed),
``meta["radii"]`` [C,N] or [C,N,2] (newer versions) and ``meta["depths"]`` [C,N]. gsplat
differentiates w.r.t. ``viewmats``, so pose gradients reach ``pose_xi`` through ``ggfslam.render.pose``.

Same conventions as the CPU backend (eps2d blur, alpha rules, near/far, classic mode, pinhole); the
known difference is gsplat's screen extent of a Gaussian (3-sigma radius, or an opacity-aware bound in
newer versions) versus our exact alpha >= 1/255 box, so pixels in the far tails of very opaque Gaussians
may differ by about 1/255. Inputs are moved to CUDA if needed and outputs come back on the device of
``means``. Extras are rendered as extra colour channels (background 0).

THIS ADAPTER WAS WRITTEN WITHOUT A GPU and has not been run; ``tests/test_render_gsplat.py`` checks it
against the CPU backend when CUDA and gsplat are present.
"""
from __future__ import annotations

import logging

import torch

from ggfslam.errors import GGFSlamError
from ggfslam.render.types import Intrinsics, RenderSettings

GSPLAT_MISSING = "gsplat backend needs a CUDA GPU and `pip install ggfslam[cuda]`"


log = logging.getLogger("ggfslam.render")
_GSPLAT_IMPORTS: bool | None = None


def gsplat_available() -> bool:
    """True when a CUDA device is present and gsplat imports (the import is tried once per process; a GPU
    whose gsplat fails to import is reported once, since ``auto`` then renders on the CPU)."""
    global _GSPLAT_IMPORTS
    if not torch.cuda.is_available():
        return False
    if _GSPLAT_IMPORTS is None:
        try:
            import gsplat  # noqa: F401

            _GSPLAT_IMPORTS = True
        except Exception as e:  # ImportError, or a CUDA extension that fails to load
            log.warning("a CUDA GPU is present but gsplat does not import (%s: %s): rendering on the CPU",
                        type(e).__name__, e)
            _GSPLAT_IMPORTS = False
    return _GSPLAT_IMPORTS


def rasterize_gsplat(means, quats, scales, opacities, colors, extras, T_cw, intr: Intrinsics,
                     settings: RenderSettings, background: torch.Tensor):
    """Render with gsplat. Returns (image [H, W, 4+K] = r, g, b, raw depth, extras; alpha [H, W];
    radii [N] int32; means2d probe [1, N, 2] (its .grad is dL/dmeans2d); depths [N])."""
    if not torch.cuda.is_available():
        raise GGFSlamError(GSPLAT_MISSING)
    try:
        from gsplat import rasterization
    except Exception as exc:  # ImportError, or a broken CUDA extension build
        raise GGFSlamError(f"{GSPLAT_MISSING} (import failed: {exc})") from exc
    out_device = means.device
    dev = means.device if means.device.type == "cuda" else torch.device("cuda")

    def cu(t):
        return t.to(device=dev, dtype=torch.float32)

    K = 0 if extras is None else extras.shape[1]
    feats = colors if extras is None else torch.cat([colors, extras.to(colors.dtype)], dim=1)  # [N, 3+K]
    bg = torch.zeros(3 + K, dtype=torch.float32, device=dev)
    bg[:3] = cu(background)
    viewmat = cu(T_cw)[None]  # [1, 4, 4]
    Ks = intr.K(torch.float32, dev)[None]  # [1, 3, 3]
    rend, alphas, meta = rasterization(
        cu(means), cu(quats), cu(scales), cu(opacities), cu(feats), viewmat, Ks, intr.width, intr.height,
        near_plane=settings.near_plane, far_plane=settings.far_plane, eps2d=settings.eps2d, sh_degree=None,
        packed=False, tile_size=16, backgrounds=bg[None], render_mode="RGB+D", rasterize_mode="classic",
        channel_chunk=max(32, 4 + K),
    )
    rend = rend[0]  # [H, W, 3+K+1]: r, g, b, extras..., depth
    img = torch.cat([rend[..., :3], rend[..., -1:], rend[..., 3:3 + K]], dim=-1)
    alpha = alphas[0, ..., 0]
    m2d = meta["means2d"]
    if m2d.requires_grad:
        m2d.retain_grad()
    radii = meta["radii"][0]
    if radii.dim() == 2:  # newer gsplat: per-axis radii [N, 2], visible where both are > 0
        radii = torch.where((radii > 0).all(dim=-1), radii.max(dim=-1).values, torch.zeros_like(radii[:, 0]))
    depths = meta["depths"][0].detach()
    return (img.to(out_device), alpha.to(out_device), radii.to(device=out_device, dtype=torch.int32), m2d,
            depths.to(out_device))
