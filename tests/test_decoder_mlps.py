"""The decoder MLPs' fused autograd node (gaussians/decoder_mlps.py) against ``ChildDecoder.raw`` (plain torch
autograd) and finite differences."""
from __future__ import annotations

import pytest
import torch

from ggfslam.gaussians.decoder_mlps import decoder_mlps
from ggfslam.gaussians.decoders import ChildDecoder, _view_inputs


def _decoder(view_dependent: bool, dtype=torch.float64) -> ChildDecoder:
    torch.manual_seed(0)
    dec = ChildDecoder(feature_dim=6, k=3, hidden=5, view_dependent=view_dependent, sh_degree=1).to(dtype)
    with torch.no_grad():  # every weight non-trivial (the constructor shrinks some), some ReLUs off
        for p in dec.parameters():
            p.normal_(0.0, 0.7)
    return dec


@pytest.mark.parametrize("view_dependent", [False, True])
def test_fused_mlps_match_plain_autograd(view_dependent):
    dec = _decoder(view_dependent)
    g = torch.Generator().manual_seed(1)
    A = 9
    features = torch.randn(A, 6, generator=g, dtype=torch.float64, requires_grad=True)
    anchors = torch.randn(A, 3, generator=g, dtype=torch.float64)
    cam = torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)
    rows = torch.tensor([7, 2, 0, 5, 8])
    view = _view_inputs(anchors[rows], cam) if view_dependent else None
    mlps = (dec.opacity, dec.color, dec.cov)
    fused = decoder_mlps(mlps, features, rows, view)
    ref = dec.raw(anchors[rows], features[rows], cam)
    for a, b in zip(fused, ref):
        torch.testing.assert_close(a, b.reshape(a.shape), atol=1e-12, rtol=1e-12)
    weights = [torch.randn(a.shape, generator=g, dtype=torch.float64) for a in fused]
    params = [features, *dec.parameters()]

    def grads(outs):
        for p in params:
            p.grad = None
        sum((w * o.reshape(w.shape)).sum() for w, o in zip(weights, outs)).backward()
        return [p.grad.clone() for p in params]

    g_fused, g_ref = grads(fused), grads(dec.raw(anchors[rows], features[rows], cam))
    for a, b in zip(g_fused, g_ref):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-10)
    others = torch.tensor([i not in rows.tolist() for i in range(A)])
    assert torch.all(g_fused[0][others] == 0)


@pytest.mark.parametrize("view_dependent", [False, True])
def test_fused_mlps_gradients_match_finite_differences(view_dependent):
    from ggfslam.gaussians.decoder_mlps import _DecoderMLPs

    dec = _decoder(view_dependent)
    g = torch.Generator().manual_seed(2)
    features = torch.randn(6, 6, generator=g, dtype=torch.float64, requires_grad=True)
    rows = torch.tensor([4, 1, 3])
    view = torch.randn(3, 4, generator=g, dtype=torch.float64) if view_dependent else None
    params = []
    for first, _act, last in (dec.opacity, dec.color, dec.cov):
        params += [first.weight, first.bias, last.weight, last.bias]

    def f(feat, *ps):
        return torch.cat([o.flatten() for o in _DecoderMLPs.apply(feat, rows, view, *ps)])

    ins = [features] + [p.detach().clone().requires_grad_() for p in params]
    assert torch.autograd.gradcheck(f, ins, eps=1e-6, atol=1e-7)


def test_repeated_rows_are_refused():
    dec = _decoder(False)
    with pytest.raises(ValueError, match="distinct"):
        decoder_mlps((dec.opacity, dec.color, dec.cov), torch.zeros(4, 6, dtype=torch.float64), torch.tensor([1, 2, 1]))
