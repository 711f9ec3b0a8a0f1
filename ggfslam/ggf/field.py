"""The Geometric-Gaussian Field (METHOD.md §3): a geometric prior plus a learned residual.

``P_prior = sigmoid(w1 (tau - kappa)) * exp(-w2 V_color) * (1 - exp(-T / T0))``: flat, photo-consistent,
often-seen neighbourhoods are planar. ``Phi_theta`` (41 -> 64 -> 64 -> 1, last layer zero so the field
starts equal to the prior) adds ``delta`` in logit space: ``P_2D = sigmoid(logit(P_prior) + delta)``.
"""
from __future__ import annotations

import torch
from torch import nn

from ggfslam.ggf.features import F_IN

PRIOR_CLAMP = 1e-4


def planar_prior(curvature: torch.Tensor, color_var: torch.Tensor, obs: torch.Tensor, tau: float, w1: float,
                 w2: float, t0: float) -> torch.Tensor:
    """P_prior [A] from curvature kappa [A], colour variance V_color [A] and observation count T [A]."""
    return torch.sigmoid(w1 * (tau - curvature)) * torch.exp(-w2 * color_var) * (1.0 - torch.exp(-obs / t0))


def planar_probability(prior: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """P_2D = sigmoid(logit(P_prior) + delta), P_prior clamped to [1e-4, 1 - 1e-4] first."""
    return torch.sigmoid(torch.logit(prior.clamp(PRIOR_CLAMP, 1.0 - PRIOR_CLAMP)) + delta)


class ResidualField(nn.Module):
    """Phi_theta: F_in [A, 41] -> delta_geo [A], zero at initialisation."""

    def __init__(self, hidden: int = 64, n_in: int = F_IN):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, 1))
        with torch.no_grad():
            self.net[-1].weight.zero_()
            self.net[-1].bias.zero_()

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """The residual logit [M] of anchors with features [M, F]."""
        return self.net(features)[:, 0]
