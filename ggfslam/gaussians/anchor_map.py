"""The structured Gaussian map (Scaffold-GS): anchors on a voxel grid, each decoding k neural Gaussians.

Per anchor v (all world frame, metres):
- ``anchors`` [A, 3]: voxel-centre position (a buffer: anchors do not move by gradient, only by pose
  corrections of the keyframe that created them, see ``transform_anchors``);
- ``features`` [A, F] (F = 32): the learned appearance/geometry code ``f_v``;
- ``log_scale`` [A, 3]: ``l_v = exp(log_scale)``, scales the offsets and the children's sizes;
- ``offsets`` [A, k, 3]: child positions ``mu = x_v + O_v * l_v``;
- ``base_color`` [A, k, 3]: logit of a per-child colour the colour MLP adds to. Scaffold-GS decodes colour
  from the feature alone; starting each child at the colour its anchor was observed with lets a CPU budget of a
  few hundred iterations per keyframe reach the same images; a colour of each child's own adds texture detail
  the 32 feature numbers do not carry for ten children (+0.4 dB after 800 steps on two 640x480 keyframes of the
  procedural room). The MLP still carries the SH view dependence.
- ``source_kf`` [A]: keyframe whose depth created the anchor (-1: grown), used to move anchors with it.

What the keyframes saw of each anchor (read by the Geometric-Gaussian Field, ggf/):
- ``surface`` [A, 3] and ``surface_n`` [A]: mean of the back-projected depth points that fell in the voxel
  (a point on the surface, unlike the voxel centre) and how many points it averages (``add_surface_points``);
- ``obs`` [A]: keyframes that saw the anchor, i.e. its surface point projects into the image in front of the
  keyframe's depth surface (the track count T, ``add_observation``);
- ``obs_color`` / ``obs_color_sq`` [A, 3]: sums over those keyframes of the colour seen there (a small
  neighbourhood's mean) and of its square (the colour variance across observations).

Children are decoded by ``ChildDecoder`` (decoders.py). All per-anchor tensors are resized together by
``select`` / ``append`` so an optimizer's state can follow them (see ``optim.py``).
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import torch
from numba import njit, prange
from torch import nn

from ggfslam.gaussians.child_head import SurfelSpec
from ggfslam.gaussians.decoders import ChildDecoder, DecodedGaussians

PER_ANCHOR_PARAMS = ("features", "log_scale", "offsets", "base_color")
# buffers resized with the anchors: name -> (shape after the anchor axis, dtype)
PER_ANCHOR_BUFFERS = {"anchors": ((3,), torch.float32), "source_kf": ((), torch.int64),
                      "surface": ((3,), torch.float32), "surface_n": ((), torch.float32),
                      "obs": ((), torch.float32), "obs_color": ((3,), torch.float32),
                      "obs_color_sq": ((3,), torch.float32)}


def voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """Integer voxel key [N] int64 of points [N, 3] (21 bits per axis, offset so negatives fit)."""
    ijk = np.floor(points / voxel).astype(np.int64) + (1 << 20)
    if ijk.size and (ijk.min() < 0 or ijk.max() >= (1 << 21)):
        raise ValueError(f"points beyond the voxel grid range (|x| > {voxel * (1 << 20):.0f} m)")
    return (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]


def spheres_in_view(centres: torch.Tensor, reach: torch.Tensor, T_cw: torch.Tensor, intr, near: float = 0.05,
                    margin: float = 0.02) -> torch.Tensor:
    """[A] bool: the spheres (centres [A, 3] world, radii reach [A]) that meet the view frustum of a camera at
    world-to-camera T_cw [4, 4] (image widened by ``margin`` of its size), or straddle the near plane while ahead of
    the camera. Plain torch in the inputs' dtype: the reference of the compiled ``AnchorMap.visible_anchors``."""
    pc = centres @ T_cw[:3, :3].T + T_cw[:3, 3]  # [A, 3] camera frame
    z = pc[:, 2]
    ahead = z - reach  # the sphere's nearest depth
    zs = ahead.clamp_min(1e-6)
    # a sphere entirely in front projects within f r / (z - r) of its centre's projection
    u = intr.fx * pc[:, 0] / z.clamp_min(1e-6) + intr.cx
    v = intr.fy * pc[:, 1] / z.clamp_min(1e-6) + intr.cy
    ru, rv = intr.fx * reach / zs + margin * intr.width, intr.fy * reach / zs + margin * intr.height
    inside = (u > -ru) & (u < intr.width + ru) & (v > -rv) & (v < intr.height + rv)
    # a sphere that reaches behind the near plane but has part in front: keep it if it is ahead of the camera
    straddle = (ahead <= near) & (z + reach > near) & (pc[:, :2].norm(dim=1) < z.abs() + reach + 1.0)
    return (z + reach > near) & (inside & (ahead > near) | straddle)


@njit(cache=True, nogil=True, parallel=True)
def _spheres_in_view(centres, reach, R, t, fx, fy, cx, cy, width, height, near, margin, out):
    """``spheres_in_view`` per sphere in float64 (R [3, 3], t [3] world-to-camera) into out [A] bool."""
    for i in prange(centres.shape[0]):
        px, py, pz = np.float64(centres[i, 0]), np.float64(centres[i, 1]), np.float64(centres[i, 2])
        x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
        y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
        z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
        r = np.float64(reach[i])
        ahead = z - r
        zs = max(ahead, 1e-6)
        zc = max(z, 1e-6)
        u = fx * x / zc + cx
        v = fy * y / zc + cy
        ru = fx * r / zs + margin * width
        rv = fy * r / zs + margin * height
        inside = u > -ru and u < width + ru and v > -rv and v < height + rv
        straddle = ahead <= near and z + r > near and np.sqrt(x * x + y * y) < abs(z) + r + 1.0
        out[i] = z + r > near and ((inside and ahead > near) or straddle)


class AnchorMap(nn.Module):
    """Anchors and the MLP decoders of their children (see the module docstring for the fields)."""

    def __init__(self, voxel_size: float, n_offsets: int = 10, feature_dim: int = 32, hidden: int = 32,
                 view_dependent: bool = False, seed: int = 0, sh_degree: int = 1, init_opacity: float = 0.1):
        super().__init__()
        if not voxel_size > 0:
            raise ValueError(f"voxel_size must be > 0, got {voxel_size}")
        self.voxel_size = float(voxel_size)
        self.k = int(n_offsets)
        self.feature_dim = int(feature_dim)
        self.gen = torch.Generator().manual_seed(seed)
        for name, (shape, dtype) in PER_ANCHOR_BUFFERS.items():
            self.register_buffer(name, torch.zeros((0,) + shape, dtype=dtype))
        # layout_version changes when anchors are added or removed (per-anchor caches must be rebuilt),
        # geometry_version when anchors move, observed_version when a keyframe observed them
        self.layout_version = self.geometry_version = self.observed_version = 0
        self.features = nn.Parameter(torch.zeros(0, feature_dim))  # [A, F]
        self.log_scale = nn.Parameter(torch.zeros(0, 3))  # [A, 3]
        self.offsets = nn.Parameter(torch.zeros(0, self.k, 3))  # [A, k, 3]
        self.base_color = nn.Parameter(torch.zeros(0, self.k, 3))  # [A, k, 3] logits
        self.decoder = ChildDecoder(feature_dim, self.k, hidden, view_dependent, sh_degree, init_opacity)
        self._keys = np.zeros(0, dtype=np.int64)  # sorted voxel keys of the anchors
        self._key_anchor = np.zeros(0, dtype=np.int64)  # anchor index of each sorted key

    # --- size and occupancy ------------------------------------------------------------------------
    @property
    def n_anchors(self) -> int:
        """Anchors in the map."""
        return int(self.anchors.shape[0])

    def _rebuild_keys(self) -> None:
        keys = voxel_keys(self.anchors.numpy().astype(np.float64), self.voxel_size)
        self._key_anchor = np.argsort(keys, kind="stable")
        self._keys = keys[self._key_anchor]

    def _anchor_of_keys(self, keys: np.ndarray) -> np.ndarray:
        """Index [N] of the anchor holding each voxel key [N] (-1: no anchor there)."""
        out = np.full(len(keys), -1, np.int64)
        if len(keys) == 0 or len(self._keys) == 0:
            return out
        pos = np.searchsorted(self._keys, keys).clip(max=len(self._keys) - 1)
        hit = self._keys[pos] == keys
        out[hit] = self._key_anchor[pos[hit]]
        return out

    def anchor_of_points(self, points: np.ndarray) -> np.ndarray:
        """Index [N] of the anchor whose voxel holds each point [N, 3] (-1: no anchor there)."""
        if len(points) == 0:
            return np.full(0, -1, np.int64)
        return self._anchor_of_keys(voxel_keys(np.asarray(points, np.float64), self.voxel_size))

    def free_voxels(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unique voxels of points [N, 3] not yet holding an anchor: (first point index [M], key [M])."""
        if len(points) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        keys = voxel_keys(points, self.voxel_size)
        uniq, first = np.unique(keys, return_index=True)
        fresh = self._anchor_of_keys(uniq) < 0
        return first[fresh], uniq[fresh]

    # --- adding, removing --------------------------------------------------------------------------
    def new_anchor_values(self, points: np.ndarray, colors: np.ndarray, source_kf: int = -1,
                          spacing: np.ndarray | None = None) -> tuple[dict[str, torch.Tensor], np.ndarray] | None:
        """Initial values of anchors at the voxel centres of points [N, 3] whose voxel is free.

        ``colors`` [N, 3] in [0, 1] start ``base_color``; ``spacing`` [N] (optional) the local point spacing
        (default: the voxel size) starts ``l_v``. Returns (values, index [M] of the point that made each
        anchor), or None when every voxel is taken.
        """
        first, keys = self.free_voxels(np.asarray(points, dtype=np.float64))
        if len(first) == 0:
            return None
        v = self.voxel_size
        centres = (np.floor(points[first] / v) + 0.5) * v  # [M, 3]
        m = len(first)
        col = torch.from_numpy(np.clip(np.asarray(colors, np.float32)[first], 0.02, 0.98))
        size = np.full(m, v, np.float32) if spacing is None else np.maximum(np.asarray(spacing, np.float32)[first], 0.25 * v)
        # children spread over the voxel from the start: zero offsets (Scaffold-GS) leave all k children on
        # the anchor, and it takes many iterations to pull them apart
        offsets = (torch.rand(m, self.k, 3, generator=self.gen) - 0.5)
        return {
            "anchors": torch.from_numpy(centres.astype(np.float32)),
            "source_kf": torch.full((m,), int(source_kf), dtype=torch.int64),
            "features": torch.zeros(m, self.feature_dim),
            "log_scale": torch.from_numpy(np.log(size))[:, None].repeat(1, 3),
            "offsets": offsets,
            "base_color": torch.logit(col)[:, None, :].repeat(1, self.k, 1),
        }, first

    def append(self, values: dict[str, torch.Tensor]) -> int:
        """Append anchors (a dict from ``new_anchor_values``); returns how many were added."""
        n = int(values["anchors"].shape[0])
        with torch.no_grad():
            for name, (shape, dtype) in PER_ANCHOR_BUFFERS.items():
                default = values["anchors"] if name == "surface" else torch.zeros((n,) + shape, dtype=dtype)
                setattr(self, name, torch.cat([getattr(self, name), values.get(name, default).to(dtype)]))
            for name in PER_ANCHOR_PARAMS:
                old = getattr(self, name)
                setattr(self, name, nn.Parameter(torch.cat([old.detach(), values[name].to(old.dtype)])))
        self._rebuild_keys()
        self.layout_version += 1
        return n

    def select(self, keep: torch.Tensor) -> None:
        """Keep only the anchors where keep [A] (bool) is True."""
        with torch.no_grad():
            for name in PER_ANCHOR_BUFFERS:
                setattr(self, name, getattr(self, name)[keep])
            for name in PER_ANCHOR_PARAMS:
                setattr(self, name, nn.Parameter(getattr(self, name).detach()[keep]))
        self._rebuild_keys()
        self.layout_version += 1

    def transform_anchors(self, mask: torch.Tensor, T: np.ndarray) -> None:
        """Move anchors [mask] rigidly by T [4, 4] (world to world), rotating their offsets with them."""
        R = torch.from_numpy(T[:3, :3].astype(np.float32))
        t = torch.from_numpy(T[:3, 3].astype(np.float32))
        with torch.no_grad():
            self.anchors[mask] = self.anchors[mask] @ R.T + t
            self.surface[mask] = self.surface[mask] @ R.T + t
            self.offsets[mask] = self.offsets[mask] @ R.T
        self._rebuild_keys()
        self.geometry_version += 1

    @torch.no_grad()
    def add_surface_points(self, points: np.ndarray) -> int:
        """Average depth points [N, 3] (world) into the surface point of the anchor whose voxel holds each;
        returns how many anchors received points."""
        a = self.anchor_of_points(points)
        hit = a >= 0
        if not hit.any():
            return 0
        a = a[hit]
        n = self.n_anchors
        cnt = np.bincount(a, minlength=n).astype(np.float64)  # [A]
        seen = np.nonzero(cnt)[0]
        psum = np.stack([np.bincount(a, points[hit, j], n) for j in range(3)], 1)[seen]  # [S, 3]
        idx, c = torch.from_numpy(seen), torch.from_numpy(cnt[seen])
        n_old = self.surface_n[idx].double()
        surf = (self.surface[idx].double() * n_old[:, None] + torch.from_numpy(psum)) / (n_old + c)[:, None]
        self.surface[idx] = surf.float()
        self.surface_n[idx] += c.float()
        self.observed_version += 1
        return len(seen)

    @torch.no_grad()
    def add_observation(self, index: np.ndarray, colors: np.ndarray) -> None:
        """One keyframe saw anchors ``index`` [S] with colours [S, 3]: count it and add to the colour sums."""
        idx = torch.from_numpy(np.asarray(index, np.int64))
        col = torch.from_numpy(np.asarray(colors, np.float32))
        self.obs[idx] += 1
        self.obs_color[idx] += col
        self.obs_color_sq[idx] += col ** 2
        self.observed_version += 1

    def color_variance(self) -> torch.Tensor:
        """V_color [A]: variance across observations of the mean colour in each voxel (mean over RGB)."""
        t = self.obs.clamp_min(1)[:, None]
        m = self.obs_color / t
        return (self.obs_color_sq / t - m * m).clamp_min(0).mean(dim=1)

    # --- decoding ----------------------------------------------------------------------------------
    @torch.no_grad()
    def reach(self, slack: float = 0.0) -> torch.Tensor:
        """Radius [A] (m) around each anchor that holds its children to 3 sigma: the farthest offset plus three
        times the largest child scale (children's scales are at most ``l_v``), plus ``slack`` times ``l_v``."""
        if self.n_anchors == 0:
            return torch.zeros(0)
        L = torch.exp(self.log_scale)  # [A, 3]
        return (self.offsets * L[:, None, :]).norm(dim=2).amax(dim=1) + (3.0 + slack) * L.amax(dim=1)

    def visible_anchors(self, T_cw: np.ndarray, intr, near: float = 0.05, margin: float = 0.02,
                        reach: torch.Tensor | None = None) -> torch.Tensor:
        """Anchors [A] bool whose children can reach the image: the sphere of ``reach()`` around the anchor meets
        the view frustum (widened by ``margin`` of the image size). Anchors culled by their centre alone (as
        Scaffold-GS does) left children that project into the image untrained and unseen in training, but drawn
        by any renderer of the whole map: floaters in the baked file. Compiled (``spheres_in_view``)."""
        if self.n_anchors == 0:
            return torch.zeros(0, dtype=torch.bool)
        r = self.reach() if reach is None or len(reach) != self.n_anchors else reach  # [A]
        out = np.empty(self.n_anchors, np.bool_)
        T = np.asarray(T_cw, np.float64)
        _spheres_in_view(self.anchors.contiguous().numpy(), r.detach().contiguous().numpy(),
                         np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]), float(intr.fx),
                         float(intr.fy), float(intr.cx), float(intr.cy), float(intr.width), float(intr.height),
                         float(near), float(margin), out)
        return torch.from_numpy(out)

    def decode(self, cam_center: np.ndarray | torch.Tensor, mask: torch.Tensor | None = None,
               surfels: Callable[[torch.Tensor], SurfelSpec | None] | None = None,
               reference: bool = False) -> DecodedGaussians:
        """Children of the anchors in ``mask`` [A] (all when None) seen from ``cam_center`` (world): one point [3],
        or one viewpoint per anchor [A, 3] (the bake). ``surfels(index [M])`` gives AMR's inputs for the decoded
        anchors (the Geometric-Gaussian Field); ``reference`` decodes in plain torch without AMR (tests)."""
        idx = torch.arange(self.n_anchors) if mask is None else torch.nonzero(mask)[:, 0]  # [M]
        c = torch.as_tensor(np.asarray(cam_center, np.float32)) if not isinstance(cam_center, torch.Tensor) else cam_center
        c = c.float()
        if c.dim() == 2:
            c = c[idx]
        if reference:
            return self.decoder.reference(self.anchors[idx], *(getattr(self, n)[idx] for n in PER_ANCHOR_PARAMS), c,
                                          idx)
        # the map's whole arrays: the decoder reads rows idx itself (and writes their gradients in place)
        return self.decoder(self.anchors, *(getattr(self, n) for n in PER_ANCHOR_PARAMS), c, idx,
                            surfels=surfels(idx) if surfels is not None else None)

    def decode_dense(self, cam_center: torch.Tensor, index: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Every child (none dropped) of anchors ``index`` [M] seen from ``cam_center`` [M, 3] (``ChildDecoder.dense``)."""
        return self.decoder.dense(self.anchors[index], self.features[index], self.log_scale[index],
                                  self.offsets[index], self.base_color[index], cam_center)

    def extra_state(self) -> dict:
        """Sizes and settings needed to rebuild an empty map before ``load_state_dict``."""
        return {"voxel_size": self.voxel_size, "n_offsets": self.k, "feature_dim": self.feature_dim,
                "hidden": self.decoder.hidden, "view_dependent": self.decoder.view_dependent,
                "sh_degree": self.decoder.sh_degree,
                "n_anchors": self.n_anchors, "layout_version": self.layout_version,
                "geometry_version": self.geometry_version, "observed_version": self.observed_version}

    @classmethod
    def from_state(cls, extra: dict, state: dict) -> AnchorMap:
        """Rebuild a map saved as (``extra_state()``, ``state_dict()``)."""
        m = cls(extra["voxel_size"], extra["n_offsets"], extra["feature_dim"], extra["hidden"],
                extra["view_dependent"], sh_degree=extra.get("sh_degree", 0))
        n = extra["n_anchors"]
        for name, (shape, dtype) in PER_ANCHOR_BUFFERS.items():
            setattr(m, name, torch.zeros((n,) + shape, dtype=dtype))
        for name in PER_ANCHOR_PARAMS:
            p = getattr(m, name)
            setattr(m, name, nn.Parameter(torch.zeros((n,) + tuple(p.shape[1:]))))
        if state["base_color"].dim() == 2:  # maps saved before children had colours of their own
            state = {**state, "base_color": state["base_color"][:, None, :].expand(-1, m.k, -1).contiguous()}
        m.load_state_dict(state)
        m._rebuild_keys()
        m.layout_version = extra.get("layout_version", 0)
        m.geometry_version = extra.get("geometry_version", 0)
        m.observed_version = extra.get("observed_version", 0)
        return m

