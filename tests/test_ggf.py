"""Geometric-Gaussian Field: the prior and field formulas, AMR's surfels, AOF's rules, and the field inside
the mapper (planar-weight channel, no gradient crossing between map and net, checkpoint, planarity PLY)."""
import copy
import math
import tempfile

import numpy as np
import pytest
import torch

from ggfslam.config import ConfigError, GGFConfig, MappingConfig, config_from_dict
from ggfslam.eval.image import normal_error_deg
from ggfslam.gaussians.anchor_map import AnchorMap
from ggfslam.gaussians.ply import read_gaussians_ply
from ggfslam.ggf import GeometricGaussianField, planarity_colors
from ggfslam.ggf.amr import morph_loss, quat_z_to, shortest_axis, surfel_shape
from ggfslam.ggf.aof import (CONSOLIDATION, EVOLUTION, SUPPRESSION, feedback_loss, feedback_targets,
                             posterior_flatness)
from ggfslam.ggf.features import (F_IN, PlaneBorrowing, anchor_geometry, borrow_planes, local_geometry,
                                  positional_encoding)
from ggfslam.ggf.field import ResidualField, planar_prior, planar_probability
from ggfslam.ggf.morph_kernels import morph_loss_raw
from ggfslam.render.api import rasterize
from ggfslam.render.projection import quat_to_rotmat
from ggfslam.render.types import RenderSettings

CFG = GGFConfig()


# --- features ----------------------------------------------------------------------------------------
def test_positional_encoding_layout_and_values():
    p = torch.tensor([[0.25, -0.5, 1.0 / 3.0]])
    g = positional_encoding(p)
    assert g.shape == (1, 36) and F_IN == 41
    for i in range(6):
        for j in range(3):
            x = (2 ** i) * math.pi * p[0, j].item()
            assert g[0, 3 * i + j].item() == pytest.approx(math.sin(x), abs=1e-5)
            assert g[0, 18 + 3 * i + j].item() == pytest.approx(math.cos(x), abs=1e-5)


def _grid(n=20, spacing=0.04):
    u, v = np.meshgrid(np.arange(n) * spacing, np.arange(n) * spacing)
    return np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], 1)


def test_local_geometry_plane_and_sphere():
    rng = np.random.default_rng(0)
    plane = _grid() @ np.linalg.qr(rng.normal(size=(3, 3)))[0].T  # a tilted plane
    n, k, s, _ = local_geometry(plane, 16)
    R = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]
    assert np.abs(np.abs(n @ R[:, 2]) - 1).max() < 1e-4  # normal of the tilted plane, up to sign
    assert k.max() < 1e-6
    assert np.median(s) == pytest.approx(0.04 * 1.5, rel=0.35)  # mean distance to 8 grid neighbours
    d = rng.normal(size=(300, 3))
    sphere = 0.1 * d / np.linalg.norm(d, axis=1, keepdims=True)
    n, k = local_geometry(sphere, 32)[:2]  # 32 of 300 points: a patch of radius ~6 cm
    assert np.median(k) > CFG.tau  # a 10 cm ball is curved at that patch size
    radial = sphere / 0.1
    assert np.median(np.abs((n * radial).sum(1))) > 0.95  # normals are radial
    # weights: an outlier standing for one sample barely tilts a plane of points standing for 100
    pts = np.concatenate([_grid(6), [[0.1, 0.1, 0.05]]])
    w = np.concatenate([np.full(36, 100.0), [1.0]])
    k_w = local_geometry(pts, 37, w).curvature
    k_u = local_geometry(pts, 37).curvature
    assert k_w[0] < 0.1 * k_u[0]


def _edge_and_cylinder(spacing=0.04, arc=np.pi):
    """Points of a floor (z = 0, x in [0, 1]) meeting a wall (x = 0, z in [0, 1]) along the y axis, and of a
    1 m tall cylinder of radius 0.2 m (the part within ``arc`` radians of the x axis), on a ``spacing`` grid."""
    t = np.arange(0, 1.0 + 1e-9, spacing)
    a, y = np.meshgrid(t, t, indexing="ij")
    floor = np.stack([a.ravel(), y.ravel(), np.zeros(a.size)], 1)
    wall = np.stack([np.zeros(a.size), y.ravel(), a.ravel()], 1)[a.ravel() > 0]
    ph = np.arange(-arc, arc + 1e-9, spacing / 0.2)
    P, Z = np.meshgrid(ph, t, indexing="ij")
    cyl = np.stack([5 + 0.2 * np.cos(P.ravel()), 0.2 * np.sin(P.ravel()), Z.ravel()], 1)
    return np.concatenate([floor, wall]), cyl


def test_curvature_sees_a_long_cylinder_patch():
    """The side of a 0.2 m pillar a camera sees (+-45 deg) gives patches long along the axis: against that
    length (METHOD.md's lambda_0 / sum) it reads planar at the ~0.25 m patch, against the narrower extent not."""
    _, cyl = _edge_and_cylinder(arc=np.pi / 4)
    k = local_geometry(cyl, 32, cell=0.08).curvature
    k_sum = local_geometry(cyl, 32, cell=0.08, curvature_norm="sum").curvature
    assert k.min() > CFG.tau
    assert np.median(k_sum) < 0.6 * CFG.tau


def test_plane_borrowing_at_an_edge():
    """Points beside a wall-floor edge: their own patch spans both faces and reads curved; a flat patch of a
    neighbour inside their face lends its plane, its normal included. A cylinder gains nothing from it."""
    edge, cyl = _edge_and_cylinder()
    borrow = PlaneBorrowing(k=96, tol=0.02, factor=4.0, min_curvature=CFG.tau / 2)
    x = edge[:, 0]
    near = (x > 0.02) & (x < 0.18) & (edge[:, 2] == 0) & (edge[:, 1] > 0.3) & (edge[:, 1] < 0.7)  # floor by the wall
    n0, k0, _, p0 = local_geometry(edge, 32, cell=0.08)
    n1, k1, _, p1 = local_geometry(edge, 32, cell=0.08, borrow=borrow)
    assert np.median(k0[near]) > CFG.tau  # without borrowing the edge reads curved
    assert k1[near].max() < CFG.tau / 2
    assert np.abs(n1[near, 2]).min() > 0.999  # the floor's normal, not a tilted mix of floor and wall
    assert np.abs(n0[near, 2]).min() < 0.99
    assert np.abs(p1[near, 2]).max() < 0.0075  # projected onto (nearly) the floor's plane, not the mixed
    assert np.median(np.abs(p0[near, 2])) > 0.02  # patch's tilted and offset one
    assert np.array_equal(k1[k0 <= CFG.tau / 2], k0[k0 <= CFG.tau / 2])  # flat points keep their patch
    kc0 = local_geometry(cyl, 32, cell=0.08).curvature
    kc1 = local_geometry(cyl, 32, cell=0.08, borrow=borrow).curvature
    assert kc1.min() > 2 * CFG.tau and kc1.min() == kc0.min()  # no patch on it is flat enough to lend


def test_plane_borrowing_kernel_matches_the_array_formula():
    """``borrow_planes``' compiled loop against the same rule written with whole arrays: every point takes the
    first flattest lending patch among its k nearest, if flatter than its own."""
    edge, _ = _edge_and_cylinder()
    rng = np.random.default_rng(3)
    pts = edge + rng.normal(0, 0.004, edge.shape)  # noisy: many candidates lend, many do not
    borrow = PlaneBorrowing(k=24, tol=0.01, factor=4.0, min_curvature=0.0)
    n0, k0, _, _ = local_geometry(pts, 32, cell=0.08)
    cen = pts + rng.normal(0, 0.01, pts.shape)
    thick = rng.uniform(0, 0.01, len(pts)).astype(np.float32)
    got_n, got_c, got_p = borrow_planes(pts, n0, k0, cen, thick, borrow, chunk=500)
    idx = np.argsort(((pts[:, None] - pts[None]) ** 2).sum(-1), axis=1, kind="stable")[:, :borrow.k + 1]  # [N, k]
    off = np.abs(np.einsum("nkd,nkd->nk", n0[idx].astype(np.float64), pts[:, None, :] - cen[idx]))
    cand = np.where(off <= 2.0 * thick[idx].astype(np.float64) + borrow.tol, borrow.factor * k0[idx], np.inf)
    best = cand.argmin(axis=1)
    flat = cand[np.arange(len(pts)), best]
    pick = flat < k0
    lender = idx[np.arange(len(pts)), best]
    assert 0.05 < pick.mean() < 0.95
    np.testing.assert_array_equal(got_c, np.where(pick, flat, k0))
    np.testing.assert_array_equal(got_n, np.where(pick[:, None], n0[lender], n0))
    np.testing.assert_array_equal(got_p, np.where(pick[:, None], cen[lender], cen))


def _plane_map(n=12, spacing=0.04, obs=5.0):
    """An anchor map whose anchors and surface points lie on z = 1 (observed ``obs`` times, no colour change)."""
    amap = AnchorMap(spacing, seed=0)
    pts = _grid(n, spacing) + [0, 0, 1.0]
    vals, _ = amap.new_anchor_values(pts, np.full((len(pts), 3), 0.5, np.float32), source_kf=0)
    amap.append(vals)
    with torch.no_grad():
        amap.surface[:] = torch.from_numpy(pts).float()[: amap.n_anchors]
        amap.surface_n[:] = 10
        amap.obs[:] = obs
        amap.obs_color[:] = 0.5 * obs
        amap.obs_color_sq[:] = 0.25 * obs
    return amap


def test_anchor_geometry_features_and_orientation():
    amap = _plane_map()
    geo = anchor_geometry(amap, {0: np.array([0.2, 0.2, 3.0])}, 16, CFG.tau)
    a = amap.n_anchors
    assert geo.features.shape == (a, F_IN)
    assert torch.allclose(geo.normals, torch.tensor([0.0, 0.0, 1.0]).expand(a, 3), atol=1e-4)  # towards the camera
    assert geo.curvature.max() < 1e-6 and geo.color_var.abs().max() < 1e-6
    assert torch.allclose(geo.plane_points, amap.surface, atol=1e-5)  # on the plane already
    assert torch.allclose(geo.features[:, 40], torch.log1p(torch.tensor(5.0)).expand(a))


def test_field_state_without_a_geometry_field_is_recomputed():
    """A checkpoint whose cached geometry lacks a field (written by an older version) is not trusted: the
    next refresh recomputes it, with the same result as a fresh field."""
    amap = _plane_map()
    cams = {0: np.array([0.2, 0.2, 3.0])}
    field = GeometricGaussianField(GGFConfig(), amap.voxel_size)
    field.refresh(amap, cams)
    st = copy.deepcopy(field.state())
    del st["geom"]["plane_points"]
    old = GeometricGaussianField(GGFConfig(), amap.voxel_size)
    old.load_state(st)
    assert old.geom is None
    assert old.refresh(amap, cams)
    assert torch.equal(old.geom.plane_points, field.geom.plane_points) and torch.equal(old.p2d(), field.p2d())


def test_observations_accumulate_surface_and_colour_variance():
    amap = AnchorMap(0.1, seed=0)
    vals, _ = amap.new_anchor_values(np.array([[0.05, 0.05, 0.05]]), np.full((1, 3), 0.5, np.float32))
    amap.append(vals)
    amap.add_surface_points(np.array([[0.02, 0.05, 0.03], [0.04, 0.05, 0.03], [0.5, 0.5, 0.5]]))
    assert amap.surface[0].tolist() == pytest.approx([0.03, 0.05, 0.03])
    amap.add_surface_points(np.array([[0.09, 0.05, 0.03]]))
    assert amap.surface[0].tolist() == pytest.approx([0.05, 0.05, 0.03], abs=1e-6)
    assert amap.surface_n[0].item() == 3
    amap.add_observation(np.array([0]), np.array([[0.2, 0.4, 0.6]]))
    amap.add_observation(np.array([0]), np.array([[0.4, 0.4, 0.2]]))
    assert amap.obs[0].item() == 2
    # per channel variances 0.01, 0, 0.04 -> mean 0.05 / 3
    assert amap.color_variance()[0].item() == pytest.approx(0.05 / 3, rel=1e-4)


# --- field -------------------------------------------------------------------------------------------
def test_prior_formula_on_hand_made_inputs():
    kappa = torch.tensor([0.0, 0.01, 0.05, 0.0, 0.0])
    var = torch.tensor([0.0, 0.0, 0.0, 0.05, 0.0])
    obs = torch.tensor([10.0, 10.0, 10.0, 10.0, 1.0])
    p = planar_prior(kappa, var, obs, tau=0.02, w1=200.0, w2=20.0, t0=3.0)
    sig = lambda x: 1 / (1 + math.exp(-x))  # noqa: E731
    phi10, phi1 = 1 - math.exp(-10 / 3), 1 - math.exp(-1 / 3)
    expected = [sig(4.0) * phi10, sig(2.0) * phi10, sig(-6.0) * phi10, sig(4.0) * math.exp(-1.0) * phi10,
                sig(4.0) * phi1]
    assert p.tolist() == pytest.approx(expected, rel=1e-5)


def test_zero_initialised_field_equals_prior():
    net = ResidualField(64)
    feats = torch.randn(50, F_IN)
    assert torch.equal(net(feats), torch.zeros(50))
    prior = torch.rand(50) * 0.98 + 0.01
    assert torch.allclose(planar_probability(prior, net(feats)), prior, atol=1e-6)
    # the clamp keeps logit finite at the ends
    assert planar_probability(torch.tensor([0.0, 1.0]), torch.zeros(2)).tolist() == pytest.approx([1e-4, 1 - 1e-4])
    # a residual moves P_2D in logit space
    assert planar_probability(torch.tensor([0.5]), torch.tensor([math.log(3.0)])).item() == pytest.approx(0.75)


# --- AMR ---------------------------------------------------------------------------------------------
def test_quat_z_to_turns_z_onto_the_normal():
    n = torch.nn.functional.normalize(torch.randn(200, 3), dim=1)
    n = torch.cat([n, torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])])
    R = quat_to_rotmat(quat_z_to(n))
    assert torch.allclose((R[:, :, 2] * n).sum(-1).abs(), torch.ones(len(n)), atol=1e-5)


def test_amr_shortest_axis_parallel_to_normal_and_scales():
    g = torch.Generator().manual_seed(1)
    n_ = 300
    quats = torch.randn(n_, 4, generator=g)
    scales = torch.rand(n_, 3, generator=g) * 0.02 + 0.001
    means = torch.randn(n_, 3, generator=g)
    normals = torch.nn.functional.normalize(torch.randn(n_, 3, generator=g), dim=1)
    surface = torch.randn(n_, 3, generator=g)
    radius = torch.full((n_,), 0.008)
    q, s, m = surfel_shape(quats, scales, means, normals, surface, radius, 4e-5)
    axis, length = shortest_axis(q, s)
    assert torch.allclose((axis * normals).sum(-1).abs(), torch.ones(n_), atol=1e-5)
    assert torch.allclose(length, torch.full((n_,), 4e-5))
    assert torch.equal(s[:, :2], torch.maximum(scales[:, :2], radius[:, None]))
    assert ((m - surface) * normals).sum(-1).abs().max() < 1e-5  # on the anchor's plane
    # the in-plane position is the decoder's
    t = means - m
    assert torch.allclose(torch.linalg.cross(t, normals), torch.zeros_like(t), atol=1e-5)


def test_morph_loss_values_and_gradient():
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0], [math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0]])
    s = torch.tensor([[0.01, 0.01, 0.001], [0.01, 0.01, 0.001]])
    loss = morph_loss(q, s, n, eps=0.001, unit=0.04)
    # child 0: aligned and thin -> 0; child 1: shortest axis turned 90 degrees -> 1 - 0 = 1
    assert loss.item() == pytest.approx(0.5, abs=1e-6)
    s2 = s.clone().requires_grad_(True)
    morph_loss(q[:1], s2[:1] * torch.tensor([1.0, 1.0, 3.0]), n[:1], eps=0.001, unit=0.04).backward()
    assert s2.grad[0, 2].item() > 0  # thickness above eps is pushed down



@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_compiled_morph_loss_matches_the_reference(dtype):
    """morph_loss_raw (compiled, on the covariance MLP's raw output) against morph_loss on the same children in
    plain torch: value and gradients wrt raw_cov and log_scale, with children sharing anchors, some below eps."""
    gen = torch.Generator().manual_seed(3)
    M, k, S = 40, 6, 90
    raw_cov = torch.randn(M, k, 7, generator=gen, dtype=dtype)
    raw_cov[:5, :, :3] -= 6.0  # thin children: s_a < eps, the relu inactive
    log_scale = (torch.randn(M, 3, generator=gen, dtype=dtype) * 0.5 - 3.0)
    flat = torch.randperm(M * k, generator=gen)[:S]
    m_idx, j_idx = flat // k, flat % k
    normals = torch.nn.functional.normalize(torch.randn(S, 3, generator=gen, dtype=dtype), dim=1)
    eps, unit = 1e-3, 0.04

    def reference(rc, ls):
        cov = rc[m_idx, j_idx]  # [S, 7]
        return morph_loss(cov[:, 3:], torch.exp(ls[m_idx]) * torch.sigmoid(cov[:, :3]), normals, eps, unit, 0.7, 1.3)

    rc1, ls1 = raw_cov.clone().requires_grad_(), log_scale.clone().requires_grad_()
    rc2, ls2 = raw_cov.clone().requires_grad_(), log_scale.clone().requires_grad_()
    ref = reference(rc1, ls1)
    ref.backward()
    got = morph_loss_raw(rc2, ls2, m_idx, j_idx, normals, eps, unit, 0.7, 1.3)
    (got * 2.0).backward()  # the upstream gradient is applied
    tol = 1e-10 if dtype == torch.float64 else 2e-5
    assert got.dtype == dtype
    assert got.item() == pytest.approx(ref.item(), rel=tol, abs=tol)
    torch.testing.assert_close(rc2.grad, 2.0 * rc1.grad, rtol=tol * 10, atol=tol)
    torch.testing.assert_close(ls2.grad, 2.0 * ls1.grad, rtol=tol * 10, atol=tol)
    assert float(ls2.grad.abs().sum()) > 0 and float(rc2.grad[..., 3:].abs().sum()) > 0
    if dtype == torch.float64:
        torch.autograd.gradcheck(lambda rc, ls: morph_loss_raw(rc, ls, m_idx, j_idx, normals, eps, unit, 0.7, 1.3),
                                 (raw_cov.clone().requires_grad_(), log_scale.clone().requires_grad_()))


def _looking_down(cam: np.ndarray) -> np.ndarray:
    """World-to-camera pose [4, 4] of a camera at ``cam`` looking along world -z (OpenCV axes)."""
    T_cw = np.eye(4)
    T_cw[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T_cw[:3, 3] = -T_cw[:3, :3] @ cam
    return T_cw


def _render_plane_alpha(amr: bool, snap: bool = False):
    amap = _plane_map(n=16)
    with torch.no_grad():
        amap.decoder.opacity[-1].bias.fill_(3.0)  # opaque children, as after training on a solid wall
    field = GeometricGaussianField(GGFConfig(amr=amr, snap=snap), amap.voxel_size)
    field.refresh(amap, {0: np.array([0.3, 0.3, 3.0])})
    assert bool(field.planar().all())
    cam = np.array([0.3, 0.3, 1.6])
    g = amap.decode(cam)
    g2, _ = field.shape(g)
    T_cw = _looking_down(cam)
    out = rasterize(g2.means, g2.quats, g2.scales, g2.opacities, g2.colors, (300.0, 300.0, 39.5, 39.5, 80, 80),
                    torch.from_numpy(T_cw).float(), settings=RenderSettings(backend="cpu"))
    return out, g2


@pytest.mark.parametrize("snap", [False, True])
def test_flat_plane_is_covered_without_holes_after_amr(snap):
    out, g = _render_plane_alpha(amr=True, snap=snap)
    # the plane spans x, y in [0, 0.6] at 0.6 m from the camera: about 300 px wide, so the centre 40x40 px
    # is well inside it
    interior = out.alpha[20:60, 20:60]
    assert interior.min().item() > 0.99
    axis, length = shortest_axis(g.quats, g.scales)
    assert length.max().item() == pytest.approx(GGFConfig().surfel_eps * 0.04)
    if snap:  # surfels moved onto the plane: rendered depth is the plane's depth
        assert torch.allclose(out.depth[20:60, 20:60], torch.full((40, 40), 0.6), atol=2e-3)


# --- AOF ---------------------------------------------------------------------------------------------
def test_posterior_flatness_per_anchor():
    scales = torch.tensor([[1.0, 2.0, 4.0], [2.0, 2.0, 2.0], [0.1, 5.0, 5.0]])
    post, count = posterior_flatness(scales, torch.tensor([0, 0, 2]), 3)
    assert post.tolist() == pytest.approx([0.25, 0.0, 0.98])
    assert count.tolist() == [2, 0, 1]


def test_aof_chooses_the_target_of_each_regime():
    p_post = torch.tensor([0.9, 0.2, 0.55, 0.65])
    prior = torch.tensor([0.5, 0.8, 0.5, 0.5])
    target, weight, regime = feedback_targets(p_post, prior, margin=0.2, lambda_con=0.1)
    assert regime.tolist() == [EVOLUTION, SUPPRESSION, CONSOLIDATION, CONSOLIDATION]
    assert target.tolist() == pytest.approx([0.9, 0.8, 0.55, 0.65])
    assert weight.tolist() == pytest.approx([1.0, 1.0, 0.1, 0.1])
    p2d = torch.tensor([0.5, 0.5, 0.5, 0.5])
    bce = lambda p, t: -(t * math.log(p) + (1 - t) * math.log(1 - p))  # noqa: E731
    expected = (bce(0.5, 0.9) + bce(0.5, 0.8) + 0.1 * bce(0.5, 0.55) + 0.1 * bce(0.5, 0.65)) / 4
    assert feedback_loss(p2d, target, weight).item() == pytest.approx(expected, rel=1e-5)


def test_aof_moves_the_field_towards_its_target_and_not_the_gaussians():
    amap = _plane_map(obs=0.3)  # rarely seen: low prior, so free children that are flat mean evolution
    field = GeometricGaussianField(GGFConfig(lr=0.01), amap.voxel_size)
    field.refresh(amap, {0: np.array([0.2, 0.2, 3.0])})
    assert not bool(field.planar().any())
    g = amap.decode(np.array([0.2, 0.2, 3.0]))
    flat = torch.cat([g.scales[:, :2], g.scales[:, :1] * 0.05], 1)  # P_post = 0.95
    g.scales = flat
    before = {k: v.detach().clone() for k, v in amap.named_parameters()}
    p0 = field.p2d().clone()
    for _ in range(20):
        field.feedback(g)
    assert float((field.p2d() - p0).min()) > 0.05  # evolution raised P_2D everywhere
    for k, v in amap.named_parameters():
        assert v.grad is None, k
        assert torch.equal(v.detach(), before[k]), k


def test_render_loss_does_not_reach_the_field():
    amap = _plane_map()
    field = GeometricGaussianField(GGFConfig(), amap.voxel_size)
    field.refresh(amap, {0: np.array([0.2, 0.2, 3.0])})
    g, l_morph = field.shape(amap.decode(np.array([0.2, 0.2, 3.0])))
    p2d = field.p2d()[g.anchor_index][:, None]
    T_cw = _looking_down(np.array([0.2, 0.2, 3.0]))
    out = rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, (200.0, 200.0, 31.5, 31.5, 64, 64),
                    torch.from_numpy(T_cw).float(), extras=p2d, settings=RenderSettings(backend="cpu"))
    (out.color.sum() + out.depth.sum() + out.extras.sum() + l_morph).backward()
    assert all(p.grad is None for p in field.net.parameters())
    assert amap.features.grad is not None and amap.offsets.grad is not None


# --- in the mapper -----------------------------------------------------------------------------------
def _mapper(ds, poses, store=None, **ggf):
    from ggfslam.mapping.mapper import Mapper

    return Mapper(MappingConfig(train_width=160, densify_from=10, densify_every=10), ds.camera,
                  RenderSettings(backend="cpu"), lambda: dict(poses), store or tempfile.mkdtemp(), ggf=GGFConfig(**ggf))


def test_mapper_with_field_renders_planar_weight_and_resumes(sequence, tmp_path):
    from ggfslam.mapping.outputs import write_planarity_ply

    ds, gt = sequence, sequence.gt_poses
    poses = {}
    m = _mapper(ds, poses, aof_every=2)
    for kf, fi in enumerate((0, 15)):
        poses[kf] = gt[fi]
        f = ds[fi]
        m.add_keyframe(kf, fi, f.rgb, f.depth)
        m.train(15, focus=kf)
    assert m.ggf.updates > 0 and m.grown + m.pruned >= 0
    st = m.ggf.stats()
    assert 0.3 < st["planar_fraction"] <= 1.0  # the room is mostly walls, floor and boxes
    out = m.render(gt[5])
    w = out.extras[..., 0]
    assert w.shape == out.alpha.shape and float(w.min()) >= 0 and float(w.max()) <= 1 + 1e-5
    assert float((w > 0.5).float().mean()) > 0.2  # planar weight image: the walls are planar
    # planarity PLY: the same Gaussians as the map PLY, red for 2D and blue for 3D
    n = write_planarity_ply(m, tmp_path / "p.ply")
    ply = read_gaussians_ply(tmp_path / "p.ply")
    assert len(ply["means"]) == n == len(m.bake_gaussians())
    # checkpoint: a restored mapper has the same field and renders the same images
    m2 = _mapper(ds, poses, store=m.store.dir, aof_every=2)
    m2.load_state(copy.deepcopy(m.state()))  # as a checkpoint file would: no tensors shared with m
    assert torch.equal(m2.ggf.p2d(), m.ggf.p2d())
    assert torch.equal(m2.render(gt[5]).color, out.color)
    m.train(4)
    m2.train(4)
    assert torch.equal(m2.ggf.p2d(), m.ggf.p2d())


@pytest.mark.parametrize("orientation", ["field", "decoder"])
def test_mapper_with_plane_depth_renders_surfel_planes(sequence, orientation):
    """With ``ggf.plane_depth`` the map's depth is where each pixel's ray meets its surfels' planes (the field's
    normals, or with ``surfel_orientation: decoder`` each surfel's own flat axis, through the children's means;
    written here in world coordinates, d = n . (mean - camera centre)), the planar-weight channel still comes back
    alone, and training runs on that depth."""
    from ggfslam.render.plane_depth import plane_depth
    from ggfslam.render.projection import quat_to_rotmat

    ds, gt = sequence, sequence.gt_poses
    poses = {0: gt[0]}
    m = _mapper(ds, poses, plane_depth=True, surfel_orientation=orientation)
    f = ds[0]
    m.add_keyframe(0, 0, f.rgb, f.depth)
    m.train(10, focus=0)
    assert np.isfinite(m.last_losses["depth"]) and m.last_losses["depth"] > 0
    T_wc = gt[3]
    out = m.render(T_wc)
    assert out.extras.shape[-1] == 1  # P_2D only: the plane channels are consumed
    with torch.no_grad():
        g, _ = m._decode_view(T_wc, m.intr)
        planar = m.ggf.planar()[g.anchor_index]
        assert 0 < int(planar.sum()) < len(g)
        if orientation == "field":
            n_w = m.ggf.geom.normals[g.anchor_index].double()
        else:
            n_w = quat_to_rotmat(g.quats.double())[:, :, 2]
            flat = g.scales[planar]
            assert torch.all(flat[:, 2] < flat[:, :2].min(1).values)  # the local z axis is the flat one
        d = (n_w * (g.means.double() - torch.from_numpy(T_wc[:3, 3]))).sum(-1)
        sign = torch.where(d < 0, -1.0, 1.0).double()
        R_cw = torch.from_numpy(T_wc[:3, :3].T)
        n_c = (n_w * sign[:, None]) @ R_cw.T
        z_c = g.means.double() @ R_cw.T - R_cw @ torch.from_numpy(T_wc[:3, 3])
        planes = torch.where(planar[:, None], torch.cat([n_c, (d * sign)[:, None]], 1),
                             torch.cat([torch.zeros_like(n_c[:, :2]), torch.ones_like(d[:, None]), z_c[:, 2:]], 1))
        ref = rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, m.intr,
                        torch.from_numpy(np.linalg.inv(T_wc)).float(), extras=planes.float(), settings=m.settings)
        expect = plane_depth(ref.extras, ref.alpha, ref.depth, m.intr, m.settings.depth_min_alpha)
        # with the depth-spread moments rendered beside the planes and P_2D, each comes back in its own place
        both, moments = m._rasterize(g, m.intr, T_wc, m._planar_channel(g), depth_moments=True)
    assert torch.allclose(out.depth, expect, atol=1e-4)
    assert torch.allclose(both.depth, out.depth, atol=1e-5) and both.extras.shape[-1] == 1
    assert torch.allclose(both.extras, out.extras, atol=1e-5)
    assert torch.allclose(moments[..., 0], both.depth_raw, rtol=1e-4, atol=1e-5)
    assert float((out.depth - ref.depth).abs().max()) > 1e-3  # tilted surfels: not the centres' depth


def test_field_off_is_the_plain_mapper(sequence):
    ds, gt = sequence, sequence.gt_poses
    poses = {0: gt[0]}
    m = _mapper(ds, poses, enabled=False)
    assert m.ggf is None
    f = ds[0]
    m.add_keyframe(0, 0, f.rgb, f.depth)
    m.train(3, focus=0)
    assert m.render(gt[0]).extras is None
    with pytest.raises(RuntimeError, match="ggf.enabled"):
        m.planarity()


def test_planarity_colours_and_config_validation():
    c = planarity_colors(torch.tensor([1.0, 0.0, 0.5]))
    assert c.tolist() == [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.5, 0.0, 0.5]]
    with pytest.raises(ConfigError, match="planar_threshold"):
        config_from_dict({"dataset": {"kind": "synthetic"}, "ggf": {"planar_threshold": 1.5}}, "t")
    with pytest.raises(ConfigError, match="knn"):
        config_from_dict({"dataset": {"kind": "synthetic"}, "ggf": {"knn": 2}}, "t")


def test_planar_fractions_against_a_labelled_mesh():
    from ggfslam.data.synthetic import make_scene
    from ggfslam.eval.planarity import planar_fractions

    scene = make_scene(0)
    floor = np.array([[0.5, 0.5, 0.0], [1.0, -1.0, 0.0], [-1.5, 0.2, 0.0]])
    sphere = np.array([[-2.3, -1.9, 0.6], [-2.0, -1.9, 0.3]])  # on the floor sphere (centre z 0.3, r 0.3)
    far = np.array([[0.0, 0.0, 1.3]])  # in mid-air
    pts = np.concatenate([floor, sphere, far])
    res = planar_fractions(pts, np.array([0.9, 0.9, 0.1, 0.9, 0.2, 0.9]), scene.mesh, scene.triangle_planar)
    assert res["planar_anchors"] == 3 and res["curved_anchors"] == 2 and res["far_anchors"] == 1
    assert res["planar_face_fraction"] == pytest.approx(2 / 3) and res["curved_object_fraction"] == pytest.approx(0.5)


def test_normal_error_degrees():
    a = np.zeros((4, 4, 3))
    a[..., 2] = 1.0
    b = np.zeros((4, 4, 3))
    b[..., 0] = 1.0
    b[0, 0] = 0.0  # undefined pixels are skipped
    assert normal_error_deg(a, a) == pytest.approx(0.0, abs=1e-6)
    assert normal_error_deg(b, a) == pytest.approx(90.0)


@pytest.mark.parametrize("orient", [True, False])
def test_surfel_shape_backward_matches_autograd_reference(orient):
    from ggfslam.ggf.amr import surfel_shape_reference

    g = torch.Generator().manual_seed(3)
    n_ = 64
    args = [torch.randn(n_, 4, generator=g, dtype=torch.float64), torch.rand(n_, 3, generator=g, dtype=torch.float64) * 0.02,
            torch.randn(n_, 3, generator=g, dtype=torch.float64)]
    normals = torch.nn.functional.normalize(torch.randn(n_, 3, generator=g, dtype=torch.float64), dim=1)
    surface = torch.randn(n_, 3, generator=g, dtype=torch.float64)
    radius = torch.full((n_,), 0.01, dtype=torch.float64)
    mask = torch.rand(n_, generator=g) > 0.3
    weights = [torch.randn(n_, k, generator=g, dtype=torch.float64) for k in (4, 3, 3)]

    def loss(fn, ins):
        outs = fn(*ins)
        return sum((o * w).sum() for o, w in zip(outs, weights))

    ins = [a.clone().requires_grad_(True) for a in args]
    fast = surfel_shape(*ins, normals, surface, radius, 1e-4, mask=mask, orient=orient)
    loss(lambda *x: fast, ins).backward()
    ref_ins = [a.clone().requires_grad_(True) for a in args]

    def ref_fn(q, s, m):
        rq, rs, rm = surfel_shape_reference(q, s, m, normals, surface, radius, 1e-4, orient)
        k = mask[:, None]
        return torch.where(k, rq, q), torch.where(k, rs, s), torch.where(k, rm, m)

    for a, b in zip(fast, ref_fn(*ref_ins)):
        assert torch.allclose(a, b, atol=1e-12)
    loss(ref_fn, ref_ins).backward()
    for a, b in zip(ins, ref_ins):
        assert torch.allclose(a.grad, b.grad, atol=1e-10)
    # and against finite differences
    assert torch.autograd.gradcheck(lambda q, s, m: surfel_shape(q, s, m, normals, surface, radius, 1e-4, mask=mask,
                                                                 orient=orient),
                                    [a.clone().requires_grad_(True) for a in args])
