"""Differentiable SE(3) in torch, GTSAM conventions, for pose gradients of renders.

- Tangent ``xi = [omega, v]`` (rotation first); ``Exp(xi)`` = ``gtsam.Pose3.Expmap(xi)``:
  ``R = exp(omega^)``, ``t = V(omega) v`` with ``V = I + (1 - cos th)/th^2 W + (th - sin th)/th^3 W^2``.
- The renderer's pose perturbation is on the right of camera-to-world (``Pose3.retract``):
  ``T_wc = T_wc0 * Exp(xi)``  =>  ``T_cw = Exp(-xi) * T_cw0``. So d(render)/d(xi) at xi = 0 is exactly the
  Jacobian a GTSAM ``CustomFactor`` on that camera's ``Pose3`` needs.
All math in float64 (the 4x4 pose is tiny; the precision matters for finite-difference checks).
"""
from __future__ import annotations

import torch


def hat(omega: torch.Tensor) -> torch.Tensor:
    """Skew matrix [3, 3] of a 3-vector."""
    z = torch.zeros((), dtype=omega.dtype, device=omega.device)
    wx, wy, wz = omega[0], omega[1], omega[2]
    return torch.stack([
        torch.stack([z, -wz, wy]),
        torch.stack([wz, z, -wx]),
        torch.stack([-wy, wx, z]),
    ])


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """GTSAM ``Pose3.Expmap``: 4x4 pose [4, 4] from ``xi = [omega, v]`` [6]; smooth at xi = 0."""
    xi = xi.to(torch.float64)
    omega, v = xi[:3], xi[3:]
    th2 = (omega * omega).sum()
    small = th2 < 1e-8
    th2s = torch.where(small, torch.ones_like(th2), th2)
    th = torch.sqrt(th2s)
    a = torch.where(small, 1.0 - th2 / 6.0, torch.sin(th) / th)
    b = torch.where(small, 0.5 - th2 / 24.0, (1.0 - torch.cos(th)) / th2s)
    c = torch.where(small, 1.0 / 6.0 - th2 / 120.0, (th - torch.sin(th)) / (th2s * th))
    W = hat(omega)
    W2 = W @ W
    eye = torch.eye(3, dtype=torch.float64, device=xi.device)
    R = eye + a * W + b * W2
    V = eye + b * W + c * W2
    t = V @ v
    top = torch.cat([R, t[:, None]], dim=1)
    bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64, device=xi.device)
    return torch.cat([top, bottom], dim=0)


def perturbed_T_cw(T_cw: torch.Tensor, pose_xi: torch.Tensor | None) -> torch.Tensor:
    """World-to-camera [4, 4] float64 after the right perturbation ``T_wc = T_wc0 Exp(xi)``."""
    T = torch.as_tensor(T_cw).to(torch.float64)
    if T.shape != (4, 4):
        raise ValueError(f"T_cw must be [4, 4], got {tuple(T.shape)}")
    if pose_xi is None:
        return T
    xi = torch.as_tensor(pose_xi).to(device=T.device)
    if xi.shape != (6,):
        raise ValueError(f"pose_xi must be [6] = [omega, v], got {tuple(xi.shape)}")
    return se3_exp(-xi.to(torch.float64)) @ T
