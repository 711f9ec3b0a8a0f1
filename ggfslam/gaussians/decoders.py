"""MLP decoders of Scaffold-GS: from an anchor's feature and the viewing ray to its k children.

Input per anchor: ``[f_v (F), view direction (3), distance (1)]`` where the direction is the unit vector
from the camera centre to the anchor (world frame) and the distance is in metres. With
``view_dependent=False`` the direction and distance are zeroed (a view-independent map, e.g. for export).
Outputs per child (Scaffold-GS activations):
- opacity ``tanh(.)``; children with opacity <= 0 are dropped from the render (Scaffold-GS's mask);
- colour ``sigmoid(base_color_logit + .)`` (see anchor_map.py for the per-anchor base colour);
- scale ``l_v * sigmoid(.)`` and rotation: a quaternion (w, x, y, z) normalised by the renderer, biased
  towards identity so the first renders are well-conditioned.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn


@dataclass
class DecodedGaussians:
    """Explicit Gaussians decoded for one view (the renderer's inputs) and where they came from."""

    means: torch.Tensor  # [G, 3] world
    quats: torch.Tensor  # [G, 4] w, x, y, z (unnormalised)
    scales: torch.Tensor  # [G, 3] linear standard deviations
    opacities: torch.Tensor  # [G] in (0, 1]
    colors: torch.Tensor  # [G, 3] in (0, 1)
    anchor_index: torch.Tensor  # [G] int64 index of the parent anchor in the map
    child_index: torch.Tensor  # [G] int64 global child id = anchor_index * k + slot

    def __len__(self) -> int:
        return int(self.means.shape[0])


def _mlp(n_in: int, hidden: int, n_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(), nn.Linear(hidden, n_out))


class ChildDecoder(nn.Module):
    """Opacity, colour and covariance MLPs shared by all anchors."""

    def __init__(self, feature_dim: int = 32, k: int = 10, hidden: int = 32, view_dependent: bool = True):
        super().__init__()
        self.k, self.hidden, self.view_dependent = k, hidden, view_dependent
        n_in = feature_dim + 4
        self.opacity = _mlp(n_in, hidden, k)
        self.color = _mlp(n_in, hidden, 3 * k)
        self.cov = _mlp(n_in, hidden, 7 * k)
        with torch.no_grad():
            # start near the base colour and an identity rotation; small random rest keeps children distinct
            self.color[-1].weight.mul_(0.1)
            self.color[-1].bias.zero_()
            self.cov[-1].weight.mul_(0.1)
            b = self.cov[-1].bias.view(k, 7)
            b.zero_()
            b[:, 3] = 1.0
            self.opacity[-1].bias.fill_(0.1)  # tanh(0.1): every child starts faintly visible

    def forward(self, anchors: torch.Tensor, features: torch.Tensor, log_scale: torch.Tensor,
                offsets: torch.Tensor, base_color: torch.Tensor, cam_center: torch.Tensor,
                anchor_index: torch.Tensor) -> DecodedGaussians:
        """Decode the children of M anchors: anchors [M, 3], features [M, F], log_scale [M, 3],
        offsets [M, k, 3], base_color [M, 3] (logits), cam_center [3], anchor_index [M]."""
        m, k = anchors.shape[0], self.k
        ray = anchors - cam_center  # [M, 3]
        dist = ray.norm(dim=1, keepdim=True).clamp_min(1e-6)  # [M, 1]
        view = torch.cat([ray / dist, dist], dim=1)
        if not self.view_dependent:
            view = torch.zeros_like(view)
        x = torch.cat([features, view], dim=1)  # [M, F + 4]
        opacity = torch.tanh(self.opacity(x)).reshape(m * k)  # [M k]
        color = torch.sigmoid(self.color(x).view(m, k, 3) + base_color[:, None, :]).reshape(m * k, 3)
        cov = self.cov(x).view(m, k, 7)
        scale = torch.exp(log_scale)  # [M, 3]
        child_scales = (scale[:, None, :] * torch.sigmoid(cov[..., :3])).reshape(m * k, 3)
        quats = cov[..., 3:].reshape(m * k, 4)
        means = (anchors[:, None, :] + offsets * scale[:, None, :]).reshape(m * k, 3)
        child = (anchor_index[:, None] * k + torch.arange(k)[None, :]).reshape(m * k)
        # one gather of the kept children instead of six boolean-mask indexings (each a nonzero + copy, and
        # an index_put in backward): ~10 ms per step at 100k children
        keep = torch.nonzero(opacity.detach() > 0)[:, 0]  # [G]
        packed = torch.cat([means, quats, child_scales, opacity[:, None], color], dim=1)  # [M k, 14]
        # split, not slicing: its backward is one cat instead of a zero-filled copy per slice
        m_, q_, s_, o_, c_ = packed.index_select(0, keep).split([3, 4, 3, 1, 3], dim=1)
        child = child.index_select(0, keep)
        return DecodedGaussians(m_, q_, s_, o_[:, 0], c_, child // k, child)
