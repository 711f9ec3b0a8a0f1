"""Render settings, intrinsics and the render output container.

Conventions of the whole ``ggfslam.render`` package
- Gaussians: ``means`` [N, 3] world positions; ``quats`` [N, 4] rotations ordered **w, x, y, z** (the 3DGS
  convention; not necessarily unit length, they are normalised inside); ``scales`` [N, 3] standard
  deviations along the rotated axes, linear (not log), >= 0; ``opacities`` [N] in [0, 1] (already
  activated, not logits); ``colors`` [N, 3] final RGB (view dependence, if any, is decoded upstream);
  ``extras`` [N, K] optional per-Gaussian values blended like colours (the GGF planar probability is
  one of them). All float32 tensors (the reference backend also accepts float64).
  Note: TUM trajectory files order pose quaternions x, y, z, w; that is a different thing.
- Camera: pinhole, OpenCV axes (x right, y down, z forward), a pixel's centre has integer coordinates
  (u, v); intrinsics from a ``ggfslam.data.types.Camera`` or a tuple ``(fx, fy, cx, cy, width, height)``.
- Pose: ``T_cw`` [4, 4] world-to-camera. An optional ``pose_xi`` [6] = [omega, v] perturbs the
  camera-to-world pose on the right, GTSAM style: ``T_wc = T_wc0 * Exp(xi)``, i.e.
  ``T_cw = Exp(-xi) * T_cw0``. Gradients w.r.t. ``pose_xi`` are therefore d/dxi of ``Pose3.retract``.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import torch

from ggfslam.errors import ConfigError

BACKENDS = ("auto", "cpu", "reference", "gsplat")


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels and the image size."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @staticmethod
    def of(camera: Any) -> Intrinsics:
        """From a ``Camera``-like object (fx fy cx cy width height attributes), a tuple or an ``Intrinsics``."""
        if isinstance(camera, Intrinsics):
            return camera
        if isinstance(camera, (tuple, list)):
            if len(camera) != 6:
                raise ValueError("camera tuple must be (fx, fy, cx, cy, width, height)")
            fx, fy, cx, cy, w, h = camera
        else:
            fx, fy, cx, cy, w, h = (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)
        intr = Intrinsics(float(fx), float(fy), float(cx), float(cy), int(w), int(h))
        if not (intr.fx > 0 and intr.fy > 0 and intr.width > 0 and intr.height > 0):
            raise ValueError(f"invalid intrinsics {intr}")
        return intr

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same camera for the image resized to ``width`` x ``height`` (pixel centres kept, as ``Camera.resized``)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5,
                          int(width), int(height))

    def half(self) -> Intrinsics:
        """``scaled`` to half the size (rounded down)."""
        return self.scaled(max(1, self.width // 2), max(1, self.height // 2))

    def crop(self, x0: int, y0: int, width: int, height: int) -> Intrinsics:
        """The camera of the pixels [y0, y0 + height) x [x0, x0 + width) of this one's image."""
        return Intrinsics(self.fx, self.fy, self.cx - x0, self.cy - y0, int(width), int(height))

    def K(self, dtype=torch.float32, device=None) -> torch.Tensor:
        """3x3 intrinsic matrix as a tensor."""
        return torch.tensor([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
                            dtype=dtype, device=device)


@dataclass(frozen=True)
class RenderSettings:
    """Options of a render. The alpha rules (clamp 0.99, skip < 1/255, stop at T < 1e-4) are fixed by the method,
    the tiles (32 x 32 pixels in the CPU kernels, gsplat's own on CUDA) by each backend; neither is a setting."""

    backend: str = "auto"  # auto | cpu | reference | gsplat
    near_plane: float = 0.01  # metres; Gaussians with view depth outside [near, far] are culled
    far_plane: float = 1e10
    eps2d: float = 0.3  # px^2 added to the 2D covariance diagonal (the 3DGS low-pass blur)
    depth_min_alpha: float = 0.01  # ``depth`` is normalised where accumulated alpha > this, else 0

    def __post_init__(self):
        if self.backend not in BACKENDS:
            raise ConfigError(f"render.backend must be one of {', '.join(BACKENDS)}, got {self.backend!r}")
        if not (0 < self.near_plane < self.far_plane):
            raise ConfigError(f"render.near_plane must be in (0, far_plane), got {self.near_plane}")
        if not self.eps2d >= 0:
            raise ConfigError(f"render.eps2d must be >= 0, got {self.eps2d}")
        if not (0 <= self.depth_min_alpha < 1):
            raise ConfigError(f"render.depth_min_alpha must be in [0, 1), got {self.depth_min_alpha}")

    @classmethod
    def from_dict(cls, d: dict | None) -> RenderSettings:
        """From a config ``render:`` section; unknown keys are an error."""
        d = dict(d or {})
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ConfigError(f"unknown render option(s): {', '.join(unknown)} (known: {', '.join(sorted(names))})")
        return cls(**d)


@dataclass
class RenderOutput:
    """What a render returns. Images are [H, W, ...] tensors on the device of the inputs.

    - ``color`` [H, W, 3]: blended colour plus ``(1 - alpha) * background``.
    - ``depth`` [H, W]: metric expected depth, ``depth_raw / alpha`` where ``alpha > depth_min_alpha``,
      else 0. This is what should be compared with sensor depth (GCGR, depth loss).
    - ``depth_raw`` [H, W]: the alpha-blended view depth ``sum_i T_i alpha_i z_i`` (paper eq. 9).
    - ``alpha`` [H, W]: accumulated opacity ``1 - T_final``.
    - ``extras`` [H, W, K] or None: alpha-blended per-Gaussian extras (background 0, not normalised).
    - ``normals`` [H, W, 3] (computed on first access, differentiable): camera-frame unit normals of
      ``depth`` (back-projection, central differences, facing the camera; 0 where undefined).
    - ``radii`` [N] int32: 3-sigma screen radius in pixels, 0 for culled Gaussians.
    - ``visible`` [N] bool: in front of the camera, in range and touching at least one pixel.
    - ``means2d`` [N, 2]: pixel centres (0 for culled ones). After ``backward``, ``means2d_grad()`` gives
      dL/dmeans2d [N, 2] in pixel units (densification statistic; no NDC scaling).
    - ``depths`` [N]: view depth of each Gaussian (detached).
    """

    color: torch.Tensor  # [H, W, 3]
    depth: torch.Tensor  # [H, W]
    depth_raw: torch.Tensor  # [H, W]
    alpha: torch.Tensor  # [H, W]
    extras: torch.Tensor | None  # [H, W, K]
    radii: torch.Tensor  # [N] int32
    visible: torch.Tensor  # [N] bool
    means2d: torch.Tensor  # [N, 2] values (detached)
    depths: torch.Tensor  # [N]
    intrinsics: Intrinsics
    backend: str
    _means2d_probe: torch.Tensor | None = field(default=None, repr=False)
    _normals: torch.Tensor | None = field(default=None, repr=False)

    @property
    def normals(self) -> torch.Tensor:
        """Camera-frame normals [H, W, 3] of ``depth`` (lazily computed, then cached)."""
        if self._normals is None:
            from ggfslam.render.normals import normals_from_depth

            i = self.intrinsics
            self._normals = normals_from_depth(self.depth, i.fx, i.fy, i.cx, i.cy)
        return self._normals

    def means2d_grad(self) -> torch.Tensor:
        """dL/dmeans2d [N, 2] accumulated by the backward passes so far (zeros if none ran)."""
        p = self._means2d_probe
        if p is None or p.grad is None:
            return torch.zeros_like(self.means2d)
        return p.grad.reshape(self.means2d.shape).to(self.means2d.device)

    def means2d_grad_norm(self) -> torch.Tensor:
        """Per-Gaussian norm of dL/dmeans2d [N] (pixels), the 3DGS densification statistic."""
        return self.means2d_grad().norm(dim=-1)
