"""GCGR factors (factors/gcgr.py): Jacobians against GTSAM's numerical derivative, pose pull-back on a textureless
scene, whitening and the per-row Huber kernel, the first-order model, and the factors inside local BA.

The scene is a room corner (back wall, floor, left wall) of flat, uniformly grey Gaussians: no texture for
features, but three non-parallel planes that fix all six degrees of freedom of a depth camera.
"""
from __future__ import annotations

import json
from types import SimpleNamespace

import cv2
import gtsam
import numpy as np
import pytest
import torch
from gtsam.symbol_shorthand import X
from gtsam.utils.numerical_derivative import numericalDerivative11

from factors.gcgr import (
    DEPTH_WEIGHT, GCGRModel, MapView, NORMAL_WEIGHT, SensorView, eliminate_offset, locally_flat, residual_rows,
    select_pixels, whitened_rows,
)
from ggfslam.config import GCGRConfig, config_from_dict
from ggfslam.errors import ConfigError
from ggfslam.geometry.se3 import invert
from ggfslam.ggf.amr import quat_z_to
from ggfslam.render.api import rasterize
from ggfslam.render.types import Intrinsics, RenderSettings

INTR = Intrinsics(40.0, 40.0, 39.5, 29.5, 80, 60)  # wide (90 degrees): all three planes in view
XI_START = np.array([0.01, -0.02, 0.015, 0.03, -0.02, 0.04])  # [omega, v]: 1.5 degrees, 5.4 cm off


def _plane(origin, a, b, na, nb, spacing, normal):
    i, j = np.meshgrid(np.arange(na), np.arange(nb), indexing="ij")
    pts = origin + (i.reshape(-1, 1) * a + j.reshape(-1, 1) * b) * spacing
    return pts, np.tile(normal, (na * nb, 1))


def _corner(spacing: float = 0.03):
    """Surfels (means [N, 3], quats [N, 4], scales [N, 3]) on three planes; the camera at the origin looks +z."""
    ex, ey, ez = np.eye(3)
    parts = [_plane(np.array([-1.5, -1.2, 3.0]), ex, ey, int(3 / spacing), int(2.2 / spacing), spacing, -ez),
             _plane(np.array([-1.5, 1.0, 0.3]), ex, ez, int(3 / spacing), int(2.7 / spacing), spacing, -ey),
             _plane(np.array([-1.2, -1.2, 0.3]), ey, ez, int(2.2 / spacing), int(2.7 / spacing), spacing, ex)]
    means = torch.tensor(np.concatenate([p for p, _ in parts]), dtype=torch.float32)
    quats = quat_z_to(torch.tensor(np.concatenate([n for _, n in parts]), dtype=torch.float32))
    scales = torch.tensor([[0.6 * spacing, 0.6 * spacing, 1e-4]]).repeat(len(means), 1)
    return means, quats, scales


@pytest.fixture(scope="module")
def scene():
    means, quats, scales = _corner()
    n = len(means)
    settings = RenderSettings(backend="cpu")

    def render_out(T_wc):
        return rasterize(means, quats, scales, torch.full((n,), 0.95), torch.full((n, 3), 0.5), INTR,
                         torch.from_numpy(invert(T_wc)).float(), extras=torch.ones(n, 1), settings=settings)

    def render(T_wc):
        return MapView.from_render(render_out(T_wc))

    truth = np.eye(4)
    sensor = SensorView.from_depth(render(truth).depth, INTR)  # the "sensor" sees the map at the true pose
    return render, render_out, sensor, truth


def _start() -> np.ndarray:
    return gtsam.Pose3.Expmap(XI_START).matrix()


def _relative_error(J: np.ndarray, num: np.ndarray) -> float:
    return float(np.linalg.norm(J - num) / np.linalg.norm(num))


def test_analytic_jacobians_match_numerical_derivative_of_renders(scene):
    render, _, sensor, _ = scene
    model = GCGRModel(0, render, sensor, _start(), GCGRConfig(pixels=400))
    assert len(model) == 400 and model.valid.all()
    pose = gtsam.Pose3(_start())
    for kind, tol in (("depth", 0.06), ("normal", 0.45)):
        # the step is the factor's trust region (relinearize_translation): the first-order model is used there
        num = numericalDerivative11(lambda p: model.rendered_rows(p.matrix())[kind], pose, 0.01)
        J = model.jacobians[kind]
        assert _relative_error(J, num) < tol, kind
        # and GTSAM sees the same Jacobian through the factor
        H = [None]
        model.evaluate(kind, pose, H)
        np.testing.assert_allclose(H[0], J)
    # depth: measured 2.8 % (the blended centre depths of surfels are not exactly the plane); normals 33 %
    # (rendered normals are central differences of that blended depth: small-scale noise the ray-plane model
    # does not have). The normal rows' derivatives are ~1e-3 of the depth rows', so the pose is set by depth.
    Jd = model.jacobians["depth"]
    assert np.linalg.norm(model.jacobians["normal"]) < 0.01 * np.linalg.norm(Jd)
    assert np.linalg.matrix_rank(Jd) == 6  # three planes: every direction is observed


def test_central_jacobians_are_gtsam_central_differences(scene):
    render, _, sensor, _ = scene
    cfg = GCGRConfig(pixels=200, jacobian="central", step=0.005)
    model = GCGRModel(0, render, sensor, _start(), cfg)
    assert model.renders == 13
    pose = gtsam.Pose3(_start())
    for kind in ("depth", "normal"):
        num = numericalDerivative11(lambda p: model.rendered_rows(p.matrix())[kind], pose, cfg.step)
        ok = model.valid & (np.abs(num).sum(1) < 1.0)  # rows that stay valid at all 12 renders
        np.testing.assert_allclose(model.jacobians[kind][ok], num[ok], atol=1e-9)


def test_gcgr_alone_pulls_a_perturbed_pose_back_on_a_textureless_scene(scene):
    render, render_out, sensor, truth = scene
    # reprojection factors have nothing to hold on to: ORB finds (almost) no corner on the uniform surfaces
    grey = (render_out(truth).color.numpy() * 255).astype(np.uint8)
    assert len(cv2.ORB_create(500).detect(cv2.cvtColor(grey, cv2.COLOR_RGB2GRAY), None)) < 20
    for xi0 in (XI_START, np.array([0.03, 0.02, -0.02, -0.06, 0.05, -0.05])):
        model = GCGRModel(0, render, sensor, gtsam.Pose3.Expmap(xi0).matrix(), GCGRConfig())
        graph = gtsam.NonlinearFactorGraph()
        for f in model.factors().values():
            graph.add(f)
        values = gtsam.Values()
        values.insert(X(0), gtsam.Pose3.Expmap(xi0))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(30)
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize().atPose3(X(0))
        err = gtsam.Pose3.Logmap(gtsam.Pose3(truth).between(result))
        assert np.degrees(np.linalg.norm(err[:3])) < 0.02  # from 1.5-2.4 degrees
        assert np.linalg.norm(err[3:]) < 1e-3  # from 5-9 cm
        assert model.renders <= 6  # the first-order model between renders: no render per error() call


def test_eliminated_offset_is_the_schur_complement_of_a_free_offset():
    rng = np.random.default_rng(3)
    J, r = rng.normal(size=(50, 6)), rng.normal(size=50)  # [N, 6], [N]
    valid = rng.random(50) > 0.2
    r2, J2 = eliminate_offset(r, J, valid)
    # least squares over (xi, c) with rows r + J xi + c: the same xi as over the eliminated rows
    A = np.concatenate([J[valid], np.ones((valid.sum(), 1))], axis=1)
    xi_c = np.linalg.lstsq(A, -r[valid], rcond=None)[0]
    xi = np.linalg.lstsq(J2[valid], -r2[valid], rcond=None)[0]
    np.testing.assert_allclose(xi, xi_c[:6], atol=1e-10)
    assert (r2[~valid] == 0).all() and (J2[~valid] == 0).all()
    assert abs(r2[valid].sum()) < 1e-9 and np.abs(J2[valid].sum(0)).max() < 1e-9


def test_free_depth_offset_ignores_a_constant_depth_shift(scene):
    render, _, sensor, truth = scene
    shifted = SensorView(np.where(sensor.depth > 0, sensor.depth + 0.02, 0.0), sensor.normals, sensor.intr)
    ends = {}
    for free in (False, True):
        model = GCGRModel(0, render, shifted, truth, GCGRConfig(pixels=400, free_depth_offset=free))
        graph = gtsam.NonlinearFactorGraph()
        graph.add(model.factor("depth"))
        values = gtsam.Values()
        values.insert(X(0), gtsam.Pose3(truth))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(20)
        end = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize().atPose3(X(0))
        ends[free] = gtsam.Pose3.Logmap(gtsam.Pose3(truth).between(end))
        if free:  # the depth rows' Jacobian checked against numerical derivatives of the eliminated rows
            def rows_at(p):
                rd, _, valid = residual_rows(render(p.matrix()), shifted, model.pixels)
                return eliminate_offset(rd, np.zeros((len(rd), 6)), valid)[0]

            num = numericalDerivative11(rows_at, gtsam.Pose3(truth), 0.01)
            assert _relative_error(model.jacobians["depth"], num) < 0.1
            assert np.abs(model.rows0["depth"]).max() < 2e-3  # a 2 cm shift: gone from the rows
    # a sensor 2 cm deeper than the map everywhere pulls the camera 2 cm back without the free offset ...
    assert np.linalg.norm(ends[False][3:]) > 0.01
    # ... and leaves it where it is with it
    assert np.linalg.norm(ends[True][3:]) < 2e-3 and np.degrees(np.linalg.norm(ends[True][:3])) < 0.05


def test_error_is_the_huber_sum_of_whitened_rows_and_linearize_whitens(scene):
    render, _, sensor, _ = scene
    cfg = GCGRConfig(pixels=300, sigma=0.002, effective_pixels=100)  # a tight sigma: rows on both sides of Huber
    model = GCGRModel(3, render, sensor, _start(), cfg)
    values = gtsam.Values()
    values.insert(X(3), gtsam.Pose3(_start()))
    k = cfg.huber
    for kind in ("depth", "normal"):
        factor = model.factor(kind)
        assert list(factor.keys()) == [X(3)] and factor.dim() == len(model)
        w = whitened_rows(model, kind, gtsam.Pose3(_start()))
        assert model.row_sigma == pytest.approx(cfg.sigma * np.sqrt(3))
        a = np.abs(w)
        rho = np.where(a <= k, 0.5 * w ** 2, k * a - 0.5 * k * k)  # Huber per row (scalar reweighting)
        assert factor.error(values) == pytest.approx(rho.sum(), rel=1e-9)
        if kind == "depth":
            assert (a > k).sum() > 10 and (a <= k).sum() > 10  # both sides of the kernel are exercised
        # linearize: rows whitened by sigma and scaled by sqrt(Huber weight)
        lin = factor.linearize(values)
        A, b = lin.jacobian()
        sw = np.sqrt(np.where(a <= k, 1.0, k / np.maximum(a, 1e-300)))[:, None]
        np.testing.assert_allclose(A, sw * model.jacobians[kind] / model.row_sigma, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(b, -sw[:, 0] * w, rtol=1e-9, atol=1e-9)
    # without the kernel a row's error would be quadratic: Huber makes a far row count linearly
    assert model.noise().loss(100.0) == pytest.approx(k * 10.0 - 0.5 * k * k)


def test_first_order_model_between_renders_and_relinearization(scene):
    render, _, sensor, _ = scene
    cfg = GCGRConfig(pixels=300)
    model = GCGRModel(0, render, sensor, _start(), cfg)
    n0 = model.renders
    small = np.array([0.001, 0.0, 0.0, 0.001, 0.0, -0.002])  # 0.06 degrees, 2.2 mm: inside the trust region
    pose = gtsam.Pose3(_start()).retract(small)
    rows = model.evaluate("depth", pose)
    assert model.renders == n0  # error() at a trial step renders nothing
    np.testing.assert_allclose(rows, model.rows0["depth"] + model.jacobians["depth"] @ small)
    # ... and the first-order model is close to a fresh render there
    exact = model.rendered_rows(pose.matrix())["depth"]
    assert np.abs(rows - exact).mean() < 0.05 * np.abs(exact - model.rows0["depth"]).mean() + 1e-4
    far = gtsam.Pose3(_start()).retract(np.array([0.0, 0.0, 0.0, 0.0, 0.02, 0.0]))  # 2 cm: past the threshold
    n1 = model.renders
    rows = model.evaluate("depth", far)  # error() there: still the first-order model
    assert model.renders == n1 and not model.T0.equals(far, 1e-12)
    H = [None]
    rows = model.evaluate("depth", far, H)  # a linearization there renders again
    assert model.renders == n1 + 1 and model.T0.equals(far, 1e-12)
    np.testing.assert_allclose(rows, model.rendered_rows(far.matrix())["depth"])
    np.testing.assert_array_equal(H[0], model.jacobians["depth"])


def test_pixel_selection_gates_and_budget():
    H, W = 20, 30
    intr = Intrinsics(30.0, 30.0, 14.5, 9.5, W, H)
    depth = np.full((H, W), 2.0)
    sensor = SensorView.from_depth(depth, intr)
    view = MapView(depth.copy(), sensor.normals.copy(), np.ones((H, W)), np.ones((H, W)))
    view.weight[:, :5] = 0.2  # not planar
    view.alpha[:5, :] = 0.5  # not opaque
    view.depth[10, 10] = 2.5  # gross depth mismatch
    view.normals = SensorView.from_depth(view.depth, intr).normals  # the render's normals see the bump
    cfg = GCGRConfig(pixels=1000)
    pix = select_pixels(view, sensor, cfg)
    u, v = pix % W, pix // W
    assert (u >= 5).all() and (v >= 5).all() and 10 * W + 10 not in pix
    assert not np.isin([9 * W + 10, 11 * W + 10, 10 * W + 9], pix).any()  # its neighbours' normals see the bump
    assert len(select_pixels(view, sensor, GCGRConfig(pixels=50))) == 50
    spread = select_pixels(view, sensor, GCGRConfig(pixels=50)) // W
    assert spread.min() <= 6 and spread.max() >= H - 3  # spread over the image, not the first rows
    rd, rn, valid = residual_rows(view, sensor, pix)
    assert valid.all() and np.allclose(rd, 0) and np.allclose(rn, 0)
    view.depth[6, 20] += 0.02
    rd, _, _ = residual_rows(view, sensor, np.array([6 * W + 20]))
    assert rd[0] == pytest.approx(DEPTH_WEIGHT * 0.02) and NORMAL_WEIGHT == 0.05
    assert not locally_flat(sensor.normals, 0.99)[0].any()  # the border has no neighbours


class _SceneMapper:
    """What ``GCGRSource`` reads of a ``Mapper``, over the corner scene."""

    def __init__(self, render_out):
        self.intr, self.iteration, self.store = INTR, 0, {}
        self.map = SimpleNamespace(n_anchors=1)
        self.render_out, self.left_out = render_out, []

    def render(self, T_wc, intr, without_kf=None):
        self.left_out.append(without_kf)
        return self.render_out(T_wc)


def test_training_renders_become_models_without_renders_of_their_own(scene):
    from ggfslam.backend.gcgr_source import GCGRSource

    _, render_out, sensor, truth = scene
    mapper = _SceneMapper(render_out)
    src = GCGRSource(mapper, None, GCGRConfig(harvest_every=10, renders_per_ba=0))
    for k in (1, 2):
        src.add_keyframe(k, sensor.depth)
    # the first harvest_every steps after a keyframe's first step are skipped (its new anchors echo its depth)
    assert not src.wants(1, 5) and not src.wants(1, 14) and src.wants(1, 15)
    src.offer(1, truth, 15, render_out(truth))
    assert not src.wants(1, 24) and src.wants(1, 25)
    mapper.iteration = 30
    labels = [(k, kind) for k, kind, _ in src.window_factors({1: truth, 2: _start()})]
    assert labels == [(1, "depth"), (1, "normal")] and src.renders == 0  # keyframe 2 has no view yet
    # one render per BA: the keyframe without a view gets its own; keyframe 1's training view is reused
    src.cfg = GCGRConfig(harvest_every=10, renders_per_ba=1)
    labels = [(k, kind) for k, kind, _ in src.window_factors({1: truth, 2: _start()})]
    assert sorted(labels) == [(1, "depth"), (1, "normal"), (2, "depth"), (2, "normal")] and src.renders == 1
    with pytest.raises(ConfigError, match="renders_per_ba"):
        GCGRSource(mapper, None, GCGRConfig(harvest_every=0, renders_per_ba=0))
    # a keyframe's view without its own anchors: training renders (which have them) cannot serve
    src = GCGRSource(mapper, None, GCGRConfig(harvest_every=10, exclude_own_anchors=True))
    src.add_keyframe(3, sensor.depth)
    assert not src.wants(3, 100)
    mapper.left_out.clear()
    assert len(src.window_factors({3: truth})) == 2 and mapper.left_out == [3]


def test_relinearize_drop_renders_nothing_in_bundle_adjustment(scene):
    from ggfslam.backend.gcgr_source import GCGRSource

    _, render_out, sensor, truth = scene
    near = gtsam.Pose3(truth).retract(np.array([0.0, 0.0, 0.0, 0.003, 0.0, 0.0]))  # 3 mm: inside the trust region
    far = gtsam.Pose3(truth).retract(np.array([0.0, 0.0, 0.0, 0.0, 0.02, 0.0]))  # 2 cm: past it
    renders = {}
    for mode in ("render", "drop"):
        mapper = _SceneMapper(render_out)
        src = GCGRSource(mapper, None, GCGRConfig(harvest_every=10, renders_per_ba=0, relinearize=mode))
        src.add_keyframe(1, sensor.depth)
        assert "gcgr.harvest_every = 10 steps" in src.unused_warning()  # a run that ended here: GCGR did nothing
        assert not src.wants(1, 0) and src.wants(1, 10)
        src.offer(1, truth, 10, render_out(truth))  # a training render at the truth
        mapper.iteration = 20
        if mode == "drop":  # a keyframe that has moved past the threshold since that render gets no factor
            assert src.window_factors({1: far.matrix()}) == [] and src.models_stale == 1
        (_, _, f), _ = src.window_factors({1: near.matrix()})
        values = gtsam.Values()
        values.insert(X(1), far)
        f.linearize(values)  # LM linearizing there
        renders[mode] = src.renders
        assert src.unused_warning() is None
        model, _ = src.cached_models()[1]
        assert model.T0.equals(far if mode == "render" else gtsam.Pose3(truth), 1e-12)
    assert renders == {"render": 1, "drop": 0}


def test_config_needs_the_map():
    with pytest.raises(ConfigError, match="gcgr.enabled needs mapping.enabled"):
        config_from_dict({"dataset": {"kind": "synthetic"}, "gcgr": {"enabled": True},
                          "mapping": {"enabled": False}}, "test")
    with pytest.raises(ValueError, match="sigma"):
        GCGRConfig(sigma=0)


def _small_run_config(tmp_path, **gcgr):
    return config_from_dict({"name": "gcgr", "dataset": {"kind": "synthetic", "synthetic": {
        "n_frames": 24, "width": 320, "height": 240, "depth_noise": True}},
        "tracking": {"keyframe_max_frames": 6},
        "mapping": {"train_width": 160, "iterations_per_keyframe": 30, "final_iterations": 0, "eval_stride": 8,
                    "mesh": False},
        "gcgr": {"enabled": True, **gcgr}}, "test")


def test_system_run_with_gcgr_in_local_ba_and_per_frame(tmp_path, monkeypatch):
    from ggfslam import slam
    from ggfslam.backend import local_ba

    monkeypatch.setenv("GGFSLAM_CACHE", str(tmp_path / "cache"))
    seen = []
    orig = local_ba.local_graph

    def spy(*args, **kwargs):
        lg = orig(*args, **kwargs)
        if lg is not None:
            seen.append((lg.n_gcgr, set(lg.window) - lg.fixed))
        return lg

    monkeypatch.setattr(local_ba, "local_graph", spy)
    metrics = slam.run(_small_run_config(tmp_path, per_frame="on"), tmp_path / "run", progress=False)
    g = metrics["backend"]["gcgr"]
    # once the map has trained, every optimized keyframe of a local BA carries a depth and a normal factor, but the
    # newest: by default (renders_per_ba None -> 0) its view comes from training, harvest_every steps later
    with_factors = [(n, free) for n, free in seen if n > 0]
    assert with_factors and all(2 * (len(free) - 1) <= n <= 2 * len(free) for n, free in with_factors[-2:])
    assert any(n == 2 * len(free) for n, free in with_factors)  # and in a later BA the newest has its factors too
    assert g["factors"] == sum(n for n, _ in seen) and g["pixels_mean"] > 100
    assert g["frames_refined"] > 10  # per-frame GCGR ran on the tracked frames
    assert metrics["trajectory"]["ate_rmse_cm"] < 3.0
    # graph.json holds the GCGR factors the latest local BAs used, with their pixels and current errors
    graph = json.loads((tmp_path / "run" / "graph.json").read_text())
    gf = [f for f in graph["factors"] if f["type"].startswith("gcgr_")]
    kfs = {k["id"] for k in graph["keyframes"]}
    assert {f["type"] for f in gf} == {"gcgr_depth", "gcgr_normal"} and {f["kf"] for f in gf} <= kfs
    assert graph["meta"]["factors_by_type"]["gcgr_depth"]["count"] == len(gf) // 2
    for f in gf:
        w, h = f["resolution"]
        uv = np.asarray(f["pixels"])
        assert f["keys"] == [f"x{f['kf']}"] and len(uv) > 100 and 0 < f["valid"] <= len(uv)
        assert (uv >= 0).all() and (uv[:, 0] < w).all() and (uv[:, 1] < h).all()
        # GTSAM's error is the Huber-robust cost: positive, at most half the unrobust chi2
        assert 0 < f["error"] <= 0.5 * f["chi2"] + 1e-9 and f["sigma"] > 0
    depth_rmse = [f["rows_rmse"] for f in gf if f["type"] == "gcgr_depth"]
    assert 0 < np.median(depth_rmse) < 0.05  # metres: the map agrees with the keyframes' depth to a few cm
    # the backend's GCGR source is not pickled into the checkpoint (the map is saved by the mapper)
    from ggfslam.checkpoint import load_checkpoint, unpickle_tracker

    assert unpickle_tracker(load_checkpoint(tmp_path / "run")).backend.gcgr is None
