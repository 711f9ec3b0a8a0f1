"""The rendering API: backend selection, settings, camera/pose inputs, depth normalisation, normals, stats."""
from __future__ import annotations

import os

import numba
import numpy as np
import pytest
import torch

from ggfslam.data.types import Camera
from ggfslam.errors import ConfigError, GGFSlamError
from ggfslam.geometry.depth import normals_from_depth as normals_np
from ggfslam.render import RenderSettings, normals_from_depth, rasterize, select_backend
from ggfslam.render.gsplat_backend import GSPLAT_MISSING, gsplat_available
from ggfslam.render.scenes import random_gaussians

CAM = (60.0, 58.0, 31.5, 23.5, 64, 48)


def _scene(n=80, seed=0, **kw):
    return {k: torch.from_numpy(v) for k, v in random_gaussians(n, seed=seed, **kw).items()}


def test_select_backend():
    assert select_backend("cpu") == "cpu"
    assert select_backend("reference") == "reference"
    assert select_backend("auto") == ("gsplat" if gsplat_available() else "cpu")
    with pytest.raises(ConfigError):
        select_backend("opengl")
    if not gsplat_available():
        with pytest.raises(GGFSlamError, match="gsplat backend needs a CUDA GPU"):
            select_backend("gsplat")
        assert "pip install ggfslam[cuda]" in GSPLAT_MISSING


def test_settings_from_dict():
    s = RenderSettings.from_dict({"backend": "cpu", "near_plane": 0.05})
    assert s.backend == "cpu" and s.near_plane == 0.05
    with pytest.raises(ConfigError, match="unknown render option"):
        RenderSettings.from_dict({"tile": 8})
    with pytest.raises(ConfigError):
        RenderSettings(backend="vulkan")
    with pytest.raises(ConfigError):
        RenderSettings(near_plane=0.0)


def test_camera_object_numpy_pose_and_settings_backend():
    sc = _scene()
    cam = Camera(fx=60.0, fy=58.0, cx=31.5, cy=23.5, width=64, height=48)
    with torch.no_grad():
        a = rasterize(**sc, camera=cam, T_cw=np.eye(4), settings=RenderSettings(backend="cpu"))
        b = rasterize(**sc, camera=CAM, T_cw=torch.eye(4), backend="cpu")
    assert a.backend == "cpu"
    assert a.color.shape == (48, 64, 3) and a.depth.shape == (48, 64) and a.alpha.shape == (48, 64)
    assert a.extras is None
    assert torch.equal(a.color, b.color)
    with pytest.raises(ValueError, match="quats must have shape"):
        rasterize(sc["means"], sc["quats"][:, :3], sc["scales"], sc["opacities"], sc["colors"], CAM, np.eye(4))


def test_depth_is_normalised_raw_depth():
    sc = _scene()
    s = RenderSettings(backend="cpu", depth_min_alpha=0.2)
    with torch.no_grad():
        out = rasterize(**sc, camera=CAM, T_cw=np.eye(4), settings=s)
    m = out.alpha > 0.2
    assert m.any() and (~m).any()
    assert torch.allclose(out.depth[m], out.depth_raw[m] / out.alpha[m])
    assert (out.depth[~m] == 0).all()
    # a single opaque Gaussian facing the camera: metric depth at its centre equals its view depth
    one = {k: v[:1].clone() for k, v in sc.items()}
    one["means"][0] = torch.tensor([0.0, 0.0, 3.0])
    one["scales"][0] = torch.tensor([0.5, 0.5, 0.01])
    one["quats"][0] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    one["opacities"][0] = 0.9
    with torch.no_grad():
        o1 = rasterize(**one, camera=CAM, T_cw=np.eye(4), backend="cpu")
    assert abs(o1.depth[23, 31].item() - 3.0) < 1e-5
    assert abs(o1.depths[0].item() - 3.0) < 1e-6


def test_extras_blend_like_colours():
    sc = _scene(n_extras=2)
    sc["extras"] = torch.cat([sc["colors"][:, :1], torch.ones(len(sc["colors"]), 1)], dim=1)
    with torch.no_grad():
        out = rasterize(**sc, camera=CAM, T_cw=np.eye(4), backend="cpu")
    assert torch.allclose(out.extras[..., 0], out.color[..., 0], atol=1e-6)  # black background
    assert torch.allclose(out.extras[..., 1], out.alpha, atol=1e-6)  # blending ones gives alpha


def test_normals_match_numpy_convention_and_plane():
    # tilted plane z = 2 + 0.3 x (camera frame), seen by a pinhole camera
    fx, fy, cx, cy, W, H = 50.0, 50.0, 19.5, 14.5, 40, 30
    _, u = np.mgrid[0:H, 0:W].astype(np.float64)
    xn = (u - cx) / fx
    depth = 2.0 / (1.0 - 0.3 * xn)
    depth[5, 7] = 0.0  # a hole
    ref = normals_np(depth, fx, fy, cx, cy)
    ours = normals_from_depth(torch.from_numpy(depth), fx, fy, cx, cy).numpy()
    assert np.allclose(ours, ref, atol=1e-9)
    n_true = np.array([0.3, 0.0, -1.0]) / np.linalg.norm([0.3, 0.0, -1.0])  # faces the camera
    assert np.allclose(ours[15, 20], n_true, atol=1e-6)
    assert (ours[5, 7] == 0).all() and (ours[0] == 0).all()
    d = torch.from_numpy(depth).requires_grad_(True)
    normals_from_depth(d, fx, fy, cx, cy).sum().backward()
    assert torch.isfinite(d.grad).all()


def test_render_output_normals_are_lazy_and_differentiable():
    sc = {k: v.requires_grad_(True) for k, v in _scene().items()}
    out = rasterize(**sc, camera=CAM, T_cw=np.eye(4), backend="cpu")
    assert out._normals is None
    n = out.normals
    assert n.shape == (48, 64, 3) and out.normals is n
    norm = n.norm(dim=-1)
    assert torch.allclose(norm[norm > 0], torch.ones_like(norm[norm > 0]), atol=1e-5)
    n[..., 2].sum().backward()
    assert torch.isfinite(sc["means"].grad).all() and sc["means"].grad.abs().sum() > 0


def test_means2d_gradient_statistic():
    sc = {k: v.requires_grad_(True) for k, v in _scene().items()}
    out = rasterize(**sc, camera=CAM, T_cw=np.eye(4), backend="cpu")
    assert (out.means2d_grad() == 0).all()  # before backward
    out.color.sum().backward()
    g = out.means2d_grad_norm()
    assert g.shape == (80,) and torch.isfinite(g).all()
    assert (g[~out.visible] == 0).all() and (g[out.visible] > 0).any()
    with torch.no_grad():
        o2 = rasterize(**sc, camera=CAM, T_cw=np.eye(4), backend="cpu")
    assert o2._means2d_probe is None and (o2.means2d_grad_norm() == 0).all()


def test_a_second_backward_of_one_cpu_render_says_what_to_do():
    sc = {k: v.requires_grad_(True) for k, v in _scene().items()}
    out = rasterize(**sc, camera=CAM, T_cw=np.eye(4), backend="cpu")
    loss = out.color.sum() + out.depth.sum()
    g1, = torch.autograd.grad(loss, sc["means"], retain_graph=True)
    assert torch.isfinite(g1).all() and g1.abs().sum() > 0
    with pytest.raises(RuntimeError, match="backward ran twice on one render.*render again"):
        loss.backward()
    out = rasterize(**sc, camera=CAM, T_cw=np.eye(4), backend="cpu")  # a new render gives the same gradient
    g2, = torch.autograd.grad(out.color.sum() + out.depth.sum(), sc["means"])
    torch.testing.assert_close(g1, g2)


def test_thread_count_does_not_change_results():
    sc = {k: v.requires_grad_(True) for k, v in _scene(200, seed=3).items()}
    res = []
    old = numba.get_num_threads()
    try:
        for nt in sorted({1, old}):
            numba.set_num_threads(nt)
            for v in sc.values():
                v.grad = None
            out = rasterize(**sc, camera=CAM, T_cw=np.eye(4), backend="cpu")
            (out.color.sum() + out.depth_raw.sum()).backward()
            res.append((out.color.detach().clone(), sc["means"].grad.clone()))
    finally:
        numba.set_num_threads(old)
    for c, g in res[1:]:
        assert torch.equal(c, res[0][0]) and torch.equal(g, res[0][1])


def test_numba_cache_outside_repository():
    import ggfslam.render.kernels_cpu  # noqa: F401

    cache = os.environ.get("NUMBA_CACHE_DIR", "")
    assert cache
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    assert not os.path.abspath(cache).startswith(repo + os.sep)


def test_allocator_tuning_opt_out(monkeypatch):
    from ggfslam.render import cpu

    monkeypatch.setattr(cpu, "_ALLOCATOR_TUNED", None)
    monkeypatch.setenv("GGFSLAM_MALLOC_TUNING", "0")
    assert cpu.tune_allocator() is False
    monkeypatch.delenv("GGFSLAM_MALLOC_TUNING")
    assert cpu.tune_allocator() is False  # tried once per process; later calls report that result


def test_a_gpu_whose_gsplat_fails_to_import_is_reported_once(monkeypatch, caplog):
    import builtins
    import logging

    from ggfslam.render import gsplat_backend

    real_import = builtins.__import__

    def broken(name, *a, **kw):
        if name == "gsplat":
            raise OSError("libcudart.so.12: cannot open shared object file")
        return real_import(name, *a, **kw)

    monkeypatch.setattr(gsplat_backend.torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(gsplat_backend, "_GSPLAT_IMPORTS", None)
    monkeypatch.setattr(builtins, "__import__", broken)
    with caplog.at_level(logging.WARNING, logger="ggfslam.render"):
        assert not gsplat_backend.gsplat_available()
        assert not gsplat_backend.gsplat_available()
    warnings = [r.getMessage() for r in caplog.records if "gsplat does not import" in r.getMessage()]
    assert len(warnings) == 1 and "libcudart" in warnings[0]
