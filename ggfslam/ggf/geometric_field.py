"""The Geometric-Gaussian Field of a Gaussian map: features, prior, residual net, AMR and AOF together.

``GeometricGaussianField`` is what the mapper talks to:
- ``refresh(amap, cameras, iteration)`` recomputes the anchors' geometry (features.py) when anchors were
  added, removed or moved (a pose correction), and at most every ``refresh_every`` steps when keyframes
  only observed them again;
- ``p2d()`` gives P_2D [A] of every anchor (cached until the net or the geometry changes; no gradient);
- ``shape(g)`` applies AMR to decoded children and returns L_morph;
- ``feedback(g)`` runs one AOF step of the residual net from the children the mapper just optimized; only
  anchors whose children were free (not under AMR) give evidence.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ggfslam.config import GGFConfig
from ggfslam.gaussians.child_head import SurfelSpec
from ggfslam.gaussians.decoders import DecodedGaussians
from ggfslam.ggf.amr import morph_loss, quat_z_to, surfel_shape
from ggfslam.ggf.aof import EVOLUTION, SUPPRESSION, feedback_loss, feedback_targets, posterior_flatness
from ggfslam.ggf.features import AnchorGeometry, PlaneBorrowing, anchor_geometry
from ggfslam.ggf.field import ResidualField, planar_prior, planar_probability
from ggfslam.ggf.morph_kernels import morph_loss_raw


def planarity_colors(p2d: torch.Tensor) -> torch.Tensor:
    """Colours [N, 3] of planar probabilities [N]: red = 2D (P_2D = 1), blue = 3D (P_2D = 0)."""
    p = p2d.clamp(0, 1)[:, None]
    return p * torch.tensor([1.0, 0.0, 0.0]) + (1 - p) * torch.tensor([0.0, 0.0, 1.0])


MORPH_SAMPLES = 8192  # planar children L_morph is evaluated on per step


class GeometricGaussianField:
    """Planar probability of every anchor of one ``AnchorMap`` (see the module docstring)."""

    def __init__(self, cfg: GGFConfig, voxel_size: float, seed: int = 0):
        self.cfg, self.voxel_size = cfg, float(voxel_size)
        self.orient = cfg.surfel_orientation == "field"  # AMR turns surfels onto the anchors' normals
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.net = ResidualField(cfg.hidden)
        self.opt = torch.optim.Adam(self.net.parameters(), lr=cfg.lr)
        self.geom: AnchorGeometry | None = None
        self.prior = torch.zeros(0)  # [A]
        self._align: torch.Tensor | None = None  # [A, 4] rotation taking z onto each anchor's normal
        self._p2d: torch.Tensor | None = None
        self._versions = (-1, -1, -1)  # (layout, geometry, observed) versions of the map last refreshed from
        self._refreshed_at = -(10 ** 9)
        self.updates = 0
        self.regimes = np.zeros(3, np.int64)  # anchors trained in each AOF regime, cumulative
        self.last_loss = 0.0

    # --- geometry ------------------------------------------------------------------------------------
    def refresh(self, amap, camera_centers: dict[int, np.ndarray], iteration: int = 0, force: bool = False) -> bool:
        """Recompute the anchors' geometry and prior if the map changed (see the module docstring)."""
        versions = (amap.layout_version, amap.geometry_version, amap.observed_version)
        changed = self.geom is None or len(self.prior) != amap.n_anchors or versions[:2] != self._versions[:2]
        observed = versions[2] != self._versions[2] and iteration - self._refreshed_at >= self.cfg.refresh_every
        if not (changed or observed or force):
            return False
        c = self.cfg
        cell = c.patch_cell * self.voxel_size if c.patch_cell > 0 else None
        # anchors under tau / 2 already have a prior above 0.9 from curvature: not worth a search
        borrow = PlaneBorrowing(c.borrow_k, c.borrow_tol * self.voxel_size, c.borrow_factor, c.tau / 2)
        self.geom = anchor_geometry(amap, camera_centers, c.knn, c.tau, cell, borrow, c.curvature)
        self._align = quat_z_to(self.geom.normals)  # [A, 4]
        self.prior = planar_prior(self.geom.curvature, self.geom.color_var, self.geom.obs, c.tau, c.w1, c.w2, c.t0)
        self._versions, self._refreshed_at, self._p2d = versions, iteration, None
        return True

    @torch.no_grad()
    def p2d(self) -> torch.Tensor:
        """P_2D [A] of every anchor (after ``refresh``)."""
        if self._p2d is None:
            self._p2d = planar_probability(self.prior, self.net(self.geom.features))
        return self._p2d

    def planar(self) -> torch.Tensor:
        """[A] bool: anchors above the planar threshold."""
        return self.p2d() > self.cfg.planar_threshold

    # --- AMR -----------------------------------------------------------------------------------------
    def surfel_spec(self, index: torch.Tensor) -> SurfelSpec | None:
        """AMR's inputs for anchors ``index`` [M] (the child head applies them while decoding); None
        when AMR is off or none of them is planar."""
        if not self.cfg.amr or len(index) == 0:
            return None
        planar = self.planar().index_select(0, index)  # [M]
        if not bool(planar.any()):
            return None
        geo, c = self.geom, self.cfg
        return SurfelSpec(planar, geo.normals.index_select(0, index), self._align.index_select(0, index),
                          geo.plane_points.index_select(0, index),
                          c.surfel_radius * geo.spacing.index_select(0, index), c.surfel_eps * self.voxel_size, c.snap,
                          self.orient)

    def morph(self, g: DecodedGaussians) -> torch.Tensor:
        """L_morph over (an even sample of) the children of planar anchors in g, on the decoder's own shape
        (``g.unshaped``): it keeps children surfel-like should their anchor later drop below the threshold."""
        if not self.cfg.amr or len(g) == 0:
            return torch.zeros(())
        idx = torch.nonzero(self.planar().index_select(0, g.anchor_index))[:, 0]
        if len(idx) == 0:
            return torch.zeros(())
        if len(idx) > MORPH_SAMPLES:  # an evenly spaced sample: the loss trains the shared decoder, not each child
            idx = idx[:: -(-len(idx) // MORPH_SAMPLES)]
        c = self.cfg
        n = self.geom.normals.index_select(0, g.anchor_index[idx])
        eps = c.surfel_eps * self.voxel_size
        lambda_dir = c.lambda_dir if self.orient else 0.0  # the decoder's own z axis is the normal then
        raw = g.raw_shape()
        if raw is not None:  # the compiled loss on the raw output (parity-tested against morph_loss)
            raw_cov, log_scale, local, k = raw
            return morph_loss_raw(raw_cov, log_scale, local[idx], g.child_index[idx] % k, n, eps, self.voxel_size,
                                  lambda_dir, c.lambda_thin)
        quats, scales = g.unshaped(idx)
        return morph_loss(quats, scales, n, eps, self.voxel_size, lambda_dir, c.lambda_thin)

    def shape(self, g: DecodedGaussians) -> tuple[DecodedGaussians, torch.Tensor]:
        """Children g of the map decoded without AMR (``decode(reference=True)``) with AMR applied to those of
        planar anchors in plain torch, and L_morph: the reference of the child head's AMR."""
        zero = torch.zeros(())
        if not self.cfg.amr or len(g) == 0:
            return g, zero
        a = g.anchor_index
        planar = self.planar().index_select(0, a)  # [G]
        if not bool(planar.any()):
            return g, zero
        geo, c = self.geom, self.cfg
        n = geo.normals.index_select(0, a)  # [G, 3]
        eps = c.surfel_eps * self.voxel_size
        radius = c.surfel_radius * geo.spacing.index_select(0, a)
        quats, scales, means = surfel_shape(g.quats, g.scales, g.means, n, geo.plane_points.index_select(0, a),
                                            radius, eps, self._align.index_select(0, a), planar, c.snap, self.orient)
        l_morph = self.morph(g)
        return DecodedGaussians(means, quats, scales, g.opacities, g.colors, g.anchor_index, g.child_index), l_morph

    # --- AOF -----------------------------------------------------------------------------------------
    def feedback(self, g: DecodedGaussians) -> float:
        """One AOF step of the residual net from the optimized children g (their scales, detached)."""
        p_post, count = posterior_flatness(g.scales, g.anchor_index, len(self.prior))
        # anchors under AMR are left out: their children's thickness is eps by construction, so P_post = 1
        # would be AMR confirming itself (with them in, every anchor of the synthetic room went planar,
        # curved objects included, within 140 updates)
        free = count > 0
        if self.cfg.amr:
            free &= ~self.planar()
        sel = torch.nonzero(free)[:, 0]
        if len(sel) == 0:
            return 0.0
        prior = self.prior[sel]
        target, weight, regime = feedback_targets(p_post[sel], prior, self.cfg.margin, self.cfg.lambda_con)
        p2d = planar_probability(prior, self.net(self.geom.features[sel]))
        loss = feedback_loss(p2d, target, weight)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self._p2d = None
        self.updates += 1
        self.regimes += np.bincount(regime.numpy(), minlength=3)
        self.last_loss = float(loss.item())
        return self.last_loss

    # --- reporting and checkpoint ------------------------------------------------------------------------
    def stats(self) -> dict:
        """Figures for metrics.json: planar fraction, mean P_2D and prior, AOF updates per regime."""
        if self.geom is None or len(self.prior) == 0:
            return {"anchors": 0, "aof_updates": self.updates}
        p = self.p2d()
        return {"anchors": int(len(p)), "planar_fraction": float((p > self.cfg.planar_threshold).float().mean()),
                "p2d_mean": float(p.mean()), "prior_mean": float(self.prior.mean()), "aof_updates": self.updates,
                "aof_evolution": int(self.regimes[EVOLUTION]), "aof_suppression": int(self.regimes[SUPPRESSION]),
                "aof_consolidation": int(self.regimes[2]), "aof_last_loss": self.last_loss}

    def state(self) -> dict:
        """Net, optimizer, cached geometry and counters (a resumed run continues bit for bit)."""
        return {"net": self.net.state_dict(), "opt": self.opt.state_dict(),
                "geom": None if self.geom is None else dataclasses.asdict(self.geom), "prior": self.prior,
                "versions": self._versions, "refreshed_at": self._refreshed_at, "updates": self.updates,
                "regimes": self.regimes.copy(), "last_loss": self.last_loss}

    def load_state(self, st: dict) -> None:
        """Restore ``state()``."""
        self.net.load_state_dict(st["net"])
        self.opt.load_state_dict(st["opt"])
        fields = {f.name for f in dataclasses.fields(AnchorGeometry)}
        if st["geom"] is not None and set(st["geom"]) == fields:
            self.geom = AnchorGeometry(**st["geom"])
            self._versions = tuple(st["versions"])
        else:  # none yet, or written by a version with other fields: the next refresh() recomputes it
            self.geom, self._versions = None, (-1, -1, -1)
        self.prior = st["prior"]
        self._align = quat_z_to(self.geom.normals) if self.geom is not None else None
        self._refreshed_at = st["refreshed_at"]
        self.updates, self.regimes, self.last_loss = st["updates"], np.asarray(st["regimes"]), st["last_loss"]
        self._p2d = None
