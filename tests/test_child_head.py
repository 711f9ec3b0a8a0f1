"""The compiled child head (gaussians/child_head.py) against its plain-torch reference (the decoder's ``reference``
path followed by AMR's ``surfel_shape``): the same children, values and gradients, with and without surfels."""
from __future__ import annotations

import pytest
import torch

from ggfslam.gaussians.anchor_map import AnchorMap
from ggfslam.gaussians.child_head import SurfelSpec
from ggfslam.ggf.amr import quat_z_to, surfel_shape


def _map(n: int = 300, seed: int = 0, view_dependent: bool = False, sh_degree: int = 1) -> AnchorMap:
    g = torch.Generator().manual_seed(seed)
    m = AnchorMap(0.05, 10, 16, 16, view_dependent, seed, sh_degree)
    pts = torch.rand(n, 3, generator=g).numpy() * 2.0
    vals, _ = m.new_anchor_values(pts, torch.rand(n, 3, generator=g).numpy())
    m.append(vals)
    with torch.no_grad():  # a trained-looking map: varied features, some children switched off
        m.features.normal_(0, 1, generator=g)
        m.log_scale.add_(0.3 * torch.randn(m.log_scale.shape, generator=g))
        m.decoder.opacity[-1].bias.normal_(0, 0.5, generator=g)
    return m


def _spec(m: AnchorMap, idx: torch.Tensor, snap: bool, seed: int = 1, orient: bool = True) -> SurfelSpec:
    g = torch.Generator().manual_seed(seed)
    n = torch.nn.functional.normalize(torch.randn(len(idx), 3, generator=g), dim=1)
    planar = torch.rand(len(idx), generator=g) > 0.4
    return SurfelSpec(planar, n, quat_z_to(n), m.surface[idx] + 0.01, 0.004 + 0.01 * torch.rand(len(idx), generator=g),
                      2e-5, snap, orient)


def _reference(m: AnchorMap, cam, spec: SurfelSpec | None):
    g = m.decode(cam, reference=True)
    if spec is None:
        return g.means, g.quats, g.scales, g.opacities, g.colors, g.child_index
    a = g.anchor_index  # the map's first anchors are the decoded ones (mask None)
    q, s, mu = surfel_shape(g.quats, g.scales, g.means, spec.normals[a], spec.surface[a], spec.radius[a], spec.eps,
                            spec.align[a], spec.planar[a], spec.snap, spec.orient)
    colors = g.colors
    if spec.snap and spec.orient:  # the SH colour is seen along the direction to where the child ends up
        raw_c = m.decoder.raw(m.anchors, m.features)[1]  # [A, k, B, 3]
        slot = g.child_index % m.k
        colors = m.decoder._color(raw_c[a, slot][:, None], m.base_color[a, slot][:, None], mu[:, None], cam)[:, 0]
    return mu, q, s, g.opacities, colors, g.child_index


@pytest.mark.parametrize("surfels,decoder", [("none", "sh1"), ("amr", "sh3"), ("amr+snap", "sh1"),
                                             ("amr", "scaffold"), ("amr, decoder's rotation", "sh1")])
def test_child_head_matches_the_torch_reference(surfels, decoder):
    m = _map(view_dependent=decoder == "scaffold", sh_degree={"sh1": 1, "sh3": 3, "scaffold": 0}[decoder])
    cam = torch.tensor([0.5, -1.0, -2.0])
    idx = torch.arange(m.n_anchors)
    spec = None if surfels == "none" else _spec(m, idx, snap=surfels == "amr+snap", orient="decoder" not in surfels)
    fused = m.decode(cam, surfels=lambda i: spec)
    ref = _reference(m, cam, spec)
    assert 0 < len(fused) < m.n_anchors * m.k  # some children dropped (opacity <= 0)
    assert torch.equal(fused.child_index, ref[5])
    assert torch.equal(fused.anchor_index, ref[5] // m.k)
    for a, b in zip((fused.means, fused.quats, fused.scales, fused.opacities, fused.colors), ref[:5]):
        torch.testing.assert_close(a, b, atol=2e-6, rtol=1e-5)
    # gradients of one random linear function of every output, w.r.t. everything that trains
    gen = torch.Generator().manual_seed(3)
    weights = [torch.randn(t.shape, generator=gen) for t in ref[:5]]

    def grads(outs):
        params = [m.features, m.log_scale, m.offsets, m.base_color, *m.decoder.parameters()]
        for p in params:
            p.grad = None
        sum((w * o).sum() for w, o in zip(weights, outs)).backward()
        return [p.grad.clone() for p in params]

    g_fused = grads((fused.means, fused.quats, fused.scales, fused.opacities, fused.colors))
    g_ref = grads(_reference(m, cam, spec)[:5])
    for a, b in zip(g_fused, g_ref):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("decoder", ["sh1", "scaffold"])
def test_child_head_reads_the_decoded_rows_of_the_maps_arrays(decoder):
    """A decode of some anchors (a mask): the fused path reads rows of the map's whole arrays and returns their
    gradients whole, zero in the rows not decoded; the reference gathers copies of the rows first."""
    m = _map(view_dependent=decoder == "scaffold", sh_degree=0 if decoder == "scaffold" else 1)
    cam = torch.tensor([0.5, -1.0, -2.0])
    mask = torch.rand(m.n_anchors, generator=torch.Generator().manual_seed(4)) > 0.6
    fused, ref = m.decode(cam, mask), m.decode(cam, mask, reference=True)
    assert torch.equal(fused.child_index, ref.child_index) and torch.equal(fused.anchor_index, ref.anchor_index)
    assert set(fused.anchor_index.tolist()) <= set(torch.nonzero(mask)[:, 0].tolist())
    outs = ("means", "quats", "scales", "opacities", "colors")
    for name in outs:
        torch.testing.assert_close(getattr(fused, name), getattr(ref, name), atol=2e-6, rtol=1e-5)
    gen = torch.Generator().manual_seed(3)
    weights = [torch.randn(getattr(ref, n).shape, generator=gen) for n in outs]
    params = [m.features, m.log_scale, m.offsets, m.base_color, *m.decoder.parameters()]

    def grads(g):
        for p in params:
            p.grad = None
        sum((w * getattr(g, n)).sum() for w, n in zip(weights, outs)).backward()
        return [p.grad.clone() for p in params]

    g_fused, g_ref = grads(fused), grads(ref)
    for a, b in zip(g_fused, g_ref):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)
    for a in g_fused[:4]:  # per-anchor gradients: nothing outside the decoded rows
        assert torch.all(a[~mask] == 0) and a[mask].abs().sum() > 0


def test_child_head_gradients_match_finite_differences_on_rows_of_larger_arrays():
    """anchor_index picks rows of per-anchor arrays larger than the decoded set, in any order: gradients of the
    whole arrays (zero in the other rows) against finite differences."""
    from ggfslam.gaussians.child_head import child_head

    g = torch.Generator().manual_seed(9)
    A, M, k = 7, 4, 3
    rows = torch.tensor([5, 1, 6, 3])
    d = dict(dtype=torch.float64)
    raw_o = (0.5 + torch.rand(M, k, generator=g, **d)) * torch.tensor([1.0, -1.0, 1.0], **d)
    raw_c, raw_cov = 0.3 * torch.randn(M, k, 4, 3, generator=g, **d), torch.randn(M, k, 7, generator=g, **d)
    raw_c[:, :, 0] += 1.0
    raw_cov[..., 3] += 2.0
    offsets, base = torch.randn(A, k, 3, generator=g, **d), torch.randn(A, k, 3, generator=g, **d)
    log_scale = torch.full((A, 3), -2.0, **d) + 0.1 * torch.randn(A, 3, generator=g, **d)
    anchors = torch.randn(A, 3, generator=g, **d)
    n = torch.nn.functional.normalize(torch.randn(M, 3, generator=g, **d), dim=1)
    spec = SurfelSpec(torch.tensor([True, False, True, False]), n, quat_z_to(n), anchors[rows] + 0.1,
                      torch.full((M,), 0.06, **d), 1e-4, True)
    cam = torch.tensor([3.0, -2.0, 4.0], **d)
    out = child_head(raw_o, raw_c, raw_cov, anchors, log_scale, offsets, base, rows, spec, cam, sh_degree=1)
    assert torch.equal(out[6], rows.repeat_interleave(k)[raw_o.flatten() > 0])  # each child's anchor id
    ins = [t.requires_grad_() for t in (raw_o, raw_c, raw_cov, offsets, log_scale, base)]

    def f(ro, rc, rv, off, ls, bc):
        o = child_head(ro, rc, rv, anchors, ls, off, bc, rows, spec, cam, sh_degree=1)
        return torch.cat([t.flatten() for t in o[:5]])

    assert torch.autograd.gradcheck(f, ins, eps=1e-6, atol=1e-6)


def test_unshaped_gives_the_decoders_own_shape_under_amr():
    m = _map()
    cam = torch.tensor([0.5, -1.0, -2.0])
    spec = _spec(m, torch.arange(m.n_anchors), snap=False)
    fused = m.decode(cam, surfels=lambda i: spec)
    plain = m.decode(cam)
    sel = torch.arange(0, len(fused), 7)
    q, s = fused.unshaped(sel)
    torch.testing.assert_close(q, plain.quats[sel])
    torch.testing.assert_close(s, plain.scales[sel])
    planar = spec.planar[fused.anchor_index]
    assert torch.all(fused.scales[planar][:, 2] == spec.eps)  # the surfels themselves are flat
    # L_morph's gradient reaches the decoder through unshaped()
    s.sum().backward()
    assert m.decoder.cov[-1].weight.grad.abs().sum() > 0


def test_child_head_gradients_match_finite_differences_with_surfels():
    from ggfslam.gaussians.child_head import child_head

    g = torch.Generator().manual_seed(5)
    M, k = 5, 3
    d = dict(dtype=torch.float64)
    raw_o = (0.5 + torch.rand(M, k, generator=g, **d)) * torch.tensor([1.0, -1.0, 1.0], **d)  # one slot dropped
    raw_c, raw_cov = torch.randn(M, k, 3, generator=g, **d), torch.randn(M, k, 7, generator=g, **d)
    raw_cov[..., 3] += 2.0  # away from the (w, z) = 0 singularity
    offsets, base = torch.randn(M, k, 3, generator=g, **d), torch.randn(M, k, 3, generator=g, **d)
    log_scale = torch.full((M, 3), -2.0, **d) + 0.1 * torch.randn(M, 3, generator=g, **d)
    anchors = torch.randn(M, 3, generator=g, **d)
    n = torch.nn.functional.normalize(torch.randn(M, 3, generator=g, **d), dim=1)
    # radius between the two tangential scales' ranges, so both branches of max(s, r) are met away from the kink
    spec = SurfelSpec(torch.tensor([True, False, True, True, False]), n, quat_z_to(n), anchors + 0.1,
                      torch.full((M,), 0.06, **d), 1e-4, True)
    ins = [t.requires_grad_() for t in (raw_o, raw_c, raw_cov, offsets, log_scale, base)]

    def f(ro, rc, rv, off, ls, bc):
        out = child_head(ro, rc, rv, anchors, ls, off, bc, torch.arange(M), spec)
        return torch.cat([t.flatten() for t in out[:5]])

    assert torch.autograd.gradcheck(f, ins, eps=1e-6, atol=1e-6)


def test_child_head_sh_gradients_match_finite_differences_with_surfels():
    """Degree-1 SH colour with surfels: every input's gradient, the view direction's through the child's mean included,
    against finite differences (the gradcheck above runs degree 0)."""
    from ggfslam.gaussians.child_head import child_head

    g = torch.Generator().manual_seed(7)
    M, k = 4, 3
    d = dict(dtype=torch.float64)
    raw_o = (0.5 + torch.rand(M, k, generator=g, **d)) * torch.tensor([1.0, 1.0, -1.0], **d)
    raw_c, raw_cov = 0.3 * torch.randn(M, k, 4, 3, generator=g, **d), torch.randn(M, k, 7, generator=g, **d)
    raw_c[:, :, 0] += 1.0  # colours well above the clamp at 0
    raw_cov[..., 3] += 2.0
    offsets, base = torch.randn(M, k, 3, generator=g, **d), torch.randn(M, k, 3, generator=g, **d)
    log_scale = torch.full((M, 3), -2.0, **d) + 0.1 * torch.randn(M, 3, generator=g, **d)
    anchors = torch.randn(M, 3, generator=g, **d)
    n = torch.nn.functional.normalize(torch.randn(M, 3, generator=g, **d), dim=1)
    spec = SurfelSpec(torch.tensor([True, False, True, False]), n, quat_z_to(n), anchors + 0.1,
                      torch.full((M,), 0.06, **d), 1e-4, True)
    cam = torch.tensor([3.0, -2.0, 4.0], **d)
    ins = [t.requires_grad_() for t in (raw_o, raw_c, raw_cov, offsets, log_scale, base)]

    def f(ro, rc, rv, off, ls, bc):
        out = child_head(ro, rc, rv, anchors, ls, off, bc, torch.arange(M), spec, cam, sh_degree=1)
        return torch.cat([t.flatten() for t in out[:5]])

    assert torch.autograd.gradcheck(f, ins, eps=1e-6, atol=1e-6)


def test_decoder_orientation_flattens_the_childs_own_z_axis():
    """``orient=False`` (``ggf.surfel_orientation: decoder``): a planar anchor's children keep the decoder's rotation
    and position, are flat along their own local z axis with the tangential floor, and get gradients for all four
    quaternion components (exact finite differences through the compiled head)."""
    from ggfslam.gaussians.child_head import child_head

    g = torch.Generator().manual_seed(11)
    M, k = 4, 3
    d = dict(dtype=torch.float64)
    raw_o = 0.5 + torch.rand(M, k, generator=g, **d)
    raw_c, raw_cov = torch.randn(M, k, 3, generator=g, **d), torch.randn(M, k, 7, generator=g, **d)
    offsets, base = torch.randn(M, k, 3, generator=g, **d), torch.randn(M, k, 3, generator=g, **d)
    log_scale = torch.full((M, 3), -2.0, **d) + 0.1 * torch.randn(M, 3, generator=g, **d)
    anchors = torch.randn(M, 3, generator=g, **d)
    n = torch.nn.functional.normalize(torch.randn(M, 3, generator=g, **d), dim=1)
    planar = torch.tensor([True, False, True, True])
    spec = SurfelSpec(planar, n, quat_z_to(n), anchors + 0.1, torch.full((M,), 0.06, **d), 1e-4, False, False)
    means, quats, scales, *_ = child_head(raw_o, raw_c, raw_cov, anchors, log_scale, offsets, base, torch.arange(M),
                                          spec)
    plain = child_head(raw_o, raw_c, raw_cov, anchors, log_scale, offsets, base, torch.arange(M))
    assert torch.equal(quats, plain[1]) and torch.equal(means, plain[0])  # rotation and position: the decoder's
    rows = planar.repeat_interleave(k)
    assert torch.all(scales[rows, 2] == 1e-4) and torch.all(scales[rows, :2] >= 0.06)
    assert torch.equal(scales[~rows], plain[2][~rows])
    ins = [t.requires_grad_() for t in (raw_cov, log_scale)]

    def f(rv, ls):
        out = child_head(raw_o, raw_c, rv, anchors, ls, offsets, base, torch.arange(M), spec)
        return torch.cat([t.flatten() for t in out[:5]])

    assert torch.autograd.gradcheck(f, ins, eps=1e-6, atol=1e-6)


def test_decoding_no_anchor_gives_no_children():
    """An all-false mask (a bake before any keyframe) and an empty map decode to zero children, and the backward
    through them gives zero gradients (the child head once failed to reshape an empty colour output)."""
    m = _map(n=20)
    g = m.decode(torch.zeros(3), torch.zeros(m.n_anchors, dtype=torch.bool))
    assert len(g) == 0 and g.means.shape == (0, 3) and g.anchor_index.shape == (0,)
    (g.means.sum() + g.colors.sum() + g.opacities.sum()).backward()
    assert m.features.grad is not None and torch.all(m.features.grad == 0) and torch.all(m.offsets.grad == 0)
    assert len(AnchorMap(0.05, 10, 16, 16, False, 0, 1).decode(torch.zeros(3))) == 0
