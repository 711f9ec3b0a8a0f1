"""The mapping loop: trains the anchor map on keyframes whose poses always come from the backend.

- ``add_keyframe`` stores the keyframe's images (training resolution, on disk + cache), seeds anchors from
  its back-projected depth and the landmarks it sees, and gives it an exposure (affine brightness).
- ``train(n, focus)`` runs n Adam steps, each on one keyframe: the new one every other step, otherwise a
  keyframe of a window sampled from the older ones (``mapping.window``); ``focus=None`` samples all.
- Before every step the keyframe poses are read from ``pose_source`` (the SLAM map); when bundle
  adjustment or a loop closure moved a keyframe by more than ``pose_update_threshold``, the anchors it
  created move rigidly with it, so corrections move the map instead of leaving a ghost copy.
- Loss (METHOD.md §5): ``0.8 L1 + 0.2 (1 - SSIM) + 0.5 L_depth + 0.05 L_normal`` plus Scaffold-GS's volume
  regulariser, plus ``0.1 L_morph`` with the Geometric-Gaussian Field (and, when ``lambda_depth_spread`` > 0, the
  depth spread along each ray, losses.depth_spread_loss); growing and pruning every ``densify_every`` steps.
- With ``ggf.enabled`` (ggf/), every keyframe's depth and view are recorded per anchor (``_observe``), AMR
  turns the children of planar anchors into surfels (training, rendering and export alike), AOF trains the
  field's residual net after the Gaussians' step, and ``render`` carries P_2D as the planar-weight channel
  (``RenderOutput.extras[..., 0]``).
- A ``view_sink`` (GCGR's ``GCGRSource``) may take the renders of training steps: on the steps it asks for, the
  render also carries the (detached) planar-weight channel and is handed over after the step, so GCGR reads the
  map at a keyframe without rendering it again.
Every public method takes ``self.lock``, so a worker thread can train while another thread renders or saves.
"""
from __future__ import annotations

import dataclasses
import threading
import time
from pathlib import Path
from typing import Callable, Protocol

import cv2
import numpy as np
import torch
from torch import nn

from ggfslam.config import GGFConfig, MappingConfig
from ggfslam.gaussians.anchor_map import AnchorMap
from ggfslam.gaussians.bake import fit_sh1, observing_keyframes
from ggfslam.gaussians.decoders import DecodedGaussians
from ggfslam.gaussians.density import DensityControl
from ggfslam.gaussians.optim import make_adam, replace_param
from ggfslam.geometry.depth import backproject, transform_points
from ggfslam.geometry.se3 import invert, rotation_angle
from ggfslam.ggf import GeometricGaussianField, planarity_colors
from ggfslam.mapping.keyframe_store import KeyframeStore, scaled_intrinsics
from ggfslam.mapping.exposure_kernels import covered_moments
from ggfslam.mapping.loss_kernels import normal_loss_from_depth
from ggfslam.mapping.losses import depth_loss, depth_spread_loss, opacity_entropy, photometric_loss, scale_volume
from ggfslam.mapping.sensor_kernels import sensor_model
from ggfslam.render.api import rasterize
from ggfslam.render.plane_depth import PLANE_CHANNELS, pixel_rays, plane_channels, plane_depth
from ggfslam.render.projection import quat_to_rotmat
from ggfslam.render.types import Intrinsics, RenderOutput, RenderSettings

PoseSource = Callable[[], dict[int, np.ndarray]]  # keyframe id -> T_wc [4, 4]
GEOMETRY_WIDTH = 400
"""Widest image anchors are seeded from (see ``Mapper.geo_level``)."""
REFERENCE_EXPOSURE = -1
"""``exposure_kf`` of views without a keyframe of their own: the reference exposure (``reference_exposure``)."""


class ViewSink(Protocol):
    """Takes training renders of keyframes (see the module docstring)."""

    def wants(self, kf_id: int, iteration: int) -> bool:
        """Whether the step ``iteration`` on keyframe ``kf_id`` should hand its render over."""

    def offer(self, kf_id: int, T_wc: np.ndarray, iteration: int, out: RenderOutput) -> None:
        """The render ``out`` of keyframe ``kf_id`` at T_wc [4, 4], made before step ``iteration``."""


def _frame_steps(per_frame: float, prev: int, start: int, end: int) -> int:
    """``per_frame`` steps for each of the frames (start, end] after the stored keyframe at frame ``prev``, rounded
    cumulatively from prev: frames paid in parts get what they would together."""
    return int(round(per_frame * (end - prev))) - int(round(per_frame * (start - prev)))


class Mapper:
    """Structured Gaussian map + its optimizer, trained from stored keyframes (see the module docstring)."""

    def __init__(self, cfg: MappingConfig, camera, settings: RenderSettings, pose_source: PoseSource,
                 store_dir: str | Path, seed: int = 0, ggf: GGFConfig | None = None):
        self.cfg, self.settings, self.pose_source = cfg, settings, pose_source
        self.ggf_cfg = ggf if ggf is not None else GGFConfig(enabled=False)
        self.ggf = GeometricGaussianField(self.ggf_cfg, cfg.voxel_size, seed) if self.ggf_cfg.enabled else None
        self.intr = scaled_intrinsics(camera, cfg.train_width)
        self.store = KeyframeStore(store_dir, self.intr, cfg.keyframe_cache)
        # coarse-to-fine only where half the training size still has detail to learn from
        self.coarse_levels = cfg.coarse_fraction > 0 and self.intr.width >= 2 * cfg.coarse_min_width
        # the level whose whole-image steps measure each keyframe's error for ``_by_error`` (one size, so errors
        # compare): the training size, or half of it where the training-size steps are crops
        self.error_level = 1 if self.coarse_levels and cfg.crop < 1.0 else 0
        # anchors are seeded from, and the field observes, images at most GEOMETRY_WIDTH wide: sensor depth noise
        # at 640 px would seed anchors in every voxel it scatters into (1.7x the anchors of the 320 px depth,
        # whose 2x2 means are smoother), and the field's filters were tuned at that scale
        self.geo_level = 0
        while (self.intr.width >> (self.geo_level + 1)) >= GEOMETRY_WIDTH // 2 and \
                (self.intr.width >> self.geo_level) > GEOMETRY_WIDTH:
            self.geo_level += 1
        self.map = AnchorMap(cfg.voxel_size, cfg.n_offsets, cfg.feature_dim, cfg.hidden, cfg.view_dependent, seed,
                             cfg.sh_degree, cfg.init_opacity)
        self.density = DensityControl(self.map, cfg.grow_grad_threshold, cfg.prune_min_opacity,
                                      cfg.density_min_visits, cfg.max_anchors)
        self.exposure = nn.Parameter(torch.zeros(0, 6))  # [E, 6]: log gain (3), offset (3) per keyframe
        self.exposure_row: dict[int, int] = {}
        self.vignette = nn.Parameter(torch.zeros(2))  # [2] v1, v2 of the radial gain 1 + v1 r^2 + v2 r^4
        self.opt = self._make_optimizer()
        self.rng = np.random.default_rng(seed)
        self.anchor_poses: dict[int, np.ndarray] = {}  # pose of each keyframe when its anchors were placed
        self._poses: dict[int, np.ndarray] = {}  # the backend's keyframe poses as last read
        self.iteration = 0
        self.train_seconds = 0.0
        self.grown = self.pruned = self.merged = 0
        self.last_losses: dict[str, float] = {}
        self.kf_loss: dict[int, float] = {}  # each keyframe's photometric loss when it was last trained
        self.rest_paid_until = -1  # the last frame at rest (no keyframe made) whose steps ``rest_steps`` handed out
        self.view_sink: ViewSink | None = None  # not part of the map's state (checkpoints)
        self._reach_cache: tuple | None = None
        self._r2_cache: dict[Intrinsics, torch.Tensor] = {}  # squared ray radius [H, W] of the levels (vignetting)
        self.lock = threading.RLock()

    def _make_optimizer(self) -> torch.optim.Adam:
        c, m = self.cfg, self.map
        return make_adam([
            {"params": [m.features], "lr": c.lr_features, "name": "features"},
            {"params": [m.log_scale], "lr": c.lr_scale, "name": "log_scale"},
            {"params": [m.offsets], "lr": c.lr_offsets, "name": "offsets"},
            {"params": [m.base_color], "lr": c.lr_color, "name": "base_color"},
            {"params": list(m.decoder.parameters()), "lr": c.lr_mlp, "name": "mlp"},
            {"params": [self.exposure], "lr": c.lr_exposure if c.exposure and not c.exposure_closed_form else 0.0,
             "name": "exposure"},
            {"params": [self.vignette], "lr": c.lr_vignetting if c.vignetting else 0.0, "name": "vignette"},
        ])

    # --- keyframes -----------------------------------------------------------------------------------
    def add_keyframe(self, kf_id: int, frame_index: int, rgb: np.ndarray, depth: np.ndarray,
                     T_wc: np.ndarray | None = None, landmarks: np.ndarray | None = None) -> int:
        """Store a keyframe and seed anchors from its depth and the landmarks [L, 3] it sees; returns new anchors."""
        self.store.add(kf_id, frame_index, rgb, depth)
        return self.seed_keyframe(kf_id, T_wc, landmarks)

    def seed_keyframe(self, kf_id: int, T_wc: np.ndarray | None = None, landmarks: np.ndarray | None = None) -> int:
        """Anchors from a stored keyframe's depth (and landmarks [L, 3]) at its current pose; returns new anchors.
        A keyframe is seeded once: again is a no-op (a checkpoint taken while the worker seeds may list it as
        still queued)."""
        item = self.store.get(kf_id, self.geo_level)
        with self.lock:
            if kf_id in self.anchor_poses:
                return 0
            if T_wc is None:
                T_wc = self.pose_source()[kf_id]
            pts, cols = self._seed_points(item.rgb, item.depth, T_wc, landmarks)
            first_new = self.map.n_anchors
            added = self._append_anchors(pts, cols, kf_id)
            if self.ggf is not None:  # only the field reads the observations
                self._observe(item.rgb, item.depth, T_wc)
                # the new anchors were also in view of the latest keyframes: count those views too, so an
                # anchor's T does not depend on whether it was created early or late in the sequence
                new = np.arange(first_new, self.map.n_anchors)
                for k in sorted(self.anchor_poses)[-self.cfg.window:] if added else []:
                    prev = self.store.get(k, self.geo_level)
                    self._observe(prev.rgb, prev.depth, self._pose(k), new)
            self.anchor_poses[kf_id] = T_wc.copy()
            if kf_id not in self.exposure_row:
                self._add_exposure(kf_id)
            return added

    def _seed_points(self, rgb: np.ndarray, depth: np.ndarray, T_wc: np.ndarray, landmarks: np.ndarray | None):
        i, s = self.store.level_intrinsics(self.geo_level), self.cfg.depth_stride
        P = backproject(depth[::s, ::s], i.fx / s, i.fy / s, (i.cx + 0.5) / s - 0.5, (i.cy + 0.5) / s - 0.5)
        valid = depth[::s, ::s] > 0
        pts = transform_points(T_wc, P[valid])  # [M, 3] world
        cols = rgb[::s, ::s][valid]  # [M, 3]
        if landmarks is not None and len(landmarks):
            pc = transform_points(invert(T_wc), landmarks)
            z = pc[:, 2]
            ok = z > 0.05
            u = np.rint(i.fx * pc[ok, 0] / z[ok] + i.cx).astype(np.int64)
            v = np.rint(i.fy * pc[ok, 1] / z[ok] + i.cy).astype(np.int64)
            inside = (u >= 0) & (u < i.width) & (v >= 0) & (v < i.height)
            pts = np.concatenate([pts, landmarks[ok][inside]])
            cols = np.concatenate([cols, rgb[v[inside], u[inside]]])
        return pts, cols

    def _observe(self, rgb: np.ndarray, depth: np.ndarray, T_wc: np.ndarray, anchors: np.ndarray | None = None) -> None:
        """What a keyframe tells the anchors (AnchorMap's module docstring): its depth pixels (training
        resolution) sharpen the voxels' surface points; the anchors it sees count one observation and record
        the colour there. With ``anchors`` [M] only those are looked at and the surface points stay."""
        i = self.store.level_intrinsics(self.geo_level)
        valid = depth > 0
        # edge-preserving smoothing: sensor noise (~1-2 cm at 3 m) would otherwise spread a wall's points over
        # several voxel layers and make it look curved
        smooth = cv2.bilateralFilter(depth.astype(np.float32), 7, 0.05, 2.0)
        smooth = np.where(valid & (np.abs(smooth - depth) < 0.1), smooth, depth)
        if anchors is None:
            self.map.add_surface_points(transform_points(T_wc, backproject(smooth, i.fx, i.fy, i.cx, i.cy)[valid]))
            anchors = np.arange(self.map.n_anchors)
        pc = transform_points(invert(T_wc), self.map.surface.numpy()[anchors].astype(np.float64))  # [M, 3] camera
        z = pc[:, 2]
        front = np.nonzero(z > self.settings.near_plane)[0]
        u = np.rint(i.fx * pc[front, 0] / z[front] + i.cx).astype(np.int64)
        v = np.rint(i.fy * pc[front, 1] / z[front] + i.cy).astype(np.int64)
        inside = (u >= 0) & (u < i.width) & (v >= 0) & (v < i.height)
        front, u, v = front[inside], u[inside], v[inside]
        d = smooth[v, u]
        # seen: on the keyframe's depth surface, not behind it (occluded) nor in front of it (free space)
        seen = (d > 0) & (np.abs(z[front] - d) < np.maximum(2 * self.cfg.voxel_size, 0.03 * d))
        blurred = cv2.blur(rgb, (3, 3))
        self.map.add_observation(anchors[front[seen]], blurred[v[seen], u[seen]])

    def _append_anchors(self, pts: np.ndarray, cols: np.ndarray, source_kf: int) -> int:
        n_free = self.cfg.max_anchors - self.map.n_anchors
        res = self.map.new_anchor_values(pts, cols, source_kf) if n_free > 0 else None
        if res is None:
            return 0
        vals, _ = res
        vals = {k: v[:n_free] for k, v in vals.items()}
        olds = {name: getattr(self.map, name) for name in ("features", "log_scale", "offsets", "base_color")}
        n = self.map.append(vals)
        for name, old in olds.items():
            replace_param(self.opt, old, getattr(self.map, name), None, n)
        self.density.on_append(n)
        return n

    def _add_exposure(self, kf_id: int) -> None:
        old = self.exposure
        self.exposure = nn.Parameter(torch.cat([old.detach(), torch.zeros(1, 6)]))
        replace_param(self.opt, old, self.exposure, None, 1)
        self.exposure_row[kf_id] = len(self.exposure_row)

    # --- pose corrections ----------------------------------------------------------------------------
    def _pose(self, kf_id: int) -> np.ndarray | None:
        """Keyframe ``kf_id``'s camera-to-world pose [4, 4]: the backend's last, else the one its anchors were seeded
        at; None for a keyframe the mapper has not seen."""
        return self._poses.get(kf_id, self.anchor_poses.get(kf_id))

    def sync_poses(self, poses: dict[int, np.ndarray] | None = None) -> int:
        """Move the anchors of keyframes the backend moved, then keep one anchor per voxel where moved anchors
        landed on others (``DensityControl.merge_collisions``); returns how many keyframes moved."""
        poses = self.pose_source() if poses is None else poses
        moved = 0
        with self.lock:
            thr = self.cfg.pose_update_threshold
            src = self.map.source_kf
            for kf_id, T_old in self.anchor_poses.items():
                T_new = poses.get(kf_id)
                if T_new is None:
                    continue
                D = T_new @ invert(T_old)  # world-to-world motion of the keyframe
                if np.linalg.norm(D[:3, 3]) < thr and rotation_angle(D[:3, :3]) < 2 * thr:
                    continue
                mask = src == kf_id
                if bool(mask.any()):
                    self.map.transform_anchors(mask, D)
                self.anchor_poses[kf_id] = T_new.copy()
                moved += 1
            if moved:
                self.merged += self.density.merge_collisions(self.opt)
        return moved

    # --- training ------------------------------------------------------------------------------------
    def keyframe_budget(self, kf_id: int) -> int:
        """Steps a new keyframe gets: ``iterations_per_frame`` per frame since the stored keyframe before it (less
        those frames at rest that ``rest_steps`` already paid), at least ``iterations_per_keyframe``."""
        c = self.cfg
        frame = self.store.frame_index(kf_id)
        before = [f for f in map(self.store.frame_index, self.store.ids()) if f < frame]
        if not before:
            return max(c.iterations_per_keyframe, int(round(c.iterations_per_frame)))
        prev = max(before)
        paid = min(max(self.rest_paid_until, prev), frame)
        return max(c.iterations_per_keyframe, _frame_steps(c.iterations_per_frame, prev, paid, frame))

    def rest_steps(self, frame_index: int) -> int:
        """Steps owed to the frames up to ``frame_index`` that made no keyframe because the camera rested at a
        keyframe's view (``tracking.keyframe_still_translation``): ``iterations_per_frame`` for each frame since the
        last stored keyframe or the last frame already paid; marks them paid (``keyframe_budget`` leaves them out)."""
        stored = [self.store.frame_index(k) for k in self.store.ids()]
        if not stored:
            return 0
        prev = max(stored)
        paid = max(self.rest_paid_until, prev)
        if frame_index <= paid:
            return 0
        self.rest_paid_until = frame_index
        return _frame_steps(self.cfg.iterations_per_frame, prev, paid, frame_index)

    def train(self, n: int, focus: int | None = None, stop: threading.Event | None = None) -> None:
        """n optimization steps. With ``focus`` every other step is on that keyframe and the others alternate
        between its covisible keyframes (``window - 1`` of them, those whose anchors fill most of its view) and
        keyframes drawn by their current error; without, every step is drawn by error (``_by_error``).
        A set ``stop`` event ends the loop after the current step."""
        ids = sorted(self.anchor_poses)  # the seeded keyframes (a stored one may still wait in the queue)
        if not ids or n <= 0:
            return
        window = self._covisible(focus, self.cfg.window - 1) if focus is not None else []
        for it in range(n):
            if stop is not None and stop.is_set():
                return
            if focus is not None and (it % 2 == 0 or len(ids) == 1):
                kf = focus
            elif focus is not None and window and (it // 2) % 2 == 0:
                kf = window[(it // 4) % len(window)]
            else:
                kf = self._by_error(ids)
            self.step(kf, *self._step_view())

    def _covisible(self, kf_id: int, n: int) -> list[int]:
        """Up to n other keyframes whose anchors are most numerous in ``kf_id``'s view (most first)."""
        T = self._pose(kf_id)
        if n <= 0 or T is None:
            return []
        mask = self.map.visible_anchors(invert(T), self.intr, self.settings.near_plane, reach=self._reach())
        src = self.map.source_kf[mask]
        src = src[(src >= 0) & (src != kf_id)]
        if len(src) == 0:
            return []
        ids, counts = torch.unique(src, return_counts=True)
        order = torch.argsort(counts, descending=True, stable=True)[:n]
        return [int(k) for k in ids[order] if int(k) in self.anchor_poses]

    def _by_error(self, ids: list[int]) -> int:
        """A keyframe drawn with probability proportional to its last photometric loss (never-trained ones count
        as the worst): steps go where the map is furthest from the images, and keyframes whose region the shared
        decoders have since drifted away from come back."""
        worst = max(self.kf_loss.values(), default=1.0)
        w = np.array([self.kf_loss.get(k, worst) for k in ids], np.float64) + 1e-6
        return int(ids[self.rng.choice(len(ids), p=w / w.sum())])

    def _step_view(self) -> tuple[int, tuple[int, int, int, int] | None]:
        """(level, crop) of the next step: a share ``coarse_fraction`` of the steps see whole images at half the
        training size, the others the training size, on a random crop of ``crop`` of each side."""
        c = self.cfg
        if self.coarse_levels and self.rng.random() < c.coarse_fraction:
            return 1, None
        if c.crop >= 1.0:
            return 0, None
        i = self.intr
        w, h = max(32, int(round(c.crop * i.width))), max(32, int(round(c.crop * i.height)))
        w, h = min(w, i.width), min(h, i.height)
        return 0, (int(self.rng.integers(i.width - w + 1)), int(self.rng.integers(i.height - h + 1)), w, h)

    def _decode(self, cam_center: np.ndarray | torch.Tensor, mask: torch.Tensor | None = None) -> DecodedGaussians:
        """Children of the anchors in ``mask`` seen from ``cam_center`` ([3], or [A, 3] one per anchor), with AMR
        on those of planar anchors when the map has a Geometric-Gaussian Field."""
        if self.ggf is None:
            return self.map.decode(cam_center, mask)
        self._refresh_field()
        return self.map.decode(cam_center, mask, self.ggf.surfel_spec)

    def _decode_view(self, T_wc: np.ndarray, intr: Intrinsics, without_kf: int | None = None
                     ) -> tuple[DecodedGaussians, torch.Tensor]:
        """The children in view of a camera at T_wc [4, 4] (and the anchor mask [A] they come from)."""
        mask = self.map.visible_anchors(invert(T_wc), intr, self.settings.near_plane, reach=self._reach())
        if without_kf is not None:
            mask &= self.map.source_kf != without_kf
        return self._decode(T_wc[:3, 3], mask), mask

    def _reach(self) -> torch.Tensor:
        """``AnchorMap.reach`` recomputed every 10 steps (or when anchors change) with a slack of one anchor scale:
        Adam moves an offset by at most ~lr_offsets (0.01 scales) a step."""
        key = (self.iteration // 10, self.map.layout_version, self.map.geometry_version)
        if self._reach_cache is None or self._reach_cache[0] != key:
            self._reach_cache = (key, self.map.reach(slack=1.0))
        return self._reach_cache[1]

    def _refresh_field(self) -> None:
        """Bring the field's anchor geometry up to date with the map (cameras orient the normals)."""
        centres = {k: T[:3, 3] for k, T in self.anchor_poses.items()}
        self.ggf.refresh(self.map, centres, self.iteration)

    def _planar_channel(self, g: DecodedGaussians) -> torch.Tensor | None:
        """P_2D of each child's anchor [G, 1] (the renderer's planar-weight channel); None without the field."""
        return None if self.ggf is None else self.ggf.p2d()[g.anchor_index][:, None]

    def step(self, kf_id: int, level: int = 0, crop: tuple[int, int, int, int] | None = None,
             poses: dict[int, np.ndarray] | None = None) -> dict[str, float]:
        """One Adam step on keyframe ``kf_id`` at ``level`` (0 = training size, 1 = half), on the pixels
        ``crop`` = (x0, y0, width, height) of that level's image (None = all); returns the loss terms."""
        t0 = time.perf_counter()
        c = self.cfg
        with self.lock:
            # the backend's poses, re-read every 10 steps (a copy under its lock) or when a keyframe is new
            if poses is None and (self.iteration % 10 == 0 or kf_id not in self._poses):
                poses = self.pose_source()
            if poses is not None:
                self._poses = poses
                self.sync_poses(poses)
            T_wc = self._poses[kf_id]
            item = self.store.get(kf_id, level)
            full = self.store.level_intrinsics(level)
            intr, rgb, depth, normals = full, item.rgb, item.depth, item.normals
            if crop is not None:
                x0, y0, w, h = crop
                intr = full.crop(x0, y0, w, h)
                rgb, depth, normals = (a[y0:y0 + h, x0:x0 + w] for a in (rgb, depth, normals))
            g, mask = self._decode_view(T_wc, intr)
            if len(g) == 0:
                return {}
            # the planar-weight channel is for renders (and a view sink), not for the loss
            sink = self.view_sink if (self.view_sink is not None and level == 0 and crop is None
                                      and self.view_sink.wants(kf_id, self.iteration)) else None
            p2d = self._planar_channel(g) if sink is not None else None
            l_morph = self.ggf.morph(g) if self.ggf is not None and self.ggf_cfg.lambda_morph > 0 else torch.zeros(())
            spread = c.lambda_depth_spread > 0
            out, moments = self._rasterize(g, intr, T_wc, None if p2d is None else p2d.detach(), spread)
            if c.exposure_closed_form:
                with torch.no_grad():
                    self._fit_exposure(kf_id, out.color.detach(), out.alpha.detach(), rgb, intr)
            # _expose(_vignetted(.)) in one compiled pass (sensor_kernels.py)
            color = sensor_model(out.color, self._ray_r2(intr) if c.vignetting else None,
                                 self.vignette if c.vignetting else None, self._exposure_of(kf_id))
            gt_rgb = torch.from_numpy(np.ascontiguousarray(rgb))
            gt_depth = torch.from_numpy(np.ascontiguousarray(depth))
            l_photo = photometric_loss(color, gt_rgb, c.lambda_ssim)
            l_depth = depth_loss(out.depth, gt_depth)
            loss = l_photo + c.lambda_depth * l_depth
            l_normal = torch.zeros(())
            if c.lambda_normal > 0:
                l_normal = normal_loss_from_depth(out.depth, torch.from_numpy(np.ascontiguousarray(normals)), intr)
                loss = loss + c.lambda_normal * l_normal
            l_spread = torch.zeros(())
            if spread:
                l_spread = depth_spread_loss(moments[..., 0], moments[..., 1], out.alpha, gt_depth > 0)
                loss = loss + c.lambda_depth_spread * l_spread
            if c.lambda_scale > 0:
                vol = scale_volume(g.scales) / self.map.voxel_size ** 3
                loss = loss + c.lambda_scale * vol
            if c.lambda_opacity_entropy > 0:
                loss = loss + c.lambda_opacity_entropy * opacity_entropy(g.opacities)
            if self.ggf is not None and self.ggf_cfg.lambda_morph > 0:
                loss = loss + self.ggf_cfg.lambda_morph * l_morph
            loss.backward()
            # NDC scale of the 2D gradients: the level's whole image, so a crop's children are judged alike
            self.density.accumulate(g, out.visible, out.means2d_grad(), mask, (full.width, full.height))
            self.opt.step()
            self.opt.zero_grad(set_to_none=True)
            if sink is not None:
                sink.offer(kf_id, T_wc.copy(), self.iteration, out)
            self.iteration += 1
            if self.ggf is not None and self.ggf_cfg.aof and self.iteration % self.ggf_cfg.aof_every == 0:
                self.ggf.feedback(g)
            if c.densify_every and self.iteration >= c.densify_from and self.iteration % c.densify_every == 0:
                self.grown += self.density.grow(self.opt)
                self.pruned += self.density.prune(self.opt)
            self.train_seconds += time.perf_counter() - t0
            self.last_losses = {"loss": loss.item(), "photo": l_photo.item(), "depth": l_depth.item(),
                                "normal": l_normal.item(), "morph": float(l_morph.detach()),
                                "spread": l_spread.item()}
            if level == self.error_level and crop is None:  # comparable across keyframes: whole images, one size
                self.kf_loss[kf_id] = self.last_losses["photo"]
            return self.last_losses

    def _rasterize(self, g: DecodedGaussians, intr: Intrinsics, T_wc: np.ndarray, p2d: torch.Tensor | None,
                   depth_moments: bool = False) -> tuple[RenderOutput, torch.Tensor | None]:
        """Render children g at camera-to-world T_wc [4, 4], with the planar-weight channel p2d [G, 1] if given (in
        ``extras``); with ``ggf.plane_depth`` surfels' depth is where each pixel's ray meets their plane. With
        ``depth_moments`` also returns (sum w z, sum w z^2) [H, W, 2] of the children's view depths z, held constant
        (their gradient reaches the blending weights only; else None)."""
        T_cw = torch.from_numpy(invert(T_wc)).float()
        planes = self.ggf is not None and self.ggf_cfg.amr and self.ggf_cfg.plane_depth
        channels: list[torch.Tensor] = []  # each [G, c], rendered as extra channels in this order
        if planes or depth_moments:
            R = T_cw[:3, :3]
            mu_c = g.means @ R.T + T_cw[:3, 3]  # [G, 3]
        if planes:
            if self.ggf.orient:
                normals_w = self.ggf.geom.normals.index_select(0, g.anchor_index)  # [G, 3]
            else:  # a surfel's own flat axis
                normals_w = quat_to_rotmat(g.quats)[:, :, 2]
            normals_c = normals_w @ R.T  # [G, 3]
            channels.append(plane_channels(mu_c, normals_c, self.ggf.planar().index_select(0, g.anchor_index)))
        if depth_moments:
            z = mu_c[:, 2:3].detach()  # [G, 1]: held, so the moments move only with the blending weights
            channels.append(torch.cat([z, z * z], 1))
        if p2d is not None:
            channels.append(p2d)
        extras = torch.cat(channels, 1) if channels else None
        out = rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, intr, T_cw, extras=extras,
                        settings=self.settings)
        rest = out.extras
        if planes:
            out.depth = plane_depth(rest[..., :PLANE_CHANNELS], out.alpha, out.depth, intr,
                                    self.settings.depth_min_alpha)
            rest = rest[..., PLANE_CHANNELS:]
        moments = None
        if depth_moments:
            moments, rest = rest[..., :2], rest[..., 2:]
        out.extras = rest if p2d is not None else None
        return out, moments

    def vignetting_gain(self, intr: Intrinsics) -> torch.Tensor:
        """The camera's learned vignetting gain [H, W] at intrinsics intr (1 at the optical axis)."""
        r2 = self._ray_r2(intr)
        return 1.0 + self.vignette[0] * r2 + self.vignette[1] * r2 * r2

    def _ray_r2(self, intr: Intrinsics) -> torch.Tensor:
        """Squared distance [H, W] of each pixel's ray from the optical axis on the z = 1 plane (kept for the two
        training levels, not for each random crop)."""
        r2 = self._r2_cache.get(intr)
        if r2 is None:
            rays = pixel_rays(intr)  # [H, W, 3]
            r2 = rays[..., 0] ** 2 + rays[..., 1] ** 2
            if intr in (self.store.level_intrinsics(0), self.store.level_intrinsics(1)):
                self._r2_cache[intr] = r2
        return r2

    def sensor_image(self, color: torch.Tensor, intr: Intrinsics, kf_id: int) -> torch.Tensor:
        """A render [H, W, 3] at intrinsics intr as the camera records it: vignetted, then keyframe ``kf_id``'s
        exposure (``REFERENCE_EXPOSURE``: the reference one, ``reference_exposure``)."""
        return self._expose(self._vignetted(color, intr), kf_id)

    def _vignetted(self, color: torch.Tensor, intr: Intrinsics) -> torch.Tensor:
        """A render [H, W, 3] at intrinsics intr with the camera's vignetting (unchanged without ``vignetting``)."""
        return color * self.vignetting_gain(intr)[..., None] if self.cfg.vignetting else color

    def _expose(self, color: torch.Tensor, kf_id: int | None) -> torch.Tensor:
        """Apply a keyframe's affine brightness (or with ``REFERENCE_EXPOSURE`` the reference one) to a rendered
        image [H, W, 3] or colours [N, 3]."""
        e = self.reference_exposure() if kf_id == REFERENCE_EXPOSURE else self._exposure_of(kf_id)
        return color if e is None else color * torch.exp(e[:3]) + e[3:]

    def _exposure_of(self, kf_id: int | None) -> torch.Tensor | None:
        """Keyframe kf_id's exposure [6] (log gains, offsets; a view of the parameter), None where it has none."""
        if kf_id is None or kf_id not in self.exposure_row or not self.cfg.exposure:
            return None
        return self.exposure[self.exposure_row[kf_id]]

    @torch.no_grad()
    def _fit_exposure(self, kf_id: int, color: torch.Tensor, alpha: torch.Tensor, rgb: np.ndarray, intr: Intrinsics,
                      min_alpha: float = 0.5, recentre: bool = True) -> bool:
        """Set keyframe ``kf_id``'s exposure to the per-channel least-squares affine map from a render [H, W, 3] at
        intrinsics intr (its alpha [H, W]), with the camera's vignetting (``_vignetted``, applied inside the compiled
        sums), to its image rgb [H, W, 3], over the pixels the map covers (alpha > min_alpha), then
        (``exposure_gauge: mean``, with ``recentre``) shift all exposures to a mean of zero. False (nothing changed)
        where too few pixels are covered, and for the first keyframe with ``exposure_gauge: first``: were every
        exposure fitted freely, the map's colours could drift by any affine map that all exposures undo (a synthetic
        test drifted to gains 0.8 and offsets -0.2)."""
        mean_gauge = self.cfg.exposure_gauge == "mean"
        if not self.cfg.exposure or kf_id not in self.exposure_row or (
                self.exposure_row[kf_id] == 0 and not mean_gauge):
            return False  # with the first keyframe as gauge its exposure stays the identity
        x = color.detach().float().contiguous().numpy()  # [H, W, 3]
        vig = self.cfg.vignetting
        # sums [4, 3]: of x, y, x y, x x per channel
        n, sums = covered_moments(x, np.ascontiguousarray(rgb, np.float32), alpha.detach().float().contiguous().numpy(),
                                  min_alpha, self._ray_r2(intr).numpy() if vig else None,
                                  tuple(self.vignette.detach().tolist()) if vig else (0.0, 0.0))
        if n < 100:
            return False
        xm, ym, sxy, sxx = torch.from_numpy(sums / n)  # [3] each
        cov = sxy - xm * ym
        var = sxx - xm * xm
        gain = (cov / var.clamp_min(1e-9)).clamp(0.25, 4.0)  # a flat or dark render cannot set a gain
        self.exposure[self.exposure_row[kf_id]] = torch.cat([gain.log(), ym - gain * xm]).float()
        if mean_gauge and recentre:
            # the shift leaves each exposure a little off its fit: that residual is what holds the map's colours
            self.exposure -= self.exposure.mean(dim=0)
        return True

    @torch.no_grad()
    def refit_exposures(self) -> int:
        """``_fit_exposure`` for every keyframe from a fresh render of the map at the training size (the end of a
        run: each keyframe's last fit is as old as its last step; with ``exposure_closed_form``); returns the number
        refitted."""
        if not (self.cfg.exposure and self.cfg.exposure_closed_form):
            return 0
        n = 0
        with self.lock:
            intr = self.store.level_intrinsics(0)
            stored = set(self.store.ids())
            for kf in sorted(self.exposure_row):
                T_wc = self._pose(kf)
                if T_wc is None or kf not in stored:
                    continue
                g, _ = self._decode_view(T_wc, intr)
                if len(g) == 0:
                    continue
                out, _ = self._rasterize(g, intr, T_wc, None)
                # no recentring: the final exposures are each keyframe's best fit to the finished map
                n += self._fit_exposure(kf, out.color, out.alpha, self.store.get(kf, 0).rgb, intr, recentre=False)
        return n

    # --- rendering -----------------------------------------------------------------------------------
    @torch.no_grad()
    def render(self, T_wc: np.ndarray, intr: Intrinsics | None = None, exposure_kf: int | None = None,
               without_kf: int | None = None, planar: bool = True) -> RenderOutput:
        """Render the map from camera-to-world T_wc [4, 4] (training intrinsics by default); ``without_kf``
        leaves out the anchors that keyframe seeded; ``planar=False`` skips the planar-weight channel (``extras``),
        which costs up to half the render on maps of many overlapping Gaussians."""
        intr = intr or self.intr
        with self.lock:
            g, _ = self._decode_view(T_wc, intr, without_kf)
            p2d = self._planar_channel(g) if planar else None
            out, _ = self._rasterize(g, intr, T_wc, p2d)
            if exposure_kf is not None:
                out.color = self.sensor_image(out.color, intr, exposure_kf)
            out.color = out.color.clamp(0, 1)
            return out

    @torch.no_grad()
    def bake_gaussians(self) -> DecodedGaussians:
        """The map as explicit 3DGS Gaussians (AMR applied), for gaussians.ply, the mesh and the Gaussian count
        (gaussians/bake.py): exactly the decoded children with their SH colours (``colors`` the DC part,
        ``sh_rest`` [G, B, 3] the rest), or for a view-dependent (Scaffold-GS) decoder each anchor decoded from the
        nearest keyframe that saw it, colours fitted as degree-1 SH over up to four observing keyframes. Colours
        carry the reference exposure (``reference_exposure``)."""
        with self.lock:
            kf_ids = sorted(self.anchor_poses)
            if not kf_ids or self.map.n_anchors == 0:
                return self.map.decode(np.zeros(3), torch.zeros(self.map.n_anchors, dtype=torch.bool))
            poses = [self._pose(k) for k in kf_ids]
            if self.map.decoder.view_dependent:
                g = self._bake_from_keyframes(kf_ids, poses)
            else:
                g = self._decode(poses[-1][:3, 3])  # the viewpoint only sets the (unused) evaluated colour
                if len(g):
                    slot = g.child_index % self.map.k
                    dc, rest = self.map.decoder.sh(self.map.features, self.map.base_color)  # [A, k, 3], [A, k, B, 3]
                    g.colors = dc[g.anchor_index, slot]
                    g.sh_rest = rest[g.anchor_index, slot] if rest.shape[2] else None
            # one file has one brightness: the keyframes' typical exposure (their learned gains drift together)
            e = self.reference_exposure()
            if e is not None:
                g.colors = self._expose(g.colors, REFERENCE_EXPOSURE)
                if g.sh_rest is not None:
                    g.sh_rest = g.sh_rest * torch.exp(e[:3])
            return g

    def _bake_from_keyframes(self, kf_ids: list[int], poses: list[np.ndarray], max_views: int = 4) -> DecodedGaussians:
        """A view-dependent map's children, each anchor decoded from its nearest observing keyframe, with
        degree-1 SH colours fitted over up to ``max_views`` observing keyframes."""
        depths = [self.store.get(k).depth for k in kf_ids]
        views = observing_keyframes(self.map.surface.numpy(), poses, depths, self.intr, self.map.voxel_size,
                                    max_views, self.settings.near_plane)
        centres = torch.from_numpy(np.stack([T[:3, 3] for T in poses]).astype(np.float32))  # [K, 3]
        first = torch.from_numpy(np.where(views.observed, views.views[:, 0], views.nearest))  # [A]
        g = self._decode(centres[first])
        if len(g):
            g.colors, g.sh_rest = self._fit_sh1(g, centres, torch.from_numpy(views.views), first)
        return g

    def _fit_sh1(self, g: DecodedGaussians, centres: torch.Tensor, views: torch.Tensor, first: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """Degree-1 SH colours of the baked children g over their anchors' observing keyframes views [A, V]."""
        k = self.map.k
        anchors, slot = g.anchor_index, g.child_index % k  # [G]
        uniq, inv = torch.unique(anchors, return_inverse=True)  # [M], [G]
        views = views[uniq].clone()  # [M, V]
        views[:, 0] = first[uniq]  # the bake's own view (a fallback where no keyframe saw the anchor)
        pos = self.map.anchors[uniq]  # [M, 3]
        cols, dirs = [], []
        for v in range(views.shape[1]):
            c = centres[views[:, v].clamp_min(0)]  # [M, 3]
            color = self.map.decode_dense(c, uniq)[4]  # [M, k, 3]
            cols.append(color[inv, slot])  # [G, 3]
            d = pos - c
            dirs.append((d / d.norm(dim=1, keepdim=True).clamp_min(1e-9))[inv])
        valid = (views >= 0)[inv]  # [G, V]
        return fit_sh1(torch.stack(cols, 1), torch.stack(dirs, 1), valid)

    @torch.no_grad()
    def reexpose(self, color: torch.Tensor, kf_id: int, intr: Intrinsics | None = None) -> torch.Tensor:
        """Colours [..., 3] under the reference exposure (a baked file's) brought to keyframe ``kf_id``'s exposure;
        for an image [H, W, 3] rendered at ``intr`` also the camera's vignetting (``sensor_image``)."""
        e_ref = self.reference_exposure()
        scene = color if e_ref is None else (color - e_ref[3:]) * torch.exp(-e_ref[:3])  # the reference undone
        kf = kf_id if kf_id in self.exposure_row else REFERENCE_EXPOSURE
        return self._expose(scene, kf) if intr is None else self.sensor_image(scene, intr, kf)

    def reference_exposure(self) -> torch.Tensor | None:
        """The brightness of views that have no keyframe of their own (baked Gaussians, renders along new paths):
        with learned exposures their median [6] (log gain, offset; they drift together); None without exposure or
        with solved ones (their gauge, ``exposure_gauge``, is the identity: the map holds the keyframes' mean or
        the first keyframe's colours, and an offset baked into Gaussians would be scaled by each pixel's alpha)."""
        if not self.cfg.exposure or self.cfg.exposure_closed_form or len(self.exposure_row) == 0:
            return None  # solved exposures are relative to the identity, whose colours the map holds
        return self.exposure.detach().median(dim=0).values

    @torch.no_grad()
    def planarity(self) -> dict[str, torch.Tensor]:
        """Per anchor [A]: P_2D, P_prior, posterior flatness of its exported children (1 - s_min / s_mid),
        curvature, colour variance, observations, and surface points [A, 3] (needs ``ggf.enabled``)."""
        from ggfslam.ggf.aof import posterior_flatness

        if self.ggf is None:
            raise RuntimeError("the map has no Geometric-Gaussian Field (ggf.enabled is false)")
        with self.lock:
            g = self.bake_gaussians()
            post, count = posterior_flatness(g.scales, g.anchor_index, self.map.n_anchors)
            geo = self.ggf.geom
            return {"p2d": self.ggf.p2d().clone(), "prior": self.ggf.prior.clone(), "posterior": post,
                    "children": count, "curvature": geo.curvature.clone(), "color_var": geo.color_var.clone(),
                    "obs": geo.obs.clone(), "surface": self.map.surface.clone(),
                    "surface_n": self.map.surface_n.clone()}

    @torch.no_grad()
    def export_planarity(self, baked: DecodedGaussians | None = None) -> DecodedGaussians:
        """The baked children (``baked``, a ``bake_gaussians()`` result, or a new bake) coloured by their anchor's
        P_2D (red = 2D, blue = 3D), as in the paper's Fig. 4; ``baked`` itself is left as it is."""
        with self.lock:
            if self.ggf is None:
                raise RuntimeError("the map has no Geometric-Gaussian Field (ggf.enabled is false)")
            g = self.bake_gaussians() if baked is None else baked
            return dataclasses.replace(g, colors=planarity_colors(self.ggf.p2d()[g.anchor_index]), sh_rest=None)

    def n_gaussians(self) -> int:
        """Children in the bake (``bake_gaussians``): those with positive opacity."""
        return len(self.bake_gaussians())

    def stats(self, baked: DecodedGaussians | None = None) -> dict:
        """Figures for metrics.json (the Gaussian count from ``baked``, a ``bake_gaussians()`` result, if given)."""
        return {"iterations": self.iteration, "train_seconds": self.train_seconds,
                "iterations_per_s": self.iteration / self.train_seconds if self.train_seconds else 0.0,
                "anchors": self.map.n_anchors,
                "gaussians": self.n_gaussians() if baked is None else len(baked), "anchors_grown": self.grown,
                "anchors_pruned": self.pruned, "anchors_merged": self.merged, "keyframes": len(self.store),
                "train_width": self.intr.width, "train_height": self.intr.height, "last_losses": self.last_losses,
                **({"ggf": self.ggf.stats()} if self.ggf is not None else {})}

    # --- checkpoint ----------------------------------------------------------------------------------
    def state(self) -> dict:
        """Everything needed to continue training (anchors, MLPs, optimizer, exposures, RNG, counters)."""
        with self.lock:
            return {"map_extra": self.map.extra_state(), "map": self.map.state_dict(),
                    "exposure": self.exposure.detach().clone(), "exposure_row": dict(self.exposure_row),
                    "vignette": self.vignette.detach().clone(),
                    "opt": self.opt.state_dict(), "density": vars(self.density.stats).copy(),
                    "anchor_poses": {k: v.copy() for k, v in self.anchor_poses.items()},
                    "poses": {k: v.copy() for k, v in self._poses.items()},
                    "rng": self.rng.bit_generator.state, "iteration": self.iteration,
                    "train_seconds": self.train_seconds, "grown": self.grown, "pruned": self.pruned,
                    "merged": self.merged, "kf_loss": dict(self.kf_loss), "rest_paid_until": self.rest_paid_until,
                    "generator": self.map.gen.get_state(),
                    "ggf": self.ggf.state() if self.ggf is not None else None}

    def load_state(self, st: dict) -> None:
        """Restore ``state()`` into this mapper (same config and camera)."""
        from ggfslam.gaussians.density import DensityStats

        with self.lock:
            self.map = AnchorMap.from_state(st["map_extra"], st["map"])
            self._reach_cache = None
            self.map.gen.set_state(st["generator"])
            self.exposure = nn.Parameter(st["exposure"].clone())
            self.exposure_row = dict(st["exposure_row"])
            self.vignette = nn.Parameter(st["vignette"].clone() if "vignette" in st else torch.zeros(2))
            self.opt = self._make_optimizer()
            opt_state = st["opt"]
            groups = self.opt.state_dict()["param_groups"]
            if len(opt_state["param_groups"]) == len(groups) - 1:  # from before the vignetting: fresh Adam state
                opt_state = {"state": opt_state["state"], "param_groups": opt_state["param_groups"] + groups[-1:]}
            self.opt.load_state_dict(opt_state)
            self.density = DensityControl(self.map, self.cfg.grow_grad_threshold, self.cfg.prune_min_opacity,
                                          self.cfg.density_min_visits, self.cfg.max_anchors)
            self.density.stats = DensityStats(**st["density"])
            self.anchor_poses = {int(k): v.copy() for k, v in st["anchor_poses"].items()}
            self._poses = {int(k): v.copy() for k, v in st["poses"].items()}
            self.rng.bit_generator.state = st["rng"]
            self.iteration, self.train_seconds = st["iteration"], st["train_seconds"]
            self.grown, self.pruned = st["grown"], st["pruned"]
            self.merged = st.get("merged", 0)  # checkpoints written before merging existed
            self.kf_loss = {int(k): float(v) for k, v in st.get("kf_loss", {}).items()}
            self.rest_paid_until = int(st.get("rest_paid_until", -1))  # checkpoints from before it: nothing paid
            if self.ggf is not None:
                if st.get("ggf") is None:
                    raise ValueError("checkpoint has no Geometric-Gaussian Field state but ggf.enabled is true: "
                                     "resume with the configuration the run started with")
                self.ggf.load_state(st["ggf"])
                self._refresh_field()  # a no-op unless the checkpoint's geometry is missing or stale
