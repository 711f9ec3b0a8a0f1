"""Anchor growing and pruning (Scaffold-GS density control) from statistics gathered during training.

- Growing: every child accumulates the norm of its 2D-mean gradient each time it is rendered, in normalised
  device coordinates as 3DGS and Scaffold-GS measure it (pixel gradient times (W/2, H/2)), so the
  threshold (Scaffold-GS: 0.0002) does not depend on the training resolution.
  Children whose mean gradient exceeds ``grad_threshold`` after at least ``min_visits`` renders propose
  their position; proposals falling in a voxel without an anchor become new anchors (features, scale and
  colour copied from the parent anchor).
- Pruning: every anchor accumulates the mean opacity of its children each time it is in view; anchors
  seen at least ``min_visits`` times whose average stays below ``min_opacity`` are removed.
Both reset the statistics of what they touched.
- Merging: the map holds one anchor per voxel, but pose corrections (bundle adjustment, loop closure) move
  each keyframe's anchors rigidly, and a revisit seeded from a drifted pose lands on the surface an earlier
  visit already covers. ``merge_collisions`` keeps, in every voxel holding several anchors, the one that
  draws the most (highest mean opacity in view; never seen: the earliest created) and removes the rest, so
  a long sequence with loop closures does not stack copies of its surfaces (synthetic:2000 had 37% of its
  anchors in shared voxels; merged, it holds 70k anchors instead of 108k at the same PSNR).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from numba import njit

from ggfslam.gaussians.anchor_map import PER_ANCHOR_PARAMS, AnchorMap, voxel_keys
from ggfslam.gaussians.decoders import DecodedGaussians
from ggfslam.gaussians.optim import replace_param


@njit(cache=True, nogil=True)
def _accumulate(visits, mask, opacity_sum, anchor_index, opac, k, grad_sum, grad_count, child_index, visible, g2d, sx,
                sy, has_grad):
    """``DensityControl.accumulate``'s sums in place (float32, children in order): visits [A] += mask [A];
    opacity_sum [A] += the anchor's children's opacities [G] summed, over k; with has_grad, per child c:
    grad_sum[c] += |g2d * (sx, sy)| and grad_count[c] += 1 where visible (serial: children share anchors)."""
    A = visits.shape[0]
    opa = np.zeros(A, np.float32)
    for i in range(anchor_index.shape[0]):
        opa[anchor_index[i]] += opac[i]
    for a in range(A):
        visits[a] += np.float32(mask[a])
        opacity_sum[a] += opa[a] / k
    if has_grad:
        for i in range(child_index.shape[0]):
            w = np.float32(visible[i])
            x = g2d[i, 0] * sx
            y = g2d[i, 1] * sy
            c = child_index[i]
            grad_sum[c] += np.sqrt(x * x + y * y) * w
            grad_count[c] += w


@dataclass
class DensityStats:
    """Per-anchor and per-child accumulators; resized with the map."""

    grad_sum: torch.Tensor  # [A * k] sum of |d L / d mean2d| (NDC units)
    grad_count: torch.Tensor  # [A * k] renders in which the child was decoded and visible
    opacity_sum: torch.Tensor  # [A] sum of mean child opacity when in view
    visits: torch.Tensor  # [A] renders in which the anchor was in view

    @classmethod
    def empty(cls, n_anchors: int, k: int) -> DensityStats:
        """Zero statistics for n_anchors anchors of k children each."""
        return cls(torch.zeros(n_anchors * k), torch.zeros(n_anchors * k), torch.zeros(n_anchors),
                   torch.zeros(n_anchors))


class DensityControl:
    """Gathers the statistics and grows/prunes an ``AnchorMap`` (keeping an optimizer's state aligned)."""

    def __init__(self, amap: AnchorMap, grad_threshold: float, min_opacity: float, min_visits: int,
                 max_anchors: int):
        self.map = amap
        self.grad_threshold, self.min_opacity = grad_threshold, min_opacity
        self.min_visits, self.max_anchors = min_visits, max_anchors
        self.stats = DensityStats.empty(amap.n_anchors, amap.k)

    def on_append(self, n: int) -> None:
        """Extend the statistics after ``n`` anchors were appended to the map."""
        k = self.map.k
        s = self.stats
        self.stats = DensityStats(torch.cat([s.grad_sum, torch.zeros(n * k)]), torch.cat([s.grad_count, torch.zeros(n * k)]),
                                  torch.cat([s.opacity_sum, torch.zeros(n)]), torch.cat([s.visits, torch.zeros(n)]))

    @torch.no_grad()
    def accumulate(self, g: DecodedGaussians, visible: torch.Tensor, grad2d: torch.Tensor | None,
                   anchor_mask: torch.Tensor, image_size: tuple[int, int] = (2, 2)) -> None:
        """Add one render: decoded children g, their visibility [G] and 2D-mean gradient [G, 2] in pixels
        of an image of ``image_size`` (width, height)."""
        s, k = self.stats, self.map.k
        # one compiled pass (in torch: masks, three index_adds and a norm, 1.1 ms a step at 100k children)
        g2d = np.zeros((0, 2), np.float32) if grad2d is None else grad2d.detach().float().contiguous().numpy()
        _accumulate(s.visits.numpy(), anchor_mask.numpy(), s.opacity_sum.numpy(), g.anchor_index.numpy(),
                    g.opacities.detach().float().contiguous().numpy(), np.float32(k), s.grad_sum.numpy(),
                    s.grad_count.numpy(), g.child_index.numpy(), visible.numpy(), g2d, np.float32(image_size[0] / 2),
                    np.float32(image_size[1] / 2), grad2d is not None)

    @torch.no_grad()
    def grow(self, opt: torch.optim.Optimizer | None) -> int:
        """Add anchors where children's mean 2D gradient is large; returns how many were added."""
        s, amap, k = self.stats, self.map, self.map.k
        room = self.max_anchors - amap.n_anchors
        if room <= 0:
            return 0
        mean = s.grad_sum / s.grad_count.clamp_min(1)
        cand = torch.nonzero((s.grad_count >= self.min_visits) & (mean > self.grad_threshold))[:, 0]
        if len(cand) == 0:
            return 0
        cand = cand[torch.argsort(mean[cand], descending=True)]
        parent = cand // k
        slot = cand % k
        scale = torch.exp(amap.log_scale[parent])
        pos = (amap.anchors[parent] + amap.offsets[parent, slot] * scale).numpy().astype(np.float64)
        s.grad_sum[cand] = 0
        s.grad_count[cand] = 0
        first, _ = amap.free_voxels(pos)
        if len(first) == 0:
            return 0
        first = np.sort(first)[:room]  # cand is sorted by gradient: the strongest proposals first
        vals, order = amap.new_anchor_values(pos[first], np.full((len(first), 3), 0.5, np.float32), -1)
        src = parent[torch.from_numpy(first[order])]
        vals["features"] = amap.features[src].detach().clone()
        vals["log_scale"] = amap.log_scale[src].detach().clone()
        vals["base_color"] = amap.base_color[src].detach().clone()
        vals["source_kf"] = amap.source_kf[src].clone()  # grown anchors move with their parent's keyframe
        vals["surface"] = torch.from_numpy(pos[first[order]]).float()  # the proposing child's mean, until observed
        olds = {name: getattr(amap, name) for name in PER_ANCHOR_PARAMS}
        n = amap.append(vals)
        if opt is not None:
            for name in PER_ANCHOR_PARAMS:
                replace_param(opt, olds[name], getattr(amap, name), None, n)
        self.on_append(n)
        return n

    @torch.no_grad()
    def prune(self, opt: torch.optim.Optimizer | None) -> int:
        """Remove anchors whose children stayed nearly transparent; returns how many were removed."""
        s = self.stats
        avg = s.opacity_sum / s.visits.clamp_min(1)
        drop = (s.visits >= self.min_visits) & (avg < self.min_opacity)
        n = int(drop.sum())
        if n == 0:
            return 0
        self._keep(~drop, opt)
        # anchors that survived start a new observation period
        self.stats.opacity_sum.zero_()
        self.stats.visits.zero_()
        return n

    @torch.no_grad()
    def merge_collisions(self, opt: torch.optim.Optimizer | None) -> int:
        """Keep one anchor per voxel (the one drawing most, see the module docstring); returns how many were removed."""
        amap, s = self.map, self.stats
        if amap.n_anchors < 2:
            return 0
        keys = voxel_keys(amap.anchors.numpy().astype(np.float64), amap.voxel_size)  # [A]
        seen = (s.visits > 0).numpy()
        score = np.where(seen, (s.opacity_sum / s.visits.clamp_min(1)).numpy(), -1.0)  # [A]
        index = np.arange(amap.n_anchors)
        order = np.lexsort((index, -score, keys))  # by voxel, then best first, then oldest first
        first = np.ones(len(order), dtype=bool)
        first[1:] = keys[order[1:]] != keys[order[:-1]]
        keep = np.zeros(amap.n_anchors, dtype=bool)
        keep[order[first]] = True
        n = int((~keep).sum())
        if n:
            self._keep(torch.from_numpy(keep), opt)
        return n

    def _keep(self, keep: torch.Tensor, opt: torch.optim.Optimizer | None) -> None:
        """Keep only the anchors where keep [A] (bool) is True: map, optimizer state and statistics."""
        s, amap, k = self.stats, self.map, self.map.k
        olds = {name: getattr(amap, name) for name in PER_ANCHOR_PARAMS}
        amap.select(keep)
        if opt is not None:
            for name in PER_ANCHOR_PARAMS:
                replace_param(opt, olds[name], getattr(amap, name), keep, 0)
        keep_child = keep[:, None].expand(-1, k).reshape(-1)
        self.stats = DensityStats(s.grad_sum[keep_child], s.grad_count[keep_child], s.opacity_sum[keep],
                                  s.visits[keep])
