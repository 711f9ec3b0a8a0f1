"""Descriptor matching: Hamming distances, projection-guided search against map points, ratio-test matching.

``match_projected`` runs every frame (twice or three times): it is a compiled kernel over a grid of the keypoints
(no GIL: tracking runs beside mapping and the backend); ``match_projected_reference`` is the same rule in numpy
over a k-d tree, and tests hold the two together.
"""
from __future__ import annotations

import cv2
import numpy as np
from numba import njit
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


def match_projected_reference(
    proj_uv: np.ndarray, proj_desc: np.ndarray, proj_level: np.ndarray, kp_uv: np.ndarray, kp_desc: np.ndarray,
    kp_octave: np.ndarray, radius: float, level_scale: np.ndarray, max_distance: int, ratio: float,
    taken: np.ndarray | None = None,
) -> np.ndarray:
    """Match projected map points to keypoints within a radius; returns [K, 2] (point index, keypoint index),
    sorted by keypoint.

    A point's radius is ``radius`` times the scale of its predicted level; keypoint octaves must be within one
    level of it; ``taken`` [N_kp] marks keypoints that are already matched. A point takes its closest descriptor
    (the lower keypoint index on a tie) if within ``max_distance`` and below ``ratio`` times the second closest.
    Each keypoint is matched at most once: the closest descriptor wins (the lower point index on a tie).
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
    order = np.lexsort((ki, dist, pi))
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


def match_projected(
    proj_uv: np.ndarray, proj_desc: np.ndarray, proj_level: np.ndarray, kp_uv: np.ndarray, kp_desc: np.ndarray,
    kp_octave: np.ndarray, radius: float, level_scale: np.ndarray, max_distance: int, ratio: float,
    taken: np.ndarray | None = None,
) -> np.ndarray:
    """``match_projected_reference``'s matches [K, 2], from the compiled kernel."""
    if len(proj_uv) == 0 or len(kp_uv) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    radii = radius * level_scale[np.clip(proj_level, 0, len(level_scale) - 1)]  # [P]
    taken = np.zeros(len(kp_uv), np.bool_) if taken is None else np.asarray(taken, np.bool_)
    return _match_projected_kernel(np.ascontiguousarray(proj_uv, np.float64), np.ascontiguousarray(proj_desc),
                                   np.asarray(proj_level, np.int64), np.ascontiguousarray(kp_uv, np.float64),
                                   np.ascontiguousarray(kp_desc), np.asarray(kp_octave, np.int64),
                                   np.asarray(radii, np.float64), taken, int(max_distance), float(ratio), _POPCOUNT)


@njit(cache=True, nogil=True)
def _match_projected_kernel(proj_uv, proj_desc, proj_level, kp_uv, kp_desc, kp_octave, radii, taken, max_distance,
                            ratio, popcount):
    P, K = proj_uv.shape[0], kp_uv.shape[0]
    # keypoints bucketed in square cells (counting sort), so each point visits the cells its circle touches
    cell = 16.0
    x0, y0 = kp_uv[:, 0].min(), kp_uv[:, 1].min()
    nx = int((kp_uv[:, 0].max() - x0) / cell) + 1
    ny = int((kp_uv[:, 1].max() - y0) / cell) + 1
    cell_of = np.empty(K, np.int64)
    start = np.zeros(nx * ny + 1, np.int64)
    for k in range(K):
        c = int((kp_uv[k, 1] - y0) / cell) * nx + int((kp_uv[k, 0] - x0) / cell)
        cell_of[k] = c
        start[c + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    members = np.empty(K, np.int64)
    for k in range(K):  # in index order: each cell lists its keypoints by index
        members[fill[cell_of[k]]] = k
        fill[cell_of[k]] += 1
    best_k = np.full(P, -1, np.int64)
    best_d = np.full(P, 1 << 30, np.int64)
    for p in range(P):
        u, v, r = proj_uv[p, 0], proj_uv[p, 1], radii[p]
        cx0 = max(int(np.floor((u - r - x0) / cell)), 0)
        cx1 = min(int(np.floor((u + r - x0) / cell)), nx - 1)
        cy0 = max(int(np.floor((v - r - y0) / cell)), 0)
        cy1 = min(int(np.floor((v + r - y0) / cell)), ny - 1)
        d1, d2, k1 = 1 << 30, 1 << 30, -1
        for cy in range(cy0, cy1 + 1):
            for cx in range(cx0, cx1 + 1):
                c = cy * nx + cx
                for j in range(start[c], start[c + 1]):
                    k = members[j]
                    du, dv = kp_uv[k, 0] - u, kp_uv[k, 1] - v
                    if du * du + dv * dv > r * r or taken[k] or abs(kp_octave[k] - proj_level[p]) > 1:
                        continue
                    d = 0
                    for b in range(proj_desc.shape[1]):
                        d += popcount[proj_desc[p, b] ^ kp_desc[k, b]]
                    if d < d1 or (d == d1 and k < k1):
                        d2 = d1
                        d1, k1 = d, k
                    elif d < d2:
                        d2 = d
        if k1 < 0:
            continue
        second = 256 if d2 == 1 << 30 else d2
        if d1 <= max_distance and d1 < ratio * second:
            best_k[p], best_d[p] = k1, d1
    # a keypoint claimed by several points keeps the closest descriptor (the lower point index on a tie)
    owner = np.full(K, -1, np.int64)
    for p in range(P):
        k = best_k[p]
        if k >= 0 and (owner[k] < 0 or best_d[p] < best_d[owner[k]]):
            owner[k] = p
    n = 0
    for k in range(K):
        if owner[k] >= 0:
            n += 1
    out = np.empty((n, 2), np.int64)
    n = 0
    for k in range(K):
        if owner[k] >= 0:
            out[n, 0], out[n, 1] = owner[k], k
            n += 1
    return out
