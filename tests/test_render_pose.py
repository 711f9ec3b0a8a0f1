"""Pose conventions (GTSAM: T_wc = T_wc0 * Exp(xi), xi = [omega, v]) and pose gradients of renders."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest
import torch

from ggfslam.geometry.se3 import invert, look_at
from ggfslam.render import perturbed_T_cw, rasterize, se3_exp
from ggfslam.render.scenes import random_gaussians

CAM = (40.0, 40.0, 19.5, 14.5, 40, 30)


def _sparse_scene(dtype=torch.float32) -> dict:
    """Six large, semi-transparent Gaussians at well separated depths whose 1/255 contours lie outside the
    image: the render is a smooth function of the pose (no alpha cut-off crossings, no depth-order swaps,
    no early stops), so finite differences are meaningful (on dense scenes they are not: PERF_NOTES)."""
    rng = np.random.default_rng(11)
    n = 6
    sc = random_gaussians(n, seed=11, scale_range=(2.5, 3.5), opacity_range=(0.2, 0.5))
    sc["means"] = np.stack([rng.uniform(-0.4, 0.4, n), rng.uniform(-0.3, 0.3, n), 4.0 + 1.2 * np.arange(n)],
                           axis=1).astype(np.float32)
    sc["scales"] *= (sc["means"][:, 2:3] / 4.0)  # keep the screen size as depth grows
    return {k: torch.from_numpy(v).to(dtype) for k, v in sc.items()}


def _T_cw0() -> np.ndarray:
    return invert(look_at(np.array([0.2, -0.1, -0.3]), np.array([0.0, 0.0, 4.0]), up=np.array([0.0, -1.0, 0.0])))


@pytest.mark.parametrize("scale", [1e-9, 1e-4, 0.3, 2.0])
def test_se3_exp_matches_gtsam(scale):
    rng = np.random.default_rng(int(scale * 1e9) % 1000)
    for _ in range(5):
        xi = rng.normal(size=6) * scale
        ours = se3_exp(torch.from_numpy(xi)).numpy()
        ref = gtsam.Pose3.Expmap(xi).matrix()
        assert np.allclose(ours, ref, atol=1e-12, rtol=1e-10)


def test_perturbation_is_gtsam_retract():
    rng = np.random.default_rng(0)
    T_cw0 = _T_cw0()
    for _ in range(5):
        xi = rng.normal(size=6) * 0.2
        T_wc = gtsam.Pose3(invert(T_cw0)).retract(xi).matrix()
        ours = perturbed_T_cw(torch.from_numpy(T_cw0), torch.from_numpy(xi)).numpy()
        assert np.allclose(ours, invert(T_wc), atol=1e-12)


def _loss(out, weights):
    wc, wd = weights
    return (out.color.double() * wc).sum() + (out.depth_raw.double() * wd).sum()


def _weights(dtype=torch.float64):
    g = torch.Generator().manual_seed(3)
    H, W = CAM[5], CAM[4]
    return torch.rand(H, W, 3, generator=g, dtype=dtype), torch.rand(H, W, generator=g, dtype=dtype)


def _fd_grad(f, n=6, h=1e-5):
    g = np.zeros(n)
    for i in range(n):
        e = np.zeros(n)
        e[i] = h
        g[i] = (f(e) - f(-e)) / (2 * h)
    return g


@pytest.mark.parametrize("backend,dtype,h,rtol,atol_rel", [
    ("reference", torch.float64, 1e-6, 1e-4, 1e-6),
    ("cpu", torch.float32, 1e-2, 1e-2, 1e-3),  # the image is float32: larger steps keep rounding noise small
])
def test_pose_gradient_matches_finite_differences(backend, dtype, h, rtol, atol_rel):
    sc = _sparse_scene(dtype)
    T0 = torch.from_numpy(_T_cw0())
    w = _weights()

    def f(xi_np):
        with torch.no_grad():
            out = rasterize(**sc, camera=CAM, T_cw=T0, pose_xi=torch.from_numpy(xi_np), backend=backend)
        return _loss(out, w).item()

    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    out = rasterize(**sc, camera=CAM, T_cw=T0, pose_xi=xi, backend=backend)
    _loss(out, w).backward()
    fd = _fd_grad(f, h=h)
    assert np.allclose(xi.grad.numpy(), fd, rtol=rtol, atol=atol_rel * np.abs(fd).max()), (xi.grad.numpy(), fd)


def test_pose_xi_equals_rendering_at_retracted_pose():
    sc = _sparse_scene()
    T0 = _T_cw0()
    xi = np.array([0.02, -0.01, 0.03, 0.05, -0.02, 0.04])
    T_cw = invert(gtsam.Pose3(invert(T0)).retract(xi).matrix())
    with torch.no_grad():
        a = rasterize(**sc, camera=CAM, T_cw=torch.from_numpy(T0), pose_xi=torch.from_numpy(xi), backend="cpu")
        b = rasterize(**sc, camera=CAM, T_cw=T_cw, backend="cpu")
    assert torch.allclose(a.color, b.color, atol=1e-6)
    assert torch.allclose(a.depth_raw, b.depth_raw, atol=1e-5)


def test_T_cw_gradient_flows_when_it_requires_grad():
    sc = _sparse_scene()
    T = torch.from_numpy(_T_cw0()).requires_grad_(True)
    out = rasterize(**sc, camera=CAM, T_cw=T, backend="cpu")
    out.color.sum().backward()
    assert T.grad is not None and torch.isfinite(T.grad).all() and T.grad[:3].abs().sum() > 0
