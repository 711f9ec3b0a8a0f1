"""The compiled CPU backend against the plain-torch reference: forward within 1e-4, gradients within 1e-3."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from ggfslam.render import rasterize
from ggfslam.render.scenes import random_gaussians, rotmat_to_quat_wxyz

PARAMS = ("means", "quats", "scales", "opacities", "colors", "extras")


def _tensors(sc: dict) -> dict:
    return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in sc.items() if k in PARAMS}


def _pose(seed: int) -> torch.Tensor:
    """A small random world-to-camera pose near identity (float64)."""
    rng = np.random.default_rng(seed)
    from ggfslam.geometry.se3 import so3_exp

    T = np.eye(4)
    T[:3, :3] = so3_exp(rng.normal(scale=0.05, size=3))
    T[:3, 3] = rng.normal(scale=0.1, size=3)
    return torch.from_numpy(T)


def _thin_diagonal(n: int, seed: int) -> dict:
    """Needle-like Gaussians at 30-60 degrees in the image: exercise the per-row "chord" mode."""
    rng = np.random.default_rng(seed)
    sc = random_gaussians(n, seed=seed, scale_range=(0.003, 0.006), n_extras=2)
    sc["scales"][:, 0] = rng.uniform(0.3, 0.6, n)
    ang = rng.uniform(np.pi / 6, np.pi / 3, n) * rng.choice([-1, 1], n)
    R = np.zeros((n, 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = np.cos(ang), -np.sin(ang), np.sin(ang), np.cos(ang), 1
    sc["quats"] = rotmat_to_quat_wxyz(R).astype(np.float32)
    return sc


def _opaque_stack(n: int, seed: int) -> dict:
    """Opaque, overlapping Gaussians: pixels stop early (T < 1e-4) and alpha hits the 0.99 clamp."""
    sc = random_gaussians(n, seed=seed, spread=(0.3, 0.2, 1.0), scale_range=(0.1, 0.4), opacity_range=(0.9, 1.0),
                          n_extras=1)
    sc["opacities"][: n // 3] = 1.0
    return sc


def _chunks(n: int, seed: int) -> dict:
    """More Gaussians than one work item of the projection kernels (SOA_CHUNK = 256, last chunk partial), with
    every kind of cull mixed in: behind the camera, under 1/255 opacity, off screen."""
    sc = random_gaussians(n, seed=seed, spread=(1.2, 0.9, 0.8), scale_range=(0.01, 0.1), n_extras=3)
    sc["means"][::7, 2] = -1.0
    sc["opacities"][1::7] = 0.002
    sc["means"][2::7, 0] += 30.0
    return sc


SCENES = {
    "random": (lambda: random_gaussians(160, seed=1, n_extras=2), (60.0, 58.0, 31.5, 23.5, 64, 48), 0),
    "odd_size": (lambda: random_gaussians(120, seed=2), (40.0, 41.0, 15.2, 16.7, 37, 29), 3),
    "thin_diagonal": (lambda: _thin_diagonal(60, seed=3), (60.0, 60.0, 31.5, 23.5, 64, 48), 0),
    "opaque_stack": (lambda: _opaque_stack(90, seed=4), (50.0, 50.0, 24.5, 18.5, 48, 40), 5),
    # one to four extras take the kernels' four-channel path (padded); five the general loop
    "five_extras": (lambda: random_gaussians(100, seed=6, n_extras=5), (60.0, 58.0, 31.5, 23.5, 64, 48), 1),
    "chunks": (lambda: _chunks(700, seed=8), (60.0, 58.0, 31.5, 23.5, 64, 48), 2),
}


def _render_pair(name, backend, requires_grad):
    make, cam, pose_seed = SCENES[name]
    sc = _tensors(make())
    leaves = {k: v.clone().requires_grad_(requires_grad) for k, v in sc.items()}
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=requires_grad)
    bg = torch.tensor([0.2, 0.1, 0.4], requires_grad=requires_grad)
    out = rasterize(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["colors"], cam,
                    _pose(pose_seed), extras=leaves.get("extras"), background=bg, pose_xi=xi, backend=backend)
    return out, leaves, xi, bg


@pytest.mark.parametrize("name", list(SCENES))
def test_forward_matches_reference(name):
    with torch.no_grad():
        a, *_ = _render_pair(name, "cpu", False)
        b, *_ = _render_pair(name, "reference", False)
    for field in ("color", "depth_raw", "alpha", "extras"):
        x, y = getattr(a, field), getattr(b, field)
        if y is None:
            assert x is None
            continue
        err = (x - y).abs().max().item()
        assert err <= 1e-4 * max(1.0, y.abs().max().item()), f"{field}: max error {err}"
    assert (a.alpha > 0.5).any()  # the scene is not trivially empty
    # normalised depth: compare where both backends normalise
    m = (a.alpha > 0.05) & (b.alpha > 0.05)
    assert (a.depth - b.depth)[m].abs().max().item() <= 1e-4 * b.depth.abs().max().item()
    assert torch.equal(a.radii, b.radii)
    assert torch.equal(a.visible, b.visible)
    assert torch.allclose(a.means2d, b.means2d, atol=1e-3)
    if name == "opaque_stack":
        assert (a.alpha > 1 - 1.2e-4).any()  # early termination actually happened


def _grads(name, backend):
    out, leaves, xi, bg = _render_pair(name, backend, True)
    H, W = out.alpha.shape
    g = torch.Generator().manual_seed(7)
    loss = ((out.color * torch.rand(H, W, 3, generator=g)).sum() + (out.depth_raw * torch.rand(H, W, generator=g)).sum()
            + (out.alpha * torch.randn(H, W, generator=g)).sum() + (out.depth * torch.rand(H, W, generator=g)).sum())
    if out.extras is not None:
        loss = loss + (out.extras * torch.rand(out.extras.shape, generator=g)).sum()
    loss.backward()
    grads = {k: v.grad for k, v in leaves.items()}
    grads["pose_xi"] = xi.grad
    grads["background"] = bg.grad
    grads["means2d"] = out.means2d_grad()
    return grads


@pytest.mark.parametrize("name", list(SCENES))
def test_gradients_match_reference(name):
    a = _grads(name, "cpu")
    b = _grads(name, "reference")
    for k in b:
        assert a[k] is not None and torch.isfinite(a[k]).all(), k
        scale = b[k].abs().max().item()
        err = (a[k].double() - b[k].double()).abs().max().item()
        assert err <= 1e-3 * scale + 1e-6, f"{name}/{k}: max error {err} vs scale {scale}"
        assert scale > 0, k


def test_depth_sort_is_the_stable_serial_order():
    """The parallel radix sort (several chunks, every digit pass used) orders keys by their upper 32 bits, ties
    in input order, as a stable argsort does."""
    from ggfslam.render.kernels_cpu import RADIX_CHUNK, _radix_sort_hi32

    rng = np.random.default_rng(0)
    n = 3 * RADIX_CHUNK + 17
    hi = rng.integers(0, 2 ** 32, n, dtype=np.uint64)
    hi[::7] = hi[0]  # ties
    keys = (hi << np.uint64(32)) | np.arange(n, dtype=np.uint64)
    want = keys[np.argsort(hi, kind="stable")]
    for workers in (1, 2, 3):
        got = _radix_sort_hi32(keys.copy(), np.empty(n, np.uint64), workers)
        assert np.array_equal(got, want)


def test_tile_lists_do_not_depend_on_the_worker_count():
    """bin_tiles with 1, 2 and 3 workers: the same depth order, tile lists, pair slots and tile costs; every pair of
    a tile in depth order and every (Gaussian, tile) pair listed once."""
    from ggfslam.render import kernels_cpu as kc

    sc = random_gaussians(5000, seed=4, scale_range=(0.005, 0.08))
    W, H = 200, 150
    n = len(sc["means"])
    rec, radii, valid = np.empty((n, kc.REC), np.float32), np.empty(n, np.int32), np.empty(n, np.bool_)
    kc.project_forward(sc["means"], sc["quats"], sc["scales"], sc["opacities"], np.eye(3), np.array([0.0, 0.0, 2.0]),
                       180.0, 180.0, 100.0, 75.0, W, H, 0.05, 100.0, 0.3, rec, radii, valid, 2)
    outs = [kc.bin_tiles(valid, rec, sc["colors"], np.zeros((n, 0), np.float32), W, H, w) for w in (1, 2, 3)]
    for other in outs[1:]:
        for a, b in zip(outs[0], other):
            assert np.array_equal(a, b)
    vis, tile_start, pidx, srec, _, pair_start, slot_pair, _ = outs[0]
    assert valid.sum() == len(vis) > 1000 and tile_start[-1] == len(pidx) == pair_start[-1]
    for t in range(len(tile_start) - 1):
        assert np.all(np.diff(pidx[tile_start[t]:tile_start[t + 1]]) > 0)  # depth ranks ascend within a tile
    assert np.array_equal(np.sort(slot_pair), np.arange(len(pidx)))  # each pair slot used once
    assert np.all(np.diff(srec[:, kc.R_Z]) >= 0)


def _with_extras(sc: dict, k: int) -> dict:
    """The scene's extras cut or zero-padded to k columns (k = 0: none)."""
    sc = dict(sc)
    e = sc.pop("extras", np.zeros((len(sc["means"]), 0), np.float32))[:, :k]
    if k:
        sc["extras"] = np.ascontiguousarray(np.pad(e, ((0, 0), (0, k - e.shape[1]))))
    return sc


@pytest.mark.parametrize("name", ["random", "odd_size", "thin_diagonal", "opaque_stack"])
@pytest.mark.parametrize("k", [0, 4])
def test_vector_lanes_match_the_scalar_pixel_loop(name, k):
    """No extras or four take the kernels' vector lanes, five the scalar pixel loop: the same scene rendered both
    ways (a fifth extra of zeros) gives the same images and gradients, to float32 rounding."""
    make, cam, pose_seed = SCENES[name]
    base = make()
    runs = []
    for kk in (k, 5):
        sc = _tensors(_with_extras(base, kk))
        leaves = {n: v.clone().requires_grad_(True) for n, v in sc.items()}
        out = rasterize(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["colors"],
                        cam, _pose(pose_seed), extras=leaves.get("extras"), backend="cpu")
        H, W = out.alpha.shape
        g = torch.Generator().manual_seed(3)
        loss = ((out.color * torch.rand(H, W, 3, generator=g)).sum() + (out.depth * torch.rand(H, W, generator=g)).sum()
                + (out.alpha * torch.randn(H, W, generator=g)).sum())
        if k:
            loss = loss + (out.extras[..., :k] * torch.rand(H, W, k, generator=g)).sum()
        loss.backward()
        runs.append((out, {n: v.grad for n, v in leaves.items()}))
    (a, ga), (b, gb) = runs
    assert (a.alpha > 0.5).any()
    for field in ("color", "depth_raw", "alpha", "depth"):
        x, y = getattr(a, field), getattr(b, field)
        assert (x - y).abs().max().item() <= 1e-6 * max(1.0, y.abs().max().item()), field
    if k:
        assert (a.extras - b.extras[..., :k]).abs().max().item() <= 1e-6
    for n in ("means", "quats", "scales", "opacities", "colors"):
        scale = gb[n].abs().max().item()
        assert scale > 0 and (ga[n] - gb[n]).abs().max().item() <= 1e-5 * scale, n
    if k:
        assert (ga["extras"] - gb["extras"][:, :k]).abs().max().item() <= 1e-5 * gb["extras"].abs().max().item()
