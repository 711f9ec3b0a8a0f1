"""The depth-spread loss (``mapping.lambda_depth_spread``): its value on hand-made two-layer renders, its gradient
through the renderer against finite differences, and that training with it pulls each ray's Gaussians onto one
depth."""
from __future__ import annotations

import tempfile

import numpy as np
import pytest
import torch

from ggfslam.config import MappingConfig
from ggfslam.eval.image import psnr
from ggfslam.mapping.losses import depth_spread_loss
from ggfslam.mapping.mapper import Mapper
from ggfslam.render import rasterize
from ggfslam.render.types import Intrinsics, RenderSettings

INTR = Intrinsics(fx=60.0, fy=60.0, cx=32.0, cy=24.0, width=64, height=48)  # principal point on a pixel centre


def _two_layers(dtype=torch.float64, z=(1.5, 2.5), opac=(0.6, 0.7), scale=3.0):
    """Two wide round Gaussians on the optical axis at depths z (camera = world frame)."""
    means = torch.tensor([[0.0, 0.0, z[0]], [0.05, -0.03, z[1]]], dtype=dtype)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, dtype=dtype)
    scales = torch.full((2, 3), scale, dtype=dtype)
    return means, quats, scales, torch.tensor(opac, dtype=dtype)


def _spread(means, quats, scales, opac, backend):
    """(loss, per-pixel ratio inputs) of a render whose extra channel is each Gaussian's squared view depth."""
    out = rasterize(means, quats, scales, opac, torch.full_like(means, 0.5), INTR, torch.eye(4, dtype=means.dtype),
                    extras=means[:, 2:3] ** 2, backend=backend)
    return depth_spread_loss(out.depth_raw, out.extras[..., 0], out.alpha), out


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_spread_is_zero_on_one_surface_and_the_weighted_variance_across_two(backend):
    """One Gaussian, or two at one depth: no spread anywhere. Two layers at 1.5 and 2.5 m: at the pixel both centres
    project to, alpha is each opacity, so the weights are o1 and (1 - o1) o2 and the loss at that pixel is their
    variance of depth over the squared mean depth."""
    means, quats, scales, opac = _two_layers()
    one, _ = _spread(means[:1], quats[:1], scales[:1], opac[:1], backend)
    assert float(one) == pytest.approx(0.0, abs=1e-6)
    same = means.clone()
    same[1, 2] = same[0, 2]
    flat, _ = _spread(same, quats, scales, opac, backend)
    assert float(flat) == pytest.approx(0.0, abs=1e-6)

    centred = means.clone()
    centred[1, :2] = 0.0
    _, out = _spread(centred, quats, scales, opac, backend)
    v, u = int(INTR.cy), int(INTR.cx)
    px = [t[v:v + 1, u:u + 1] for t in (out.depth_raw, out.extras[..., 0], out.alpha)]
    got = float(depth_spread_loss(*px))
    w = np.array([0.6, 0.4 * 0.7])
    zz = np.array([1.5, 2.5])
    mean = (w * zz).sum() / w.sum()
    want = ((w * (zz - mean) ** 2).sum() / w.sum()) / mean ** 2
    assert want > 0.02  # a real spread, not a rounding residue
    assert got == pytest.approx(want, rel=1e-4 if backend == "cpu" else 1e-9)


def test_spread_counts_the_pixels_asked_for_and_does_not_reward_transparency():
    """Pixels outside ``valid``, without blended depth or with alpha <= min_alpha add nothing and are not counted;
    scaling every weight of a pixel (a more transparent map) leaves its spread unchanged."""
    raw = torch.tensor([[1.0, 2.0, 0.0, 1.0, 3.0]], dtype=torch.float64)
    sq = torch.tensor([[1.25, 100.0, 0.0, 1.0, 50.0]], dtype=torch.float64)
    alpha = torch.tensor([[1.0, 0.005, 0.9, 1.0, 0.9]], dtype=torch.float64)
    valid = torch.tensor([[True, True, True, True, False]])
    # pixels 0 and 3 count: (1 * 1.25 / 1^2 - 1 + 0) / 2
    assert float(depth_spread_loss(raw, sq, alpha, valid)) == pytest.approx(0.125)
    for c in (0.6, 0.1):
        assert float(depth_spread_loss(c * raw, c * sq, c * alpha, valid)) == pytest.approx(0.125)


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_spread_gradient_through_the_renderer_matches_finite_differences(backend):
    """d(loss)/d(means) of the two layers (every pixel covered with alpha ~0.88, so no pixel enters or leaves the
    loss under the probe): float64 reference and the compiled float32 kernel against central differences."""
    means, quats, scales, opac = _two_layers()
    m = means.clone().requires_grad_(True)
    loss, _ = _spread(m, quats, scales, opac, backend)
    loss.backward()
    h = 1e-4 if backend == "reference" else 2e-3
    num = torch.zeros_like(means)
    with torch.no_grad():
        for i in range(2):
            for k in range(3):
                e = torch.zeros_like(means)
                e[i, k] = h
                num[i, k] = (_spread(means + e, quats, scales, opac, backend)[0]
                             - _spread(means - e, quats, scales, opac, backend)[0]) / (2 * h)
    # the depths dominate: the front layer's move along z narrows the spread, the back one's widens it
    assert num[0, 2] < 0 < num[1, 2]
    tol = 1e-6 if backend == "reference" else 2e-2
    assert torch.allclose(m.grad, num, rtol=tol, atol=tol * num.abs().max())


def test_training_with_the_term_pulls_each_rays_gaussians_onto_one_depth(sequence):
    """The same keyframes, steps and initial weights with and without ``lambda_depth_spread``: the map trained with it
    renders the keyframes with about half the spread (every pixel counted alike; 0.52-0.55 of it over seeds 0-3) and
    a colour cost under 1.5 dB (0.5-0.9 dB over those seeds; 1.2 dB in one unseeded run), the cost that keeps it off
    by default."""
    poses = {kf: sequence.gt_poses[fi] for kf, fi in enumerate((0, 12, 24))}
    results = []
    for weight in (0.0, 10.0):
        with torch.random.fork_rng():  # the decoders' initial weights: alike in both runs, whatever ran before
            torch.manual_seed(0)
            m = Mapper(MappingConfig(train_width=160, lambda_depth_spread=weight), sequence.camera,
                       RenderSettings(backend="cpu"), lambda: dict(poses), tempfile.mkdtemp())
        for kf, fi in enumerate((0, 12, 24)):
            f = sequence[fi]
            m.add_keyframe(kf, fi, f.rgb, f.depth)
            m.train(40, focus=kf)
        spread, quality = [], []
        with torch.no_grad():
            for kf in poses:
                g, _ = m._decode_view(poses[kf], m.intr)
                out, mom = m._rasterize(g, m.intr, poses[kf], None, depth_moments=True)
                assert torch.allclose(mom[..., 0], out.depth_raw, rtol=1e-4, atol=1e-5)  # the same blend
                spread.append(float(depth_spread_loss(mom[..., 0], mom[..., 1], out.alpha)))
                color = m.sensor_image(out.color, m.intr, kf)
                quality.append(psnr(color.numpy(), m.store.get(kf).rgb))
        results.append((np.mean(spread), np.mean(quality)))
    (s0, p0), (s1, p1) = results
    assert s1 < 0.7 * s0, (s0, s1)  # seed 0: 0.00236 -> 0.00125
    assert p1 > p0 - 1.5, (p0, p1)  # seed 0: 27.36 -> 26.82 dB
