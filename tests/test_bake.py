"""The baked map (gaussians.ply) as standard viewers read it: an independent 3DGS renderer (tests/standard_splat.py,
reading nothing but the file) against the project's own render of a small trained scene, the view selection of
the bake, the SH fit, and ``ggfslam render --ply``."""
from __future__ import annotations

import tempfile

import numpy as np
import pytest
import torch

import standard_splat
from ggfslam.config import MappingConfig
from ggfslam.eval.image import psnr
from ggfslam.gaussians.bake import fit_sh1, observing_keyframes
from ggfslam.gaussians.explicit import ExplicitGaussians, sh_basis
from ggfslam.gaussians.ply import write_gaussians_ply
from ggfslam.mapping.mapper import Mapper
from ggfslam.mapping.outputs import write_map_ply
from ggfslam.render.types import Intrinsics, RenderSettings

KEYFRAMES = (0, 10, 20)


def _train(sequence, **cfg) -> tuple[Mapper, dict]:
    """A map trained on three keyframes of the procedural room (ground-truth poses, 160x120)."""
    poses = {}
    m = Mapper(MappingConfig(train_width=160, **cfg), sequence.camera, RenderSettings(backend="cpu"),
               lambda: dict(poses), tempfile.mkdtemp())
    for kf, fi in enumerate(KEYFRAMES):
        poses[kf] = sequence.gt_poses[fi]
        f = sequence[fi]
        m.add_keyframe(kf, fi, f.rgb, f.depth)
        m.train(40, focus=kf)
    m.train(40)
    return m, poses


@pytest.fixture(scope="module")
def trained(sequence):
    """The default map (view-independent shapes, degree-1 SH colours)."""
    return _train(sequence)


def _independent_psnr(path, m: Mapper, poses: dict) -> list[float]:
    ply = standard_splat.read_ply(path)
    i = m.intr
    out = []
    for kf, T in poses.items():
        img, _ = standard_splat.render(ply, i.fx, i.fy, i.cx, i.cy, i.width, i.height, T)
        out.append(psnr(np.clip(img, 0, 1), m.store.get(kf).rgb))
    return out


def test_standard_renderer_of_the_ply_matches_the_map(trained, tmp_path):
    m, poses = trained
    path = tmp_path / "gaussians.ply"
    n = write_map_ply(m, path)
    assert n == m.n_gaussians() > 0
    own = [psnr(m.render(T, exposure_kf=kf).color.numpy(), m.store.get(kf).rgb) for kf, T in poses.items()]
    ply = _independent_psnr(path, m, poses)
    assert np.mean(own) > 24.0
    assert np.mean(ply) > np.mean(own) - 0.5, (own, ply)
    # our own reading of the file (ggfslam render --ply) agrees with the independent renderer
    baked = ExplicitGaussians.from_ply(path)
    assert baked.degree == 3  # 45 f_rest values, as viewers expect: the map's degree-1 terms, then zeros
    assert baked.sh[:, 4:].abs().max() == 0 and baked.sh[:, 1:4].abs().max() > 0
    ours = [psnr(baked.render(T, m.intr).color.clamp(0, 1).numpy(), m.store.get(kf).rgb) for kf, T in poses.items()]
    np.testing.assert_allclose(ours, ply, atol=0.05)


@pytest.mark.parametrize("degree", [0, 2, 3])
def test_the_file_holds_the_map_exactly_for_every_sh_degree(sequence, tmp_path, degree):
    """Without the exposure, the independent renderer of the file and the map's render are the same image."""
    poses = {0: sequence.gt_poses[0]}
    m = Mapper(MappingConfig(train_width=80, sh_degree=degree, exposure=False), sequence.camera,
               RenderSettings(backend="cpu"), lambda: dict(poses), tempfile.mkdtemp())
    f = sequence[0]
    m.add_keyframe(0, 0, f.rgb, f.depth)
    with torch.no_grad():  # SH terms as large as training could make them
        m.map.decoder.color[-1].weight.normal_(0, 0.2, generator=torch.Generator().manual_seed(degree))
    write_map_ply(m, tmp_path / "g.ply")
    ply = standard_splat.read_ply(tmp_path / "g.ply")
    i = m.intr
    for T in (sequence.gt_poses[0], sequence.gt_poses[8]):  # a keyframe and a new view
        theirs, _ = standard_splat.render(ply, i.fx, i.fy, i.cx, i.cy, i.width, i.height, T)
        own = m.render(T).color.numpy()
        assert psnr(np.clip(theirs, 0, 1), own) > 45.0


def test_scaffold_decoder_is_baked_from_real_viewpoints(sequence, tmp_path):
    """A view-dependent (Scaffold-GS) map: decoding from nowhere (zero view direction and distance, inputs the
    decoder never saw) loses several dB in a standard renderer; the bake from observing keyframes does not."""
    m, poses = _train(sequence, view_dependent=True, sh_degree=0)
    with torch.no_grad():
        m.map.decoder.view_dependent = False
        try:
            zero = m._decode(np.zeros(3))
        finally:
            m.map.decoder.view_dependent = True
    write_gaussians_ply(tmp_path / "zero.ply", zero.means, zero.quats, zero.scales, zero.opacities, zero.colors)
    write_map_ply(m, tmp_path / "baked.ply")
    zero = np.mean(_independent_psnr(tmp_path / "zero.ply", m, poses))
    baked = np.mean(_independent_psnr(tmp_path / "baked.ply", m, poses))
    own = np.mean([psnr(m.render(T, exposure_kf=kf).color.numpy(), m.store.get(kf).rgb) for kf, T in poses.items()])
    assert baked > zero + 2.0 and baked > own - 1.0, (zero, baked, own)


def test_observing_keyframes_picks_the_nearest_that_saw_a_point():
    intr = Intrinsics(50.0, 50.0, 15.5, 11.5, 32, 24)
    wall = np.zeros((24, 32), np.float32)

    def cam(z):  # camera at (0, 0, z) looking along +z
        T = np.eye(4)
        T[2, 3] = z
        return T

    points = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 2.0], [5.0, 0.0, 2.0]])
    points[1, 0] = 0.01
    poses = [cam(-2.0), cam(0.5), cam(-1.0)]
    depths = [wall + 4.0, wall + 1.5, wall + 3.0]
    depths[2][:] = 1.0  # keyframe 2 sees an occluder in front of the points
    v = observing_keyframes(points, poses, depths, intr, voxel=0.04, max_views=3)
    assert list(v.nearest[:2]) == [1, 1] and v.observed[:2].all()
    assert list(v.views[0]) == [1, 0, -1]  # nearest first; the occluded keyframe 2 never
    # the third point is outside every image: not observed, its fallback is the nearest camera centre
    assert not v.observed[2] and v.nearest[2] == 1


def test_sh1_fit_recovers_a_linear_sh_colour():
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(50, 6, 3, generator=g, dtype=torch.float64), dim=-1)  # [G, V, 3]
    c0 = torch.rand(50, 3, generator=g, dtype=torch.float64)
    a = 0.3 * torch.randn(50, 3, 3, generator=g, dtype=torch.float64)
    cols = c0[:, None] + torch.einsum("gvb,gbc->gvc", sh_basis(d, 1)[..., 1:], a)
    c0_fit, a_fit = fit_sh1(cols, d, torch.ones(50, 6, dtype=torch.bool), ridge=1e-12)
    torch.testing.assert_close(c0_fit, c0, atol=1e-6, rtol=0)
    torch.testing.assert_close(a_fit, a, atol=1e-6, rtol=0)
    # one view only: the fit is that view's colour and no direction dependence
    one = torch.zeros(50, 6, dtype=torch.bool)
    one[:, 0] = True
    c0_1, a_1 = fit_sh1(cols, d, one)
    assert a_1.abs().max() < 1e-4
    torch.testing.assert_close(c0_1, cols[:, 0], atol=1e-4, rtol=0)


def test_sh_in_the_file_is_read_as_3dgs_does(tmp_path):
    """Degree-1 coefficients written channel-major in f_rest and evaluated by the independent renderer's SH."""
    g = torch.Generator().manual_seed(1)
    n = 20
    rest = 0.2 * torch.randn(n, 3, 3, generator=g)
    colors = torch.rand(n, 3, generator=g) * 0.5 + 0.25
    means = torch.randn(n, 3, generator=g) + torch.tensor([0.0, 0.0, 4.0])
    write_gaussians_ply(tmp_path / "sh.ply", means, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                        torch.full((n, 3), 0.05), torch.full((n,), 0.5), colors, rest)
    ply = standard_splat.read_ply(tmp_path / "sh.ply")
    cam = np.array([0.3, -0.2, 0.0])
    d = means.double() - torch.from_numpy(cam)
    d = d / d.norm(dim=1, keepdim=True)
    theirs = standard_splat._sh_colour(ply, d)
    ours = ExplicitGaussians.from_ply(tmp_path / "sh.ply").colors(cam)
    expect = colors.double() + torch.einsum("nb,nbc->nc", sh_basis(d, 1)[:, 1:], rest.double())
    torch.testing.assert_close(theirs, expect, atol=1e-5, rtol=0)
    torch.testing.assert_close(ours.double(), expect, atol=1e-5, rtol=0)
