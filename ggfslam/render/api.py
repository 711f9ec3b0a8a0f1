"""The one rendering entry point: ``rasterize(...) -> RenderOutput``, and backend selection.

Backends (config ``render.backend``):
- ``cpu``: compiled numba kernels (``kernels_cpu``), hand-written backward; the default without a GPU.
- ``reference``: the same math in plain torch autograd (slow; ground truth for tests; float32 or float64).
- ``gsplat``: CUDA via gsplat (optional ``[cuda]`` extra).
- ``auto``: gsplat when ``torch.cuda.is_available()`` and gsplat imports, else cpu.

Example::

    out = rasterize(means, quats, scales, opacities, colors, camera, T_cw, pose_xi=xi, extras=p2d[:, None])
    loss = (out.depth - sensor_depth).abs()[mask].mean()
    loss.backward()          # xi.grad = d loss / d xi, GTSAM's tangent convention
"""
from __future__ import annotations

import numpy as np
import torch

from ggfslam.errors import ConfigError, GGFSlamError
from ggfslam.render.gsplat_backend import GSPLAT_MISSING, gsplat_available
from ggfslam.render.pose import perturbed_T_cw
from ggfslam.render.types import BACKENDS, Intrinsics, RenderOutput, RenderSettings


def select_backend(name: str = "auto") -> str:
    """Resolve a backend name: 'auto' -> 'gsplat' if a CUDA GPU and gsplat are available, else 'cpu'."""
    if name not in BACKENDS:
        raise ConfigError(f"render.backend must be one of {', '.join(BACKENDS)}, got {name!r}")
    if name == "auto":
        return "gsplat" if gsplat_available() else "cpu"
    if name == "gsplat" and not gsplat_available():
        raise GGFSlamError(GSPLAT_MISSING)
    return name


def _check(name: str, t, shape: tuple) -> torch.Tensor:
    if not isinstance(t, torch.Tensor):
        t = torch.as_tensor(np.asarray(t))
    if t.dim() != len(shape) or any(s is not None and a != s for a, s in zip(t.shape, shape)):
        want = "[" + ", ".join("?" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {want}, got {list(t.shape)}")
    if not t.is_floating_point():
        t = t.to(torch.float32)
    return t


def rasterize(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
              colors: torch.Tensor, camera, T_cw, *, extras: torch.Tensor | None = None,
              background: torch.Tensor | None = None, pose_xi: torch.Tensor | None = None,
              settings: RenderSettings | None = None, backend: str | None = None) -> RenderOutput:
    """Render N Gaussians from one pinhole camera.

    Args:
        means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 3] (linear std devs), opacities [N] in [0, 1],
        colors [N, 3]: the Gaussians (see ``ggfslam.render.types`` for conventions).
        camera: ``Camera`` or ``(fx, fy, cx, cy, width, height)``.
        T_cw [4, 4]: world-to-camera pose (tensor or array; may require grad).
        extras [N, K]: optional per-Gaussian channels, alpha-blended with background 0.
        background [3]: colour behind the Gaussians (default black).
        pose_xi [6]: optional tangent ``[omega, v]``; renders at ``T_wc = T_wc0 * Exp(xi)`` (GTSAM
            ``Pose3.retract`` on the camera-to-world pose), so ``xi.grad`` is d/dxi in GTSAM's convention.
        settings: ``RenderSettings`` (near/far, eps2d, depth normalisation threshold, backend).
        backend: overrides ``settings.backend`` ('auto' | 'cpu' | 'reference' | 'gsplat').
    Returns: ``RenderOutput`` (colour, normalised and raw depth, alpha, extras, lazily computed normals,
        radii, visibility, means2d and their gradient after backward).
    """
    settings = settings or RenderSettings()
    name = select_backend(backend or settings.backend)
    intr = Intrinsics.of(camera)
    means = _check("means", means, (None, 3))
    n = means.shape[0]
    quats = _check("quats", quats, (n, 4))
    scales = _check("scales", scales, (n, 3))
    opacities = _check("opacities", opacities, (n,))
    colors = _check("colors", colors, (n, 3))
    if extras is not None:
        extras = _check("extras", extras, (n, None))
        if extras.shape[1] == 0:
            extras = None
    K = 0 if extras is None else extras.shape[1]
    if background is None:
        background = torch.zeros(3)
    background = _check("background", background, (3,))
    T = perturbed_T_cw(T_cw if isinstance(T_cw, torch.Tensor) else torch.as_tensor(np.asarray(T_cw)), pose_xi)
    grad_on = torch.is_grad_enabled() and any(
        t is not None and t.requires_grad
        for t in (means, quats, scales, opacities, colors, extras, background, T))
    probe = None
    if name == "cpu":
        from ggfslam.render.cpu import rasterize_cpu

        def f32(t):
            return None if t is None else t.to(device="cpu", dtype=torch.float32)

        if grad_on:
            probe = torch.zeros(n, 2, requires_grad=True)
        color, depth_raw, alpha, depth, ext, info = rasterize_cpu(
            f32(means), f32(quats), f32(scales), f32(opacities), f32(colors), f32(extras), T.cpu(), intr, settings,
            f32(background), probe)
        return RenderOutput(
            color=color, depth=depth, depth_raw=depth_raw, alpha=alpha, extras=ext if K else None,
            radii=torch.from_numpy(info.radii), visible=torch.from_numpy(info.visible),
            means2d=torch.from_numpy(info.means2d), depths=torch.from_numpy(info.depths), intrinsics=intr,
            backend=name, _means2d_probe=probe)
    elif name == "reference":
        from ggfslam.render.reference import rasterize_reference

        dt = means.dtype
        img, alpha, proj, m2d = rasterize_reference(
            means, quats.to(dt), scales.to(dt), opacities.to(dt), colors.to(dt),
            None if extras is None else extras.to(dt), T, intr, settings, background.to(dt))
        radii = torch.zeros(n, dtype=torch.int32)
        radii[proj.idx] = proj.radii
        visible = radii > 0
        probe = m2d if m2d.requires_grad else None
        means2d = m2d.detach()
        depths = proj.all_depths
    else:
        from ggfslam.render.gsplat_backend import rasterize_gsplat

        img, alpha, radii, probe, depths = rasterize_gsplat(means, quats, scales, opacities, colors, extras, T,
                                                            intr, settings, background)
        visible = radii > 0
        means2d = probe.detach()[0].to(img.device)
        if not probe.requires_grad:
            probe = None
    depth_raw = img[..., 3]
    thr = settings.depth_min_alpha  # the CPU backend does the same inside its kernels
    depth = torch.where(alpha > thr, depth_raw / alpha.clamp_min(max(thr, 1e-12)), torch.zeros_like(depth_raw))
    return RenderOutput(
        color=img[..., :3], depth=depth, depth_raw=depth_raw, alpha=alpha,
        extras=img[..., 4:4 + K] if K else None, radii=radii, visible=visible, means2d=means2d, depths=depths,
        intrinsics=intr, backend=name, _means2d_probe=probe)
