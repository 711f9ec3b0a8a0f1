"""The decoder's three MLPs for the mapper's training step: one autograd node with a hand-written backward.

Math (``ChildDecoder.raw`` is the plain-torch reference; tests/test_decoder_mlps.py checks values and gradients
against it and against finite differences): for decoded anchor m (row ``rows[m]`` of the map's features [A, F])
the input is ``x = [features[rows[m]], view]`` with ``view`` the unit ray and distance from the camera (a
view-dependent decoder) or nothing (the default: the first layers' four view columns then multiply zeros and are
left out), and each MLP is ``linear -> ReLU -> linear``.

Why not autograd: at 10k anchors the matrix products of a step take ~6 ms, and autograd's graph around them took
as long again in small operations: the feature rows gathered with ``index_select`` and their gradient scattered
back by ``index_add`` into a zeroed [A, F] tensor, the weights' column slice and its backward, the three MLPs'
feature gradients added pairwise, a node per operation. Here the forward saves x and the hidden activations; the
backward forms the weight and bias gradients and sums the feature gradient of the three MLPs in place (``addmm_``),
then writes it into the rows of the [A, F] gradient (``index_copy_``: the decoded rows are distinct).
"""
from __future__ import annotations

import torch
from torch import nn
from torch.autograd.function import once_differentiable


class _DecoderMLPs(torch.autograd.Function):
    @staticmethod
    def forward(ctx, features, rows, view, *params):
        x = features.index_select(0, rows)  # [M, F]
        if view is not None:
            x = torch.cat([x, view.to(x.dtype)], dim=1)  # [M, F + 4]
        n_in = x.shape[1]
        outs, hidden = [], []
        for i in range(0, len(params), 4):
            w1, b1, w2, b2 = params[i:i + 4]
            h = torch.addmm(b1, x, w1[:, :n_in].t()).relu_()  # [M, H]
            outs.append(torch.addmm(b2, h, w2.t()))  # [M, n_out]
            hidden.append(h)
        ctx.save_for_backward(x, rows, *hidden, *params)
        ctx.shape = (features.shape, len(hidden))
        return tuple(outs)

    @staticmethod
    @once_differentiable
    def backward(ctx, *g_outs):
        (f_shape, n_mlp), saved = ctx.shape, ctx.saved_tensors
        x, rows, hidden, params = saved[0], saved[1], saved[2:2 + n_mlp], saved[2 + n_mlp:]
        n_in, n_feat = x.shape[1], f_shape[1]
        want_f = ctx.needs_input_grad[0]
        g_x = None  # [M, F]
        g_params = []
        for h, g_y, i in zip(hidden, g_outs, range(0, len(params), 4)):
            w1, b1, w2, b2 = params[i:i + 4]
            if g_y is None:  # this MLP's output did not reach the loss
                g_params += [None] * 4
                continue
            g_w2 = g_y.t().mm(h)  # [n_out, H]
            g_b2 = g_y.sum(dim=0)
            # ReLU's gradient (0 at 0, as torch); one pass, where a mask and a product took two (~0.3 ms each MLP)
            g_h = torch.ops.aten.threshold_backward(g_y.mm(w2), h, 0.0)  # [M, H]
            g_w1 = g_h.t().mm(x)  # [H, n_in]
            if n_in < w1.shape[1]:  # the view columns multiplied zeros
                g_w1 = torch.cat([g_w1, g_w1.new_zeros(g_w1.shape[0], w1.shape[1] - n_in)], dim=1)
            g_params += [g_w1, g_h.sum(dim=0), g_w2, g_b2]
            if want_f:
                w_feat = w1[:, :n_feat]
                g_x = g_h.mm(w_feat) if g_x is None else g_x.addmm_(g_h, w_feat)
        g_features = None
        if want_f:
            g_features = x.new_zeros(f_shape)
            if g_x is not None:
                g_features.index_copy_(0, rows, g_x)
        return (g_features, None, None, *g_params)


def decoder_mlps(mlps: tuple[nn.Sequential, ...], features: torch.Tensor, rows: torch.Tensor,
                 view: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:
    """Outputs [M, n_out] of each ``linear -> ReLU -> linear`` MLP for the rows ``rows`` [M] (distinct) of
    ``features`` [A, F], with ``view`` [M, 4] (no gradient) appended to the input when given; the gradient of
    ``features`` comes back [A, F], zero in the rows not decoded."""
    if rows.numel() > 1 and not bool((rows[1:] > rows[:-1]).all()) and torch.unique(rows).numel() != rows.numel():
        raise ValueError("decoder_mlps: rows must be distinct (each decoded anchor once)")
    params = []
    for first, _act, last in mlps:
        params += [first.weight, first.bias, last.weight, last.bias]
    return _DecoderMLPs.apply(features, rows, None if view is None else view.detach(), *params)
