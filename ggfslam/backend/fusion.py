"""Landmark fusion between a new keyframe and its neighbours (ORB-SLAM's "search in neighbours").

Tracking only matches a frame against points it predicts in view, so the same physical point is often created
again by a later keyframe. Fusion projects each keyframe's landmarks into the other's image, matches them by
descriptor within a radius and, with RGB-D, by depth: a keypoint whose measured depth disagrees with the
projected point is not the same surface. A matched keypoint without a landmark gains an observation; one that
already has another landmark is merged into the landmark with more observations. Longer tracks are what let
bundle adjustment average the keypoint noise over many views.
"""
from __future__ import annotations

import numpy as np

from ggfslam.backend.slam_map import SlamMap
from ggfslam.config import TrackingConfig
from ggfslam.data.types import Camera
from ggfslam.frontend.matching import match_projected
from ggfslam.geometry.se3 import invert


def project_landmarks(smap: SlamMap, lm: np.ndarray, T_wc: np.ndarray, camera: Camera, scale_factor: float,
                      n_levels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixels [K, 2], depths [K], predicted pyramid levels [K] and in-view mask [K] of landmarks seen from T_wc.

    Caller holds ``smap.lock``."""
    X = smap.positions[lm]  # [K, 3] world
    T_cw = invert(T_wc)
    p = X @ T_cw[:3, :3].T + T_cw[:3, 3]  # [K, 3] camera frame
    z = p[:, 2]
    zs = np.where(z > 1e-6, z, 1.0)
    uv = np.stack([camera.fx * p[:, 0] / zs + camera.cx, camera.fy * p[:, 1] / zs + camera.cy], axis=1)
    dist = np.linalg.norm(p, axis=1)
    ref_d = np.maximum(smap.ref_distance[lm], 1e-6)
    level_scale_max = scale_factor ** (n_levels - 1)
    inside = (z > 0.05) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & \
             (uv[:, 1] < camera.height) & (dist < 3.0 * ref_d * level_scale_max) & (dist > ref_d / (3.0 * level_scale_max))
    # a point seen at level o from distance d appears at level o + log_s(d / dist) from distance dist
    level = np.round(smap.ref_octave[lm] + np.log(ref_d / np.maximum(dist, 1e-6)) / np.log(scale_factor))
    return uv, z, np.clip(level, 0, n_levels - 1).astype(np.int64), inside


def fuse_into(smap: SlamMap, lm: np.ndarray, target_id: int, camera: Camera, cfg: TrackingConfig,
              radius: float, max_distance: int = 50, depth_tol_abs: float = 0.05,
              depth_tol_rel: float = 0.04) -> tuple[int, int]:
    """Fuse landmarks ``lm`` into keyframe ``target_id``; returns (observations added, landmarks merged).

    Caller holds ``smap.lock``."""
    kf = smap.keyframes[target_id]
    F = kf.features
    lm = lm[smap.alive[lm]]
    lm = np.array([l for l in lm if target_id not in smap.observations[l]], dtype=np.int64)
    if len(lm) == 0 or len(F) == 0:
        return 0, 0
    uv, z, level, inside = project_landmarks(smap, lm, kf.T_wc, camera, cfg.scale_factor, cfg.n_levels)
    lm, uv, z, level = lm[inside], uv[inside], z[inside], level[inside]
    level_scale = cfg.scale_factor ** np.arange(cfg.n_levels)
    pairs = match_projected(uv, smap.descriptors[lm], level, F.uv, F.descriptors, F.octave, radius, level_scale,
                            max_distance, cfg.match_ratio)
    added = merged = 0
    for pi, ki in pairs:
        d = F.depth[ki]
        if d > 0 and abs(d - z[pi]) > max(depth_tol_abs, depth_tol_rel * d):
            continue  # another surface along the same ray
        # reprojection gate at the keypoint's own scale (chi2 2 dof, 95 %) like ORB-SLAM's Fuse
        sigma = cfg.pixel_sigma * level_scale[F.octave[ki]]
        if np.sum((uv[pi] - F.uv[ki]) ** 2) > 5.991 * sigma ** 2:
            continue
        src = int(lm[pi])
        if not smap.alive[src] or target_id in smap.observations[src]:
            continue
        old = int(kf.landmark_ids[ki])
        if old < 0 or not smap.alive[old]:
            smap.add_observation(src, kf, int(ki))
            added += 1
        elif old != src:
            # the better-established landmark survives: more observations, then the older one
            rank_src = (len(smap.observations[src]), -smap.born[src])
            rank_old = (len(smap.observations[old]), -smap.born[old])
            keep, drop = (src, old) if rank_src > rank_old else (old, src)
            smap.merge_landmarks(keep=keep, drop=drop)
            merged += 1
    return added, merged


def fuse_neighbours(smap: SlamMap, kf_id: int, neighbours: list[int], camera: Camera, cfg: TrackingConfig,
                    radius: float = 3.0, max_distance: int = 50) -> tuple[int, int]:
    """Fuse keyframe ``kf_id``'s landmarks into its neighbours and theirs into it; returns (added, merged)."""
    added = merged = 0
    with smap.lock:
        if kf_id not in smap.keyframes:
            return 0, 0
        own = smap.landmarks_of([kf_id])
        for n in neighbours:
            if n == kf_id or n not in smap.keyframes:
                continue
            a, m = fuse_into(smap, own, n, camera, cfg, radius, max_distance)
            added, merged = added + a, merged + m
            own = smap.landmarks_of([kf_id])  # merges may have replaced some of them
        theirs = smap.landmarks_of([n for n in neighbours if n != kf_id])
        a, m = fuse_into(smap, theirs, kf_id, camera, cfg, radius, max_distance)
    return added + a, merged + m
