"""Anchor map: decoders' shapes and gradients, voxel occupancy, growing/pruning invariants, PLY export."""
import numpy as np
import pytest
import torch

from ggfslam.gaussians.anchor_map import PER_ANCHOR_PARAMS, AnchorMap, spheres_in_view, voxel_keys
from ggfslam.gaussians.decoders import ChildDecoder
from ggfslam.gaussians.density import DensityControl
from ggfslam.gaussians.optim import make_adam, replace_param
from ggfslam.gaussians.ply import read_gaussians_ply, write_gaussians_ply


def _map(n=50, voxel=0.1, k=4, seed=0, **decoder):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1, 1, (n, 3))
    m = AnchorMap(voxel, n_offsets=k, feature_dim=8, hidden=16, seed=seed, **decoder)
    vals, first = m.new_anchor_values(pts, rng.uniform(0, 1, (n, 3)), source_kf=3)
    m.append(vals)
    with torch.no_grad():
        m.features.normal_(0, 0.5, generator=torch.Generator().manual_seed(seed))
    return m, pts


def test_anchors_sit_on_voxel_centres_one_per_voxel():
    m, pts = _map(200, voxel=0.25)
    keys = voxel_keys(pts, 0.25)
    assert m.n_anchors == len(np.unique(keys))
    a = m.anchors.numpy().astype(np.float64)
    np.testing.assert_allclose((a / 0.25) % 1.0, 0.5, atol=1e-5)
    # the same points again add nothing; a point in a new voxel adds one anchor
    assert m.new_anchor_values(pts, np.zeros((200, 3))) is None
    vals, _ = m.new_anchor_values(np.array([[5.0, 5.0, 5.0]]), np.zeros((1, 3)))
    assert m.append(vals) == 1 and m.n_anchors == len(np.unique(keys)) + 1
    assert (m.source_kf[:-1] == 3).all()


def test_decoder_shapes_activations_and_masking():
    m, _ = _map(30, k=5)
    g = m.decode(np.array([0.0, 0.0, -3.0]))
    G = len(g)
    assert 0 < G <= 30 * 5
    assert g.means.shape == (G, 3) and g.quats.shape == (G, 4) and g.scales.shape == (G, 3)
    assert g.opacities.shape == (G,) and g.colors.shape == (G, 3) and g.child_index.shape == (G,)
    assert (g.opacities > 0).all() and (g.opacities <= 1).all()  # tanh, children <= 0 are dropped
    assert (g.colors > 0).all() and (g.colors < 1).all()
    scale = torch.exp(m.log_scale)[g.anchor_index]
    assert (g.scales > 0).all() and (g.scales <= scale + 1e-6).all()  # l_v * sigmoid
    assert torch.equal(g.anchor_index, g.child_index // 5)
    # children sit at anchor + offset * l_v
    slot = g.child_index % 5
    expect = m.anchors[g.anchor_index] + m.offsets[g.anchor_index, slot] * scale
    torch.testing.assert_close(g.means, expect)


def test_decoder_gradients_match_finite_differences():
    torch.manual_seed(0)
    dec = ChildDecoder(feature_dim=6, k=3, hidden=8).double()
    M = 4
    anchors = torch.randn(M, 3, dtype=torch.float64)
    feats = torch.randn(M, 6, dtype=torch.float64, requires_grad=True)
    log_scale = torch.full((M, 3), -1.0, dtype=torch.float64, requires_grad=True)
    offsets = torch.randn(M, 3, 3, dtype=torch.float64, requires_grad=True)
    base = torch.zeros(M, 3, 3, dtype=torch.float64, requires_grad=True)
    cam = torch.tensor([0.1, -0.2, -4.0], dtype=torch.float64)
    with torch.no_grad():
        dec.opacity[-1].bias.fill_(2.0)  # every child kept, so the mask does not change under the probes
    idx = torch.arange(M)

    def f(feats, log_scale, offsets, base):
        g = dec(anchors, feats, log_scale, offsets, base, cam, idx)
        assert len(g) == M * 3
        return torch.cat([g.means.flatten(), g.scales.flatten(), g.opacities, g.colors.flatten(), g.quats.flatten()])

    assert torch.autograd.gradcheck(f, (feats, log_scale, offsets, base), eps=1e-6, atol=1e-6)



def test_view_independent_decoder_equals_its_mlps_on_zero_view_inputs():
    """Without view inputs the first layers skip their four view columns: the same outputs and weight gradients
    as the MLPs applied to [features, 0, 0, 0, 0] (the view columns' gradient is zero)."""
    torch.manual_seed(0)
    dec = ChildDecoder(feature_dim=6, k=3, hidden=8, sh_degree=1).double()
    feats = torch.randn(5, 6, dtype=torch.float64)
    x = torch.cat([feats, torch.zeros(5, 4, dtype=torch.float64)], 1)
    got = dec.raw(torch.randn(5, 3, dtype=torch.float64), feats)
    want = (dec.opacity(x), dec.color(x).view(5, 3, 4, 3), dec.cov(x).view(5, 3, 7))
    weights = [p for mlp in (dec.opacity, dec.color, dec.cov) for p in mlp.parameters()]
    gouts = [torch.randn_like(t) for t in want]
    g_got = torch.autograd.grad(got, weights, gouts)
    g_want = torch.autograd.grad(want, weights, gouts)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    for a, b in zip(g_got, g_want):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    for i in (0, 4, 8):  # each MLP's first-layer weight [8, 10]: nothing reaches the view columns
        assert float(g_got[i][:, 6:].abs().max()) == 0.0 and float(g_got[i][:, :6].abs().max()) > 0.0



def test_anchor_culling_matches_its_torch_reference():
    """The compiled frustum test of anchor spheres against spheres_in_view in float64 (the same decisions), for
    anchors around, behind and straddling the camera; the centre-only cull would lose spheres reaching in."""
    from ggfslam.geometry.se3 import so3_exp
    from ggfslam.render.types import Intrinsics

    rng = np.random.default_rng(7)
    m = AnchorMap(0.05, 4, 8, 8, False, 0, 1)
    pts = rng.uniform(-4.0, 4.0, (4000, 3))
    vals, _ = m.new_anchor_values(pts, rng.random((4000, 3)))
    m.append(vals)
    intr = Intrinsics(fx=300.0, fy=300.0, cx=160.0, cy=120.0, width=320, height=240)
    reach = torch.from_numpy(rng.uniform(0.01, 0.6, m.n_anchors).astype(np.float32))
    for seed in range(3):
        T = np.eye(4)
        T[:3, :3] = so3_exp(np.random.default_rng(seed).normal(scale=0.5, size=3))
        T[:3, 3] = np.random.default_rng(seed + 10).normal(scale=0.5, size=3)
        got = m.visible_anchors(T, intr, 0.05, reach=reach)
        want = spheres_in_view(m.anchors.double(), reach.double(), torch.from_numpy(T), intr, 0.05)
        assert torch.equal(got, want)
        assert 0 < int(got.sum()) < m.n_anchors
        pc = m.anchors.double() @ torch.from_numpy(T[:3, :3]).T + torch.from_numpy(T[:3, 3])
        u = intr.fx * pc[:, 0] / pc[:, 2] + intr.cx
        centre_in = (pc[:, 2] > 0.05) & (u >= 0) & (u < intr.width)
        assert bool((got & ~centre_in).any())  # spheres whose centre is outside but which reach into the image


def test_what_the_viewpoint_changes_in_each_decoder():
    """Default: only the SH colour follows the view; degree 0: nothing; Scaffold-GS: shape and opacity too."""
    m, _ = _map(10)
    with torch.no_grad():
        m.decoder.opacity[-1].bias.fill_(5.0)  # every child kept from both views
        m.decoder.color[-1].weight.normal_(0, 0.3, generator=torch.Generator().manual_seed(1))
    front, side = np.array([0.0, 0.0, -3.0]), np.array([3.0, 0.0, 0.0])
    a, b = m.decode(front), m.decode(side)
    assert len(a) == len(b) == m.n_anchors * m.k
    assert (a.colors - b.colors).abs().max() > 1e-3
    for name in ("means", "quats", "scales", "opacities"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name))
    flat, _ = _map(10, sh_degree=0)
    torch.testing.assert_close(flat.decode(front).colors, flat.decode(side).colors)
    scaffold, _ = _map(10, view_dependent=True, sh_degree=0)
    with torch.no_grad():
        scaffold.decoder.opacity[-1].bias.fill_(5.0)
        for mlp in (scaffold.decoder.opacity, scaffold.decoder.cov):
            mlp[0].weight[:, -4:].normal_(0, 1.0, generator=torch.Generator().manual_seed(2))
    a, b = scaffold.decode(front), scaffold.decode(side)
    assert (a.scales - b.scales).abs().max() > 1e-4 and (a.opacities - b.opacities).abs().max() > 1e-4


def _optimizer(m):
    return make_adam([{"params": [getattr(m, n)], "lr": 0.01} for n in PER_ANCHOR_PARAMS])


def _take_a_step(m, opt):
    g = m.decode(np.array([0.0, 0.0, -3.0]))
    (g.colors.sum() + g.means.square().sum() + g.opacities.sum()).backward()
    opt.step()
    opt.zero_grad()


def test_prune_removes_transparent_anchors_and_keeps_optimizer_rows_aligned():
    m, _ = _map(40)
    opt = _optimizer(m)
    _take_a_step(m, opt)
    dc = DensityControl(m, grad_threshold=1.0, min_opacity=0.05, min_visits=2, max_anchors=1000)
    A = m.n_anchors
    low = torch.zeros(A, dtype=torch.bool)
    low[::3] = True
    dc.stats.visits[:] = 5
    dc.stats.opacity_sum[:] = torch.where(low, 0.01, 1.0) * 5  # mean child opacity 0.01 vs 1.0
    dc.stats.visits[1] = 1  # seen too rarely to judge
    dc.stats.opacity_sum[1] = 0.0
    feats_before = m.features.detach().clone()
    moment_before = opt.state[m.features]["exp_avg"].clone()
    keys_before = m._keys.copy()
    removed = dc.prune(opt)
    assert removed == int(low.sum())
    keep = ~low
    assert m.n_anchors == A - removed
    torch.testing.assert_close(m.features.detach(), feats_before[keep])
    torch.testing.assert_close(opt.state[m.features]["exp_avg"], moment_before[keep])
    for name in PER_ANCHOR_PARAMS:
        p = getattr(m, name)
        assert opt.state[p]["exp_avg"].shape == p.shape and any(p is q for g in opt.param_groups for q in g["params"])
    assert len(dc.stats.visits) == m.n_anchors and len(dc.stats.grad_sum) == m.n_anchors * m.k
    assert set(m._keys) == set(keys_before[np.isin(keys_before, m._keys)]) and len(m._keys) == m.n_anchors
    _take_a_step(m, opt)  # the optimizer still works on the resized tensors


def test_merge_keeps_one_anchor_per_voxel_the_most_opaque_else_the_oldest():
    m, _ = _map(30, voxel=0.1)
    opt = _optimizer(m)
    _take_a_step(m, opt)
    dc = DensityControl(m, grad_threshold=1.0, min_opacity=0.0, min_visits=1, max_anchors=1000)
    A = m.n_anchors
    # a second copy of the first 10 anchors (a revisit seeded from a drifted pose), then moved onto the
    # originals by a pose correction, 1 cm off their voxel centres
    copy = {name: getattr(m, name).detach()[:10].clone() for name in PER_ANCHOR_PARAMS}
    copy["anchors"] = m.anchors[:10] + 0.3
    copy["source_kf"] = torch.full((10,), 7)
    olds = {name: getattr(m, name) for name in PER_ANCHOR_PARAMS}
    m.append(copy)
    for name in PER_ANCHOR_PARAMS:
        replace_param(opt, olds[name], getattr(m, name), None, 10)
    dc.on_append(10)
    m.transform_anchors(m.source_kf == 7, np.array([[1, 0, 0, -0.29], [0, 1, 0, -0.29], [0, 0, 1, -0.29],
                                                   [0, 0, 0, 1.0]]))
    # voxels 0-3: the copy draws more (kept); 4-6: the original does; 7-9: never seen (the original is kept)
    dc.stats.visits[:] = 0
    dc.stats.visits[list(range(7)) + list(range(A, A + 7))] = 2
    dc.stats.opacity_sum[:] = 0.0
    dc.stats.opacity_sum[A:A + 4] = 1.6
    dc.stats.opacity_sum[:4] = 0.4
    dc.stats.opacity_sum[4:7] = 1.0
    dc.stats.opacity_sum[A + 4:A + 7] = 0.2
    feats = m.features.detach().clone()
    moment = opt.state[m.features]["exp_avg"].clone()
    assert dc.merge_collisions(opt) == 10
    keep = torch.ones(A + 10, dtype=torch.bool)
    keep[:4] = False
    keep[A + 4:] = False
    assert m.n_anchors == A
    torch.testing.assert_close(m.features.detach(), feats[keep])
    torch.testing.assert_close(opt.state[m.features]["exp_avg"], moment[keep])
    assert (m.source_kf == 7).sum() == 4
    keys = voxel_keys(m.anchors.numpy().astype(np.float64), 0.1)
    assert len(np.unique(keys)) == A and len(m._keys) == A
    assert len(dc.stats.visits) == A and len(dc.stats.grad_sum) == A * m.k
    assert dc.merge_collisions(opt) == 0  # one per voxel already


def test_grow_adds_anchors_only_in_free_voxels_where_gradients_are_large():
    m, _ = _map(20, voxel=0.1, k=4)
    with torch.no_grad():
        m.offsets.fill_(0.0)
        m.offsets[0, 2] = torch.tensor([30.0, 0.0, 0.0])  # child 2 of anchor 0 sits 3 voxels away (l_v = 0.1)
        m.offsets[1, 0] = torch.tensor([0.2, 0.0, 0.0])  # inside its own voxel: no new anchor
    opt = _optimizer(m)
    _take_a_step(m, opt)
    dc = DensityControl(m, grad_threshold=0.5, min_opacity=0.0, min_visits=3, max_anchors=1000)
    A = m.n_anchors
    dc.stats.grad_count[:] = 5
    dc.stats.grad_sum[:] = 0.1 * 5
    dc.stats.grad_sum[0 * 4 + 2] = 2.0 * 5
    dc.stats.grad_sum[1 * 4 + 0] = 2.0 * 5
    target = (m.anchors[0] + m.offsets[0, 2].detach() * torch.exp(m.log_scale[0].detach())).numpy()
    occupied = set(m._keys.tolist())
    added = dc.grow(opt)
    key = voxel_keys(target[None].astype(np.float64), 0.1)[0]
    if key in occupied:
        assert added == 0
    else:
        assert added == 1 and m.n_anchors == A + 1
        new = m.anchors[-1].numpy()
        np.testing.assert_allclose(new, (np.floor(target / 0.1) + 0.5) * 0.1, atol=1e-5)
        torch.testing.assert_close(m.features[-1], m.features[0])  # copied from the parent
        assert int(m.source_kf[-1]) == int(m.source_kf[0])
        assert opt.state[m.features]["exp_avg"].shape == m.features.shape
        assert float(opt.state[m.features]["exp_avg"][-1].abs().sum()) == 0.0
    assert dc.stats.grad_count[0 * 4 + 2] == 0 and dc.stats.grad_count[1 * 4 + 0] == 0  # reset after use
    assert len(dc.stats.grad_sum) == m.n_anchors * m.k
    _take_a_step(m, opt)


def test_grow_respects_the_anchor_budget():
    m, _ = _map(20, voxel=0.1, k=4)
    with torch.no_grad():
        m.offsets.copy_(torch.randn(m.offsets.shape, generator=torch.Generator().manual_seed(1)) * 20)
    dc = DensityControl(m, grad_threshold=0.0, min_opacity=0.0, min_visits=1, max_anchors=m.n_anchors + 3)
    dc.stats.grad_count[:] = 1
    dc.stats.grad_sum[:] = 1.0
    assert dc.grow(None) == 3


def test_transform_anchors_moves_positions_and_offsets_rigidly():
    m, _ = _map(20)
    with torch.no_grad():
        m.decoder.opacity[-1].bias.fill_(5.0)  # every child kept from both views
    before = m.decode(np.zeros(3))
    T = np.eye(4)
    c, s = np.cos(0.3), np.sin(0.3)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [0.5, -0.2, 0.1]
    m.transform_anchors(torch.ones(m.n_anchors, dtype=torch.bool), T)
    after = m.decode(np.zeros(3) @ T[:3, :3].T + T[:3, 3])
    moved = before.means.detach().numpy() @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(after.means.detach().numpy(), moved, atol=1e-5)


def test_state_round_trip_rebuilds_the_same_map():
    m, _ = _map(25)
    m2 = AnchorMap.from_state(m.extra_state(), m.state_dict())
    a, b = m.decode(np.array([0.0, 1.0, -2.0])), m2.decode(np.array([0.0, 1.0, -2.0]))
    for name in ("means", "quats", "scales", "opacities", "colors"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name))
    np.testing.assert_array_equal(m._keys, m2._keys)


def test_exported_children_round_trip_through_ply(tmp_path):
    m, _ = _map(30)
    g = m.decode(np.zeros(3))
    write_gaussians_ply(tmp_path / "g.ply", g.means, g.quats, g.scales, g.opacities, g.colors)
    r = read_gaussians_ply(tmp_path / "g.ply")
    np.testing.assert_allclose(r["means"], g.means.detach().numpy(), atol=1e-6)
    np.testing.assert_allclose(r["scales"], g.scales.detach().numpy(), rtol=1e-5)
    np.testing.assert_allclose(r["opacities"], g.opacities.detach().numpy(), rtol=1e-4, atol=1e-6)
    q = torch.nn.functional.normalize(g.quats.detach(), dim=1).numpy()
    np.testing.assert_allclose(np.abs((r["quats"] * q).sum(1)), 1.0, atol=1e-5)


@pytest.mark.parametrize("bad", [0.0, -1.0])
def test_voxel_size_must_be_positive(bad):
    with pytest.raises(ValueError, match="voxel_size"):
        AnchorMap(bad)


def test_gradient_statistics_are_in_ndc_units_and_count_visible_children_only():
    m, _ = _map(10, k=4)
    g = m.decode(np.array([0.0, 0.0, -3.0]))
    dc = DensityControl(m, grad_threshold=1.0, min_opacity=0.0, min_visits=1, max_anchors=100)
    grad = torch.zeros(len(g), 2)
    grad[:, 0] = 0.01  # pixels, along x
    visible = torch.ones(len(g), dtype=torch.bool)
    visible[0] = False
    mask = torch.ones(m.n_anchors, dtype=torch.bool)
    dc.accumulate(g, visible, grad, mask, image_size=(320, 240))
    ci = g.child_index
    torch.testing.assert_close(dc.stats.grad_sum[ci[1:]], torch.full((len(g) - 1,), 0.01 * 160))
    assert dc.stats.grad_count[ci[0]] == 0 and (dc.stats.grad_count[ci[1:]] == 1).all()
    assert (dc.stats.visits == 1).all()
    opa = torch.zeros(m.n_anchors).index_add_(0, g.anchor_index, g.opacities.detach()) / m.k
    torch.testing.assert_close(dc.stats.opacity_sum, opa)
    # a second render of part of the map, without gradients: sums accumulate, gradient statistics stay
    before = dc.stats.grad_sum.clone()
    mask[::2] = False
    part = m.decode(np.array([0.0, 0.0, -3.0]), mask)
    dc.accumulate(part, torch.ones(len(part), dtype=torch.bool), None, mask, image_size=(320, 240))
    assert torch.equal(dc.stats.visits, 1.0 + mask.float())
    opa2 = torch.zeros(m.n_anchors).index_add_(0, part.anchor_index, part.opacities.detach()) / m.k
    torch.testing.assert_close(dc.stats.opacity_sum, opa + opa2)
    assert torch.equal(dc.stats.grad_sum, before)
