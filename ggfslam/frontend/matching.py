"""Descriptor matching: Hamming distances, projection-guided search against map points, ratio-test matching."""
from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)  # [256]


def hamming_pairs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances [K] between row pairs of a [K, 32] and b [K, 32] (uint8 descriptors)."""
    return _POPCOUNT[np.bitwise_xor(a, b)].sum(axis=1, dtype=np.int32)


def match_ratio(a: np.ndarray, b: np.ndarray, max_distance: int, ratio: float) -> np.ndarray:
    """Mutual nearest-neighbour matches [K, 2] (index in a, index in b) passing a ratio test (OpenCV brute force)."""
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    fwd = bf.knnMatch(a, b, k=2)
    back = bf.match(b, a)
    back_best = np.full(len(b), -1, dtype=np.int64)
    for m in back:
        back_best[m.queryIdx] = m.trainIdx
    pairs = [(m[0].queryIdx, m[0].trainIdx) for m in fwd
             if len(m) == 2 and m[0].distance <= max_distance and m[0].distance < ratio * m[1].distance
             and back_best[m[0].trainIdx] == m[0].queryIdx]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def match_projected(
    proj_uv: np.ndarray, proj_desc: np.ndarray, proj_level: np.ndarray, kp_uv: np.ndarray, kp_desc: np.ndarray,
    kp_octave: np.ndarray, radius: float, level_scale: np.ndarray, max_distance: int, ratio: float,
    taken: np.ndarray | None = None,
) -> np.ndarray:
    """Match projected map points to keypoints within a radius; returns [K, 2] (point index, keypoint index).

    Each keypoint is matched at most once (the closest descriptor wins); keypoint octaves must be within one
    level of the point's predicted level. ``taken`` [N_kp] marks keypoints that are already matched.
    """
    if len(proj_uv) == 0 or len(kp_uv) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    tree = cKDTree(kp_uv)
    radii = radius * level_scale[np.clip(proj_level, 0, len(level_scale) - 1)]  # [P]
    cand = tree.query_ball_point(proj_uv, r=radii)
    pi = np.repeat(np.arange(len(proj_uv)), [len(c) for c in cand])
    if len(pi) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    ki = np.concatenate([np.asarray(c, dtype=np.int64) for c in cand])
    keep = np.abs(kp_octave[ki] - proj_level[pi]) <= 1
    if taken is not None:
        keep &= ~taken[ki]
    pi, ki = pi[keep], ki[keep]
    if len(pi) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    dist = hamming_pairs(proj_desc[pi], kp_desc[ki])
    # per point: best and second-best distance among its candidates
    order = np.lexsort((dist, pi))
    pi, ki, dist = pi[order], ki[order], dist[order]
    first = np.r_[True, pi[1:] != pi[:-1]]
    start = np.nonzero(first)[0]
    best_d = dist[start]
    second = np.full(len(start), 256, dtype=np.int32)
    has2 = np.r_[start[1:], len(pi)] - start > 1
    second[has2] = dist[start[has2] + 1]
    ok = (best_d <= max_distance) & (best_d < ratio * second)
    p_sel, k_sel, d_sel = pi[start[ok]], ki[start[ok]], best_d[ok]
    if len(p_sel) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    # a keypoint claimed by several points keeps the closest descriptor
    order = np.lexsort((d_sel, k_sel))
    p_sel, k_sel = p_sel[order], k_sel[order]
    uniq = np.r_[True, k_sel[1:] != k_sel[:-1]]
    return np.stack([p_sel[uniq], k_sel[uniq]], axis=1)
