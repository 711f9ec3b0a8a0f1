"""Geometric features of the anchors (METHOD.md §3): F_in = [gamma(p) (36), n (3), kappa (1), T (1)].

Everything is computed from the anchors' surface points (``AnchorMap.surface``: the mean of the depth points
that fell in each voxel, so a plane's anchors lie exactly on it, unlike their voxel centres):
- ``gamma(p)``: sin and cos of ``2^i * pi * p`` for i = 0..5 on x, y, z (world metres) -> 36 values;
- ``n``: unit normal, the PCA direction of least variance of the K nearest points (Open3D KNN) of the
  surface points averaged over cells of ``patch_cell`` voxels, each weighted by the depth points it stands
  for, oriented towards the camera of the keyframe that created the anchor;
- ``kappa``: curvature, lambda_0 / (lambda_0 + 2 lambda_1) of the PCA's ascending eigenvalues (0: plane, 1/3:
  isotropic; against the narrower tangent extent so that a long patch on a cylinder still reads as curved;
  METHOD.md's lambda_0 / sum with ``ggf.curvature: sum``);
  near an edge an anchor takes the normal and curvature of a flat neighbouring patch it lies on
  (``borrow_planes``): its own patch spans both faces;
- ``T``: keyframes that saw the anchor (``AnchorMap.obs``);
- ``spacing``: mean distance to the 8 nearest anchors (the surfel radius of AMR follows it).
The patch is wide (32 cells of 2 voxels: ~0.25 m radius at a 4 cm voxel): with depth noise of 1-2 cm at 3 m, a
smaller patch cannot tell a wall from a 0.2 m pillar (curvature grows with the patch radius squared, noise
shrinks); averaging cells first makes that patch cost 32 neighbours instead of ~100.
The network input carries ``kappa / tau`` (clipped to 10) and ``log(1 + T)`` instead of the raw values so its
inputs have comparable ranges; the prior uses the raw values.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import open3d as o3d
import torch
from numba import njit, prange

from ggfslam.gaussians.anchor_map import voxel_keys

N_FREQ = 6
F_IN = 6 * N_FREQ + 3 + 1 + 1  # 41


def positional_encoding(p: torch.Tensor, n_freq: int = N_FREQ) -> torch.Tensor:
    """gamma(p) [A, 6 n_freq]: sin then cos of 2^i pi p for i < n_freq, frequency-major, x y z inner."""
    f = (2.0 ** torch.arange(n_freq, dtype=p.dtype)) * torch.pi  # [n_freq]
    x = (p[:, None, :] * f[None, :, None]).reshape(p.shape[0], -1)  # [A, 3 n_freq]
    return torch.cat([torch.sin(x), torch.cos(x)], dim=1)


def _knn(data: np.ndarray, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Open3D KNN: indices [Q, k] into data [N, 3] and distances [Q, k] of queries [Q, 3]."""
    nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(np.ascontiguousarray(data, np.float32)))
    nns.knn_index()
    idx, d2 = nns.knn_search(o3d.core.Tensor(np.ascontiguousarray(queries, np.float32)), k)
    return idx.numpy(), np.sqrt(np.maximum(d2.numpy(), 0.0))


def cell_means(points: np.ndarray, weights: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean point [C, 3] and total weight [C] of the points [N, 3] in each occupied cubic cell."""
    _, inv = np.unique(voxel_keys(points, cell), return_inverse=True)
    inv = inv.reshape(-1)
    w = np.bincount(inv, weights)
    mean = np.stack([np.bincount(inv, weights * points[:, j]) for j in range(3)], 1) / w[:, None]
    return mean, w


class LocalGeometry(NamedTuple):
    """What ``local_geometry`` finds for each of N points."""

    normals: np.ndarray  # [N, 3] unit, unoriented: the patch's direction of least variance
    curvature: np.ndarray  # [N] 0 on a plane, 1/3 for an isotropic cloud
    spacing: np.ndarray  # [N] mean distance to the k_spacing nearest points (m)
    plane_points: np.ndarray  # [N, 3] the point projected onto its patch's plane (a plane averaged over the patch)


@dataclass(frozen=True)
class PlaneBorrowing:
    """How points near an edge take a neighbour's plane (``borrow_planes``)."""

    k: int  # neighbouring points whose patches are candidates (0: off)
    tol: float  # metres a point may lie off a candidate plane beyond twice that patch's thickness
    factor: float  # a borrowed curvature counts this many times its value
    min_curvature: float = 0.0  # points flatter than this keep their own patch (and are not searched)


def local_geometry(points: np.ndarray, k: int, weights: np.ndarray | None = None, cell: float | None = None,
                   k_spacing: int = 8, chunk: int = 32768, borrow: PlaneBorrowing | None = None,
                   curvature_norm: str = "tangent") -> LocalGeometry:
    """Weighted PCA of the k nearest neighbours of every point [N, 3] (see ``LocalGeometry``); curvature =
    lambda_0 / (lambda_0 + 2 lambda_1) (eigenvalues ascending; ``curvature_norm="sum"``: lambda_0 / sum).

    ``weights`` [N] (default 1): how many samples each point stands for (an anchor's surface point averages
    many depth points; sparse outliers of a noisy surface average few and so count little). With ``cell``
    the neighbours are the weighted means of the points in cubic cells of that size (a coarser cloud), so a
    wide patch costs k neighbours instead of k * (points per cell). With ``borrow``, points near an edge take
    the plane of a neighbour's patch they lie on (``borrow_planes``)."""
    n = len(points)
    if n == 0:
        return LocalGeometry(np.zeros((0, 3), np.float32), np.zeros(0, np.float32), np.zeros(0, np.float32),
                             np.zeros((0, 3), np.float64))
    pts = np.asarray(points, dtype=np.float64)
    w_pts = np.ones(n) if weights is None else np.maximum(np.asarray(weights, np.float64), 1e-6)
    cloud, w_cloud = (pts, w_pts) if cell is None else cell_means(pts, w_pts, cell)
    k = min(k, len(cloud))
    normals = np.zeros((n, 3), np.float32)
    curvature = np.zeros(n, np.float32)
    centroids = np.zeros((n, 3), np.float64)
    thickness = np.zeros(n, np.float32)  # [N] standard deviation of the patch along its normal (m)
    for s in range(0, n, chunk):  # bounded memory: [chunk, k, 3] at a time
        q = pts[s:s + chunk]
        idx, _ = _knn(cloud, q, k)
        w = w_cloud[idx]
        w /= w.sum(axis=1, keepdims=True)
        nb = (cloud[idx] - q[:, None, :]).astype(np.float32)  # [C, k, 3], relative for precision
        wf = w.astype(np.float32)
        mu = np.einsum("ck,cki->ci", wf, nb)
        cov = np.matmul(nb.transpose(0, 2, 1) * wf[:, None, :], nb) - mu[:, :, None] * mu[:, None, :]  # [C, 3, 3]
        evals, evecs = np.linalg.eigh(cov.astype(np.float64))  # ascending eigenvalues
        evals = evals.clip(min=0)
        normals[s:s + chunk] = evecs[:, :, 0]
        # against the patch's narrower extent, not the sum: a cylinder's patch is long along its axis, and
        # that length hid its curvature (a 0.2 m pillar read as planar)
        denom = evals.sum(axis=1) if curvature_norm == "sum" else evals[:, 0] + 2 * evals[:, 1]
        curvature[s:s + chunk] = np.where(denom > 0, evals[:, 0] / np.maximum(denom, 1e-30), 0.0)
        centroids[s:s + chunk] = q + mu
        thickness[s:s + chunk] = np.sqrt(evals[:, 0])
    if borrow is not None and borrow.k > 0:
        normals, curvature, centroids = borrow_planes(pts, normals, curvature, centroids, thickness, borrow, chunk)
    ks = min(k_spacing + 1, n)
    spacing = _knn(pts, pts, ks)[1][:, 1:].mean(axis=1) if ks > 1 else np.zeros(n)
    plane_points = pts - np.einsum("ni,ni->n", normals, pts - centroids)[:, None] * normals
    return LocalGeometry(normals, curvature, spacing.astype(np.float32), plane_points)


def borrow_planes(points: np.ndarray, normals: np.ndarray, curvature: np.ndarray, centroids: np.ndarray,
                  thickness: np.ndarray, borrow: PlaneBorrowing, chunk: int = 32768
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals [N, 3], curvature [N] and patch centroids [N, 3] after every point [N, 3] took the flattest
    patch among its ``borrow.k`` nearest points' patches whose plane passes through it (within 2 thickness +
    ``tol``).

    A patch centred on an edge spans both faces and reads as curved; the patch of a neighbour a little
    inside the point's own face is flat and contains it. The borrowed curvature is scaled by ``factor`` so
    that only clearly flat patches lend their plane: on a curved surface the neighbours' patches are about
    as curved as the point's own, and taking their minimum would let noise flatten it (the synthetic room's
    pillar: 27% of its anchors planar with factor 1, 5% with 4)."""
    n = len(points)
    k = min(borrow.k + 1, n)
    out_n, out_c, out_p = normals.copy(), curvature.copy(), centroids.copy()
    borrowers = np.nonzero(curvature > borrow.min_curvature)[0]
    pts = np.ascontiguousarray(points, np.float64)
    cen = np.ascontiguousarray(centroids, np.float64)
    for s in range(0, len(borrowers), chunk):
        rows = borrowers[s:s + chunk]
        idx, _ = _knn(pts, pts[rows], k)  # [C, k], itself included
        _borrow_rows(rows, idx.astype(np.int64), pts, normals, curvature, cen, thickness, float(borrow.tol),
                     float(borrow.factor), out_n, out_c, out_p)
    return out_n, out_c, out_p


@njit(cache=True, nogil=True, parallel=True)
def _borrow_rows(rows, idx, points, normals, curvature, centroids, thickness, tol, factor, out_n, out_c, out_p):
    """Body of ``borrow_planes`` for the points ``rows`` [C] and their neighbours idx [C, k]: each takes the
    flattest lending patch (the first of equals, in neighbour order) if it is flatter than its own."""
    for r in prange(rows.shape[0]):
        i = rows[r]
        best = -1
        flat = np.inf
        for j in range(idx.shape[1]):
            m = idx[r, j]
            off = abs(np.float64(normals[m, 0]) * (points[i, 0] - centroids[m, 0])
                      + np.float64(normals[m, 1]) * (points[i, 1] - centroids[m, 1])
                      + np.float64(normals[m, 2]) * (points[i, 2] - centroids[m, 2]))
            if off <= 2.0 * np.float64(thickness[m]) + tol:
                c = factor * np.float64(curvature[m])
                if c < flat:
                    flat = c
                    best = m
        if best >= 0 and flat < curvature[i]:
            out_c[i] = flat
            out_n[i, 0] = normals[best, 0]
            out_n[i, 1] = normals[best, 1]
            out_n[i, 2] = normals[best, 2]
            out_p[i, 0] = centroids[best, 0]
            out_p[i, 1] = centroids[best, 1]
            out_p[i, 2] = centroids[best, 2]


@dataclass
class AnchorGeometry:
    """Per-anchor geometric inputs of the field, valid for one layout of the anchor map."""

    normals: torch.Tensor  # [A, 3] unit, towards the anchor's source camera
    curvature: torch.Tensor  # [A]
    spacing: torch.Tensor  # [A] metres
    color_var: torch.Tensor  # [A] V_color
    obs: torch.Tensor  # [A] T
    features: torch.Tensor  # [A, 41] F_in (network-scaled, see the module docstring)
    plane_points: torch.Tensor  # [A, 3] the surface point projected onto its (own or borrowed) patch's plane


def anchor_geometry(amap, camera_centers: dict[int, np.ndarray], k: int, tau: float, cell: float | None = None,
                    borrow: PlaneBorrowing | None = None, curvature_norm: str = "tangent") -> AnchorGeometry:
    """Normals, curvature, spacing, colour variance, track count and F_in of every anchor of ``amap``;
    ``camera_centers`` maps keyframe id -> camera centre [3] (world) to orient the normals."""
    surf = amap.surface.numpy()  # [A, 3]
    normals, curv, spacing, plane = local_geometry(surf, k, amap.surface_n.numpy(), cell, borrow=borrow,
                                                   curvature_norm=curvature_norm)
    # orient towards the camera that created the anchor (grown anchors carry their parent's keyframe)
    src = amap.source_kf.numpy()
    eye = np.zeros_like(surf)
    for kf, c in camera_centers.items():
        eye[src == kf] = c
    flip = np.einsum("ni,ni->n", normals, eye - surf) < 0
    normals[flip] *= -1
    n_t, c_t = torch.from_numpy(normals), torch.from_numpy(curv)
    obs = amap.obs.clone()
    feats = torch.cat([positional_encoding(amap.surface), n_t, (c_t / tau).clamp(max=10.0)[:, None],
                       torch.log1p(obs)[:, None]], dim=1)  # [A, 41]
    return AnchorGeometry(n_t, c_t, torch.from_numpy(spacing), amap.color_variance(), obs, feats,
                          torch.from_numpy(plane.astype(np.float32)))
