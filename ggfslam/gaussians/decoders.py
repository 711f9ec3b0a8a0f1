"""MLP decoders of Scaffold-GS: from an anchor's feature to its k children.

Default (``view_dependent=False``): the three MLPs read the anchor's feature only (their four view inputs are
zeros), so a child has one shape and opacity from every viewpoint, and the colour MLP outputs per child a DC
logit and real spherical-harmonic coefficients of degree ``sh_degree`` (0-3) that the child head
(child_head.py) evaluates for the direction from the camera centre to the child, as 3DGS does. The decoded map
is then exactly a standard 3DGS model: gaussians.ply reproduces the render (bake.py), and frames between
keyframes see the geometry the keyframes trained.
Scaffold-GS's own design (``view_dependent=True``): all three MLPs also read the unit direction from the camera
centre to the anchor and its distance, so opacity, shape and colour change with the viewpoint. On real data that
lets every keyframe's view switch children on and off for itself; one explicit file cannot hold that (on TUM
fr3/cabinet the baked file scored ~3 dB under the map's own render at the keyframes, after matching exposure).
Outputs per child (Scaffold-GS activations):
- opacity ``tanh(.)``; children with opacity <= 0 are dropped from the render (Scaffold-GS's mask);
- colour ``sigmoid(base_color_logit + .)`` plus the SH terms (see anchor_map.py for the per-child base colour);
- scale ``l_v * sigmoid(.)`` and rotation: a quaternion (w, x, y, z) normalised by the renderer, biased
  towards identity so the first renders are well-conditioned.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ggfslam.gaussians.child_head import SurfelSpec, child_head
from ggfslam.gaussians.decoder_mlps import decoder_mlps


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
    sh_rest: torch.Tensor | None = None  # [G, B, 3] SH coefficients of degree >= 1 (a bake); colors = the DC part
    _unshaped: tuple | None = field(default=None, repr=False)  # (raw_cov [M, k, 7], log_scale [M, 3], local [G], k)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def raw_shape(self) -> tuple | None:
        """(raw_cov [M, k, 7], log_scale [M, 3], local [G] anchor row of each child, k): the decoder's raw shape
        output behind these children (what ``unshaped`` reads), None for children without one (a bake)."""
        return self._unshaped

    def unshaped(self, sel: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The decoder's own rotation [S, 4] and scales [S, 3] of children ``sel`` [S] before AMR made surfels of
        them (differentiable; what L_morph acts on)."""
        if self._unshaped is None:
            return self.quats[sel], self.scales[sel]
        raw_cov, log_scale, local, k = self._unshaped
        m, j = local[sel], self.child_index[sel] % k
        cov = raw_cov[m, j]  # [S, 7]
        return cov[:, 3:], torch.exp(log_scale[m]) * torch.sigmoid(cov[:, :3])


def _mlp(n_in: int, hidden: int, n_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(), nn.Linear(hidden, n_out))


def _view_inputs(anchors: torch.Tensor, cam_center: torch.Tensor) -> torch.Tensor:
    """A view-dependent decoder's extra inputs [M, 4]: the unit ray from the camera centre ([3] or [M, 3]) to each
    anchor [M, 3] and its length."""
    ray = anchors - cam_center  # [M, 3]
    dist = ray.norm(dim=1, keepdim=True).clamp_min(1e-6)  # [M, 1]
    return torch.cat([ray / dist, dist], dim=1)


def _without_view(mlp: nn.Sequential, features: torch.Tensor) -> torch.Tensor:
    """``mlp(cat([features, zeros(M, 4)]))`` [M, out] from features [M, F] alone (the first layer's view columns
    multiply zeros)."""
    first, act, last = mlp
    return last(act(F.linear(features, first.weight[:, :features.shape[1]], first.bias)))


class ChildDecoder(nn.Module):
    """Opacity, colour and covariance MLPs shared by all anchors."""

    def __init__(self, feature_dim: int = 32, k: int = 10, hidden: int = 32, view_dependent: bool = False,
                 sh_degree: int = 1, init_opacity: float = 0.1):
        super().__init__()
        if not 0 <= sh_degree <= 3:
            raise ValueError(f"sh_degree must be 0-3, got {sh_degree}")
        self.k, self.hidden, self.view_dependent, self.sh_degree = k, hidden, view_dependent, sh_degree
        self.n_sh = (sh_degree + 1) ** 2  # DC + SH coefficients per colour channel
        n_in = feature_dim + 4
        self.opacity = _mlp(n_in, hidden, k)
        self.color = _mlp(n_in, hidden, 3 * k * self.n_sh)
        self.cov = _mlp(n_in, hidden, 7 * k)
        with torch.no_grad():
            # start near the base colour and an identity rotation; small random rest keeps children distinct
            self.color[-1].weight.mul_(0.1)
            self.color[-1].bias.zero_()
            self.cov[-1].weight.mul_(0.1)
            b = self.cov[-1].bias.view(k, 7)
            b.zero_()
            b[:, 3] = 1.0
            self.opacity[-1].bias.fill_(float(np.arctanh(init_opacity)))  # every child starts visible

    def raw(self, anchors: torch.Tensor, features: torch.Tensor, cam_center: torch.Tensor | None = None
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The MLPs' raw outputs for M anchors: opacity [M, k], colour [M, k, n_sh, 3] (DC logit, then SH
        coefficients), covariance [M, k, 7]. ``cam_center`` ([3] or one per anchor [M, 3]) is read only by a
        view-dependent (Scaffold-GS) decoder."""
        m, k = anchors.shape[0], self.k
        if self.view_dependent:
            x = torch.cat([features, _view_inputs(anchors, cam_center)], dim=1)  # [M, F + 4]
            return self.opacity(x), self.color(x).view(m, k, self.n_sh, 3), self.cov(x).view(m, k, 7)
        # the four view inputs are zeros: the first layers leave them out (the same sums without the cat and four
        # of each row's products; ~4% of the MLPs' forward + backward at 10k anchors)
        o, c, v = (_without_view(mlp, features) for mlp in (self.opacity, self.color, self.cov))
        return o, c.view(m, k, self.n_sh, 3), v.view(m, k, 7)

    def dense(self, anchors: torch.Tensor, features: torch.Tensor, log_scale: torch.Tensor, offsets: torch.Tensor,
              base_color: torch.Tensor, cam_center: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Every child of M anchors, none dropped: (means [M, k, 3], quats [M, k, 4], scales [M, k, 3],
        opacity [M, k] (tanh, may be <= 0), colour [M, k, 3] seen from ``cam_center`` ([3] or [M, 3]))."""
        raw_o, raw_c, cov = self.raw(anchors, features, cam_center)
        scale = torch.exp(log_scale)  # [M, 3]
        child_scales = scale[:, None, :] * torch.sigmoid(cov[..., :3])  # [M, k, 3]
        means = anchors[:, None, :] + offsets * scale[:, None, :]  # [M, k, 3]
        return means, cov[..., 3:], child_scales, torch.tanh(raw_o), self._color(raw_c, base_color, means, cam_center)

    def _color(self, raw_c: torch.Tensor, base_color: torch.Tensor, means: torch.Tensor, cam_center) -> torch.Tensor:
        """Colour [M, k, 3] of children at means [M, k, 3] from raw_c [M, k, n_sh, 3], seen from cam_center
        (plain torch, differentiable in the means through the viewing direction too)."""
        color = torch.sigmoid(raw_c[:, :, 0] + base_color)  # [M, k, 3]
        if self.sh_degree == 0:
            return color
        from ggfslam.gaussians.explicit import sh_basis

        c = torch.as_tensor(cam_center, dtype=means.dtype)
        d = (means - (c[:, None, :] if c.dim() == 2 else c))
        d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        Y = sh_basis(d.reshape(-1, 3), self.sh_degree)[:, 1:].view(*means.shape[:2], -1)  # [M, k, n_sh - 1]
        return (color + (Y[..., None] * raw_c[:, :, 1:]).sum(dim=2)).clamp_min(0.0)

    def sh(self, features: torch.Tensor, base_color: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The view-independent decoder's colours as 3DGS SH: DC colour [M, k, 3] (``sigmoid``, what f_dc
        encodes) and the higher coefficients [M, k, n_sh - 1, 3] (``f_rest``)."""
        if self.view_dependent:
            raise ValueError("a view-dependent (Scaffold-GS) decoder has no SH colours")
        raw_c = self.raw(features.new_zeros(len(features), 3), features)[1]
        return torch.sigmoid(raw_c[:, :, 0] + base_color), raw_c[:, :, 1:]

    def forward(self, anchors: torch.Tensor, features: torch.Tensor, log_scale: torch.Tensor,
                offsets: torch.Tensor, base_color: torch.Tensor, cam_center: torch.Tensor,
                anchor_index: torch.Tensor, surfels: SurfelSpec | None = None) -> DecodedGaussians:
        """Decode the children of the M anchors ``anchor_index`` [M] (distinct rows) of the map's arrays anchors
        [A, 3], features [A, F], log_scale [A, 3], offsets [A, k, 3], base_color [A, k, 3] (logits), seen from
        cam_center [3] (a view-dependent decoder also takes one viewpoint per decoded anchor, [M, 3]); ``surfels``
        applies AMR to the children of planar anchors. Children with opacity <= 0 are dropped. The MLPs run as one
        autograd node (decoder_mlps.py), the rest in the compiled child head; neither gathers the anchors' rows
        into copies, so their gradients come back [A, ...] without a scatter."""
        m, k = anchor_index.shape[0], self.k
        view = _view_inputs(anchors.index_select(0, anchor_index), cam_center) if self.view_dependent else None
        raw_o, raw_c, raw_cov = decoder_mlps((self.opacity, self.color, self.cov), features, anchor_index, view)
        raw_c, raw_cov = raw_c.view(m, k, self.n_sh, 3), raw_cov.view(m, k, 7)
        cam = None if self.sh_degree == 0 else cam_center
        means, quats, scales, opac, color, child, parent, local = child_head(
            raw_o, raw_c, raw_cov, anchors, log_scale, offsets, base_color, anchor_index, surfels, cam, self.sh_degree)
        return DecodedGaussians(means, quats, scales, opac, color, parent, child,
                                _unshaped=(raw_cov, log_scale.index_select(0, anchor_index), local, self.k))

    def reference(self, anchors: torch.Tensor, features: torch.Tensor, log_scale: torch.Tensor,
                  offsets: torch.Tensor, base_color: torch.Tensor, cam_center: torch.Tensor,
                  anchor_index: torch.Tensor) -> DecodedGaussians:
        """``forward`` without AMR in plain torch autograd (the parity reference of the child head)."""
        m, k = anchors.shape[0], self.k
        means, quats, child_scales, opacity, color = self.dense(anchors, features, log_scale, offsets, base_color,
                                                                cam_center)
        opacity = opacity.reshape(m * k)
        child = (anchor_index[:, None] * k + torch.arange(k)[None, :]).reshape(m * k)
        keep = torch.nonzero(opacity.detach() > 0)[:, 0]  # [G]
        packed = torch.cat([means.reshape(m * k, 3), quats.reshape(m * k, 4), child_scales.reshape(m * k, 3),
                            opacity[:, None], color.reshape(m * k, 3)], dim=1)  # [M k, 14]
        m_, q_, s_, o_, c_ = packed.index_select(0, keep).split([3, 4, 3, 1, 3], dim=1)
        child = child.index_select(0, keep)
        return DecodedGaussians(m_, q_, s_, o_[:, 0], c_, child // k, child)
