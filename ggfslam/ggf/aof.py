"""Asymmetric Optimization Feedback (METHOD.md §6): the optimized Gaussians teach the residual net.

``P_post = 1 - s_min / s_mid`` of an anchor's children (their mean) says how flat the photometric and
geometric losses made them. With margin ``m``:
- evolution (``P_post - P_prior > m``): the Gaussians found a surface the prior missed; target ``P_post``;
- degeneration suppression (``P_post - P_prior < -m``): blobs where the geometry is flat are not believed
  (they are under-trained or fit texture); target ``P_prior``;
- consolidation (otherwise): target ``P_post`` with the loss scaled by ``lambda_con``.
The loss is the binary cross-entropy of ``P_2D`` against the target, on the net's own optimizer. Targets
are computed from detached Gaussians, and ``P_2D`` enters the Gaussians' render detached, so no gradient
crosses between the map and the net in either direction.
"""
from __future__ import annotations

import torch

EVOLUTION, SUPPRESSION, CONSOLIDATION = 0, 1, 2


def posterior_flatness(scales: torch.Tensor, anchor_index: torch.Tensor, n_anchors: int
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean over each anchor's children of 1 - s_min / s_mid: scales [G, 3], parent anchor [G] ->
    (P_post [n_anchors], number of children [n_anchors]); anchors without children get 0."""
    s = scales.detach().sort(dim=1).values  # [G, 3] ascending
    flat = 1.0 - s[:, 0] / s[:, 1].clamp_min(1e-12)
    total = torch.zeros(n_anchors, dtype=s.dtype).index_add_(0, anchor_index, flat)
    count = torch.zeros(n_anchors, dtype=s.dtype).index_add_(0, anchor_index, torch.ones_like(flat))
    return total / count.clamp_min(1), count


def feedback_targets(p_post: torch.Tensor, p_prior: torch.Tensor, margin: float, lambda_con: float
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(target [A], loss weight [A], regime [A] in {EVOLUTION, SUPPRESSION, CONSOLIDATION}) of the AOF rules."""
    d = p_post - p_prior
    regime = torch.full_like(d, CONSOLIDATION, dtype=torch.int64)
    regime[d > margin] = EVOLUTION
    regime[d < -margin] = SUPPRESSION
    target = torch.where(regime == SUPPRESSION, p_prior, p_post)
    weight = torch.where(regime == CONSOLIDATION, torch.full_like(d, lambda_con), torch.ones_like(d))
    return target.detach(), weight.detach(), regime


def feedback_loss(p2d: torch.Tensor, target: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Weighted binary cross-entropy of P_2D [A] against the AOF targets [A] (mean over anchors)."""
    bce = torch.nn.functional.binary_cross_entropy(p2d.clamp(1e-6, 1 - 1e-6), target, reduction="none")
    return (weight * bce).mean()
