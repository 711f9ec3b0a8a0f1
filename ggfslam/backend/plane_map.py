"""Plane landmarks: associate a keyframe's detected planes with the map's planes, or start new ones.

A plane detected in a keyframe (``frontend/planes.py``, camera coefficients (n, d) with n . x + d = 0) is
predicted from every map plane through the keyframe's current pose; it joins the map plane whose prediction
agrees in normal direction and distance, else it becomes a new plane landmark. Local bundle adjustment then
holds keyframes and planes together with GTSAM ``OrientedPlane3Factor``s.
"""
from __future__ import annotations

import numpy as np

from ggfslam.backend.slam_map import SlamMap
from ggfslam.config import BackendConfig


def plane_to_camera(plane_w: np.ndarray, T_wc: np.ndarray) -> np.ndarray:
    """World plane [4] -> the same plane [4] in the camera frame of pose T_wc (GTSAM's OrientedPlane3.transform)."""
    R, t = T_wc[:3, :3], T_wc[:3, 3]
    n_w, d_w = plane_w[:3], plane_w[3]
    return np.r_[R.T @ n_w, d_w + n_w @ t]


def plane_to_world(plane_c: np.ndarray, T_wc: np.ndarray) -> np.ndarray:
    """Camera-frame plane [4] of pose T_wc -> world plane [4]."""
    R, t = T_wc[:3, :3], T_wc[:3, 3]
    n_w = R @ plane_c[:3]
    return np.r_[n_w, plane_c[3] - n_w @ t]


def associate_planes(smap: SlamMap, kf_id: int, cfg: BackendConfig) -> list[int]:
    """Give each plane detected in keyframe ``kf_id`` (``meta["planes"]``) a map plane; returns their ids."""
    with smap.lock:
        kf = smap.keyframes[kf_id]
        detected = kf.meta.get("planes", [])
        ids: list[int] = []
        used: set[int] = set()
        cos_max = np.cos(np.radians(cfg.plane_match_deg))
        for plane in detected:
            z = np.asarray(plane.coefficients, np.float64)  # [4]
            best, best_cost = -1, np.inf
            for pid, pw in smap.planes.items():
                if pid in used:
                    continue
                pred = plane_to_camera(pw, kf.T_wc)
                cos = float(pred[:3] @ z[:3])
                dd = abs(pred[3] - z[3])
                if cos < cos_max or dd > cfg.plane_match_distance:
                    continue
                cost = (1.0 - cos) / (1.0 - cos_max) + dd / cfg.plane_match_distance
                if cost < best_cost:
                    best, best_cost = pid, cost
            if best < 0:
                best = max(smap.planes, default=-1) + 1
                smap.planes[best] = plane_to_world(z, kf.T_wc)
                smap.plane_observations[best] = {}
            smap.plane_observations[best][kf_id] = z
            used.add(best)
            ids.append(best)
        kf.meta["plane_ids"] = ids
        return ids
