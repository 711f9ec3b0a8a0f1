"""Surfels' ray-plane depth (``ggfslam.render.plane_depth``): exact on a tilted surfel, the expected depth for
Gaussians without a plane, and its gradient against finite differences."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from ggfslam.ggf.amr import quat_z_to
from ggfslam.render import rasterize
from ggfslam.render.plane_depth import PLANE_CHANNELS, plane_channels, plane_depth
from ggfslam.render.types import Intrinsics, RenderSettings

INTR = Intrinsics(fx=60.0, fy=60.0, cx=31.5, cy=23.5, width=64, height=48)
MIN_ALPHA = RenderSettings().depth_min_alpha  # what the renderer's own depth uses


def _tilted_surfel(dtype=torch.float32, tilt_deg: float = 40.0):
    """One wide opaque surfel 2 m ahead, its normal tilted about the y axis (camera = world frame)."""
    a = np.deg2rad(tilt_deg)
    n = torch.tensor([[np.sin(a), 0.0, -np.cos(a)]], dtype=dtype)
    means = torch.tensor([[0.1, -0.05, 2.0]], dtype=dtype)
    quats = quat_z_to(n)
    scales = torch.tensor([[0.5, 0.4, 1e-4]], dtype=dtype)
    return means, quats, scales, n


def _render(means, quats, scales, opac, n, planar, backend="cpu"):
    planes = plane_channels(means, n, planar)
    out = rasterize(means, quats, scales, opac, torch.full_like(means, 0.5), INTR, torch.eye(4, dtype=means.dtype),
                    extras=planes, backend=backend)
    return out, plane_depth(out.extras[..., :PLANE_CHANNELS], out.alpha, out.depth, INTR, MIN_ALPHA)


def _rays() -> torch.Tensor:
    """Every pixel's ray [H, W, 3] (z = 1), float64, written here independently of ``pixel_rays``."""
    v, u = np.mgrid[0:INTR.height, 0:INTR.width].astype(np.float64)
    return torch.from_numpy(np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u)], -1))


def _ray_plane(n: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Depth [H, W] where each pixel's ray meets the plane through p with normal n."""
    nn, pp = n[0].double(), p[0].double()
    return (nn @ pp) / (_rays() @ nn)


def test_tilted_surfel_depth_is_where_the_ray_meets_its_plane():
    means, quats, scales, n = _tilted_surfel()
    out, z = _render(means, quats, scales, torch.tensor([0.9]), n, torch.tensor([True]))
    truth = _ray_plane(n, means)
    inside = out.alpha > 0.5
    assert inside.sum() > 300  # the surfel covers much of the image
    assert (z - truth).abs()[inside].max() < 1e-4
    # the expected depth gives every pixel the centre's depth: centimetres off across the tilted surfel
    assert (out.depth - truth).abs()[inside].max() > 0.1
    assert (out.depth[inside] - 2.0).abs().max() < 1e-4


def test_gaussians_without_a_plane_keep_the_expected_depth():
    rng = np.random.default_rng(0)
    means = torch.tensor(rng.uniform([-0.5, -0.4, 1.5], [0.5, 0.4, 3.0], (40, 3)), dtype=torch.float32)
    quats = torch.nn.functional.normalize(torch.tensor(rng.normal(size=(40, 4)), dtype=torch.float32), dim=1)
    scales = torch.tensor(rng.uniform(0.05, 0.2, (40, 3)), dtype=torch.float32)
    opac = torch.tensor(rng.uniform(0.3, 0.9, 40), dtype=torch.float32)
    n = torch.nn.functional.normalize(torch.tensor(rng.normal(size=(40, 3)), dtype=torch.float32), dim=1)
    out, z = _render(means, quats, scales, opac, n, torch.zeros(40, dtype=torch.bool))
    assert (out.alpha > 0.5).sum() > 500
    assert torch.allclose(z, out.depth, atol=1e-5, rtol=1e-5)


def test_two_surfels_of_one_plane_blend_to_that_plane():
    """Where two overlapping surfels of the same plane blend, the depth is still that plane's (the expected
    depth averages their two centre depths)."""
    means, quats, scales, n = _tilted_surfel()
    t = torch.tensor([[0.3, 0.0, 0.3 * np.tan(np.deg2rad(40.0))]], dtype=torch.float32)  # along the plane
    means2 = torch.cat([means, means + t])
    out, z = _render(means2, quats.repeat(2, 1), scales.repeat(2, 1), torch.tensor([0.5, 0.5]), n.repeat(2, 1),
                     torch.tensor([True, True]))
    ok = out.alpha > 0.3
    assert (z - _ray_plane(n, means)).abs()[ok].max() < 1e-4


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_plane_depth_gradient_matches_finite_differences(backend):
    """d(sum of w * depth)/d(surfel mean) over the surfel's inner pixels (alpha > 0.2, which a small move never
    changes): float64 reference and compiled float32 kernel against central differences and against the
    closed form: only the plane's offset d = n . mean sets the depth there, so the gradient is
    sum(w / (n . r)) n, none of it along the plane."""
    means, quats, scales, n = _tilted_surfel(torch.float64)
    opac = torch.tensor([0.9], dtype=torch.float64)
    with torch.no_grad():
        out, _ = _render(means, quats, scales, opac, n, torch.tensor([True]), backend)
    w = torch.from_numpy(np.random.default_rng(1).uniform(0.5, 1.5, (INTR.height, INTR.width)))
    w = w * (out.alpha.double() > 0.2)

    def loss(m):
        _, z = _render(m, quats, scales, opac, n, torch.tensor([True]), backend)
        return (w * z.double()).sum()

    m = means.clone().requires_grad_(True)
    loss(m).backward()
    h = 1e-3
    num = torch.zeros(3, dtype=torch.float64)
    with torch.no_grad():
        for k in range(3):
            e = torch.zeros_like(means)
            e[0, k] = h
            num[k] = (loss(means + e) - loss(means - e)) / (2 * h)
    nn = -n[0]  # the plane's normal as plane_channels orients it: away from the camera
    closed = (w / (_rays() @ nn)).sum() * nn
    tol = 1e-6 if backend == "reference" else 1e-2
    assert torch.allclose(m.grad[0], closed, rtol=tol, atol=tol * closed.abs().max())
    assert torch.allclose(num, closed, rtol=10 * tol, atol=10 * tol * closed.abs().max())
