"""Pose-graph optimisation over keyframe poses (GTSAM), and moving map points with their keyframes.

Nodes are keyframe poses T_wc; edges are relative-pose measurements ``T_ij = inv(T_wi) @ T_wj`` from
odometry, covisibility (e.g. relative poses after bundle adjustment) and loop closures. Loop edges may be
wrong (perceptual aliasing), so with ``robust=True`` they get a robust kernel: the graph is first solved
with the kernel, loop edges still far from agreeing with the solution are dropped, and the graph is solved
again by plain least squares from there, so accepted loops act with their full weight.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import gtsam
import numpy as np

from ggfslam.geometry.se3 import from_gtsam, invert, rigidity_error, to_gtsam

__all__ = ["EDGE_KINDS", "PoseEdge", "PoseGraphResult", "optimize_pose_graph", "solve_pose_graph", "correct_points"]

EDGE_KINDS = ("odometry", "covisibility", "loop")
_CHI2_6DOF_999 = 22.458  # 99.9% quantile of chi-square with 6 degrees of freedom


@dataclass
class PoseEdge:
    """Relative-pose measurement between keyframes i and j: T_ij = inv(T_wi) @ T_wj [4, 4].

    Noise is on xi = [omega, v] in T_ij * Exp(xi) (GTSAM's BetweenFactor): ``sigmas_rot`` (rad) and
    ``sigmas_trans`` (m), each a scalar or 3 values, or a full ``covariance`` [6, 6] that overrides them
    (e.g. ``LoopResult.covariance``).
    """

    i: int
    j: int
    T_ij: np.ndarray  # [4, 4]
    sigmas_rot: float | Sequence[float] = 0.01
    sigmas_trans: float | Sequence[float] = 0.01
    kind: str = "odometry"
    covariance: np.ndarray | None = None  # [6, 6], [omega, v] order

    def noise_model(self) -> gtsam.noiseModel.Base:
        """Gaussian GTSAM noise model of the edge (before any robust kernel)."""
        if self.covariance is not None:
            cov = np.asarray(self.covariance, np.float64)
            if cov.shape != (6, 6) or not np.all(np.isfinite(cov)):
                raise ValueError(f"edge {self.i}->{self.j}: covariance must be a finite 6x6 matrix")
            return gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov + cov.T))
        rot = np.broadcast_to(np.asarray(self.sigmas_rot, np.float64), (3,))
        trans = np.broadcast_to(np.asarray(self.sigmas_trans, np.float64), (3,))
        sigmas = np.concatenate([rot, trans])
        if not np.all(np.isfinite(sigmas)) or np.any(sigmas <= 0):
            raise ValueError(f"edge {self.i}->{self.j}: sigmas must be positive and finite, got {sigmas.tolist()}")
        return gtsam.noiseModel.Diagonal.Sigmas(sigmas)


@dataclass
class PoseGraphResult:
    """Optimised poses and what the optimiser did."""

    poses: dict[int, np.ndarray]  # id -> T_wc [4, 4]
    error_before: float  # GTSAM graph error (0.5 * sum of squared whitened residuals) at the start
    error_after: float  # the same at the end (plain least squares, rejected loops left out)
    iterations: int  # LM iterations over all solves
    rejected_loops: list[int] = field(default_factory=list)  # indices into ``edges`` of dropped loop edges
    anchored_ids: set[int] = field(default_factory=set)  # poses held fixed (given, or added per component)


def _key(kf_id: int) -> int:
    return gtsam.symbol("x", int(kf_id))


def _robust(model: gtsam.noiseModel.Base, kernel: str, param: float) -> gtsam.noiseModel.Base:
    """Wrap a noise model with a Huber or Cauchy kernel (on the whitened error)."""
    if kernel == "huber":
        est = gtsam.noiseModel.mEstimator.Huber.Create(param)
    elif kernel == "cauchy":
        est = gtsam.noiseModel.mEstimator.Cauchy.Create(param)
    else:
        raise ValueError(f"unknown robust kernel {kernel!r}; expected 'huber' or 'cauchy'")
    return gtsam.noiseModel.Robust.Create(est, model)


def _components(ids: list[int], edges: list[PoseEdge]) -> list[list[int]]:
    """Connected components (sorted id lists) of the graph."""
    parent = {i: i for i in ids}

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for e in edges:
        ra, rb = find(e.i), find(e.j)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    groups: dict[int, list[int]] = {}
    for i in ids:
        groups.setdefault(find(i), []).append(i)
    return [sorted(g) for g in groups.values()]


def _solve(poses: dict[int, np.ndarray], edges: list[PoseEdge], models: list, anchored: set[int],
           max_iterations: int) -> tuple[gtsam.Values, float, float, int]:
    """One LM solve; returns (values, error before, error after, iterations)."""
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k, T in poses.items():
        values.insert(_key(k), to_gtsam(T))
        if k in anchored:
            graph.add(gtsam.NonlinearEqualityPose3(_key(k), to_gtsam(T)))  # hard constraint: exactly fixed
    for e, model in zip(edges, models):
        graph.add(gtsam.BetweenFactorPose3(_key(e.i), _key(e.j), to_gtsam(e.T_ij), model))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(max_iterations))
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-12)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    return result, float(graph.error(values)), float(graph.error(result)), int(optimizer.iterations())


def solve_pose_graph(poses: dict[int, np.ndarray], edges: list[PoseEdge], fixed_ids: set[int] | None = None,
                     robust: bool = True, robust_kernel: str = "cauchy", robust_param: float = 3.0,
                     outlier_chi2: float = _CHI2_6DOF_999, max_iterations: int = 100) -> PoseGraphResult:
    """Optimise keyframe poses T_wc [4, 4] under relative-pose edges with Levenberg-Marquardt (GTSAM).

    ``fixed_ids`` stay exactly where they are; a connected component without a fixed pose gets its
    smallest id fixed (a pose graph is only defined up to one rigid motion per component). With
    ``robust``, loop edges get the robust kernel; after that solve, loop edges whose squared whitened
    error exceeds ``outlier_chi2`` are rejected, and the rest is solved again without the kernel.
    """
    poses = {int(k): np.asarray(T, np.float64) for k, T in poses.items()}
    for k, T in poses.items():
        err = rigidity_error(T)
        if err is not None:
            raise ValueError(f"pose {k}: {err}")
    for n, e in enumerate(edges):
        if e.i not in poses or e.j not in poses:
            raise ValueError(f"edge {n} ({e.kind}) joins {e.i} -> {e.j}, but pose {e.j if e.i in poses else e.i} "
                             "is not in the graph")
        if e.kind not in EDGE_KINDS:
            raise ValueError(f"edge {n}: unknown kind {e.kind!r}; expected one of {', '.join(EDGE_KINDS)}")
        err = rigidity_error(e.T_ij)
        if err is not None:
            raise ValueError(f"edge {n} ({e.i} -> {e.j}): {err}")
    fixed = {int(k) for k in (fixed_ids or set())}
    unknown = fixed - set(poses)
    if unknown:
        raise ValueError(f"fixed ids not in the graph: {sorted(unknown)}")
    anchored = set(fixed)
    for comp in _components(sorted(poses), edges):
        if not anchored.intersection(comp):
            anchored.add(comp[0])
    if not edges:
        return PoseGraphResult({k: T.copy() for k, T in poses.items()}, 0.0, 0.0, 0, [], anchored)

    base = [e.noise_model() for e in edges]
    use_kernel = robust and any(e.kind == "loop" for e in edges)
    models = [_robust(m, robust_kernel, robust_param) if use_kernel and e.kind == "loop" else m
              for e, m in zip(edges, base)]
    values, err0, err1, iters = _solve(poses, edges, models, anchored, max_iterations)
    rejected: list[int] = []
    if use_kernel:
        for n, e in enumerate(edges):
            if e.kind != "loop":
                continue
            factor = gtsam.BetweenFactorPose3(_key(e.i), _key(e.j), to_gtsam(e.T_ij), base[n])
            if 2.0 * factor.error(values) > outlier_chi2:  # error() is half the squared whitened residual
                rejected.append(n)
        keep = [n for n in range(len(edges)) if n not in set(rejected)]
        start = {k: from_gtsam(values.atPose3(_key(k))) for k in poses}
        values, _, err1, it2 = _solve(start, [edges[n] for n in keep], [base[n] for n in keep], anchored,
                                      max_iterations)
        iters += it2
    out = {k: from_gtsam(values.atPose3(_key(k))) for k in poses}
    for k in anchored:  # bit-exact: the constraint holds them, this removes float round trips
        out[k] = poses[k].copy()
    return PoseGraphResult(out, err0, err1, iters, rejected, anchored)


def optimize_pose_graph(poses: dict[int, np.ndarray], edges: list[PoseEdge], fixed_ids: set[int] | None = None,
                        robust: bool = True, **kwargs) -> dict[int, np.ndarray]:
    """Optimised poses {id: T_wc [4, 4]} of a pose graph (see ``solve_pose_graph`` for the options)."""
    return solve_pose_graph(poses, edges, fixed_ids, robust, **kwargs).poses


def correct_points(points_w: np.ndarray, ref_ids: np.ndarray, old_poses: dict[int, np.ndarray],
                   new_poses: dict[int, np.ndarray]) -> np.ndarray:
    """Move world points [P, 3] rigidly with their reference keyframes ref_ids [P]: p' = T_new inv(T_old) p.

    Points whose keyframe is missing from either dict (or ref id < 0) stay where they are.
    """
    pts = np.asarray(points_w, np.float64).reshape(-1, 3)
    ref = np.asarray(ref_ids).reshape(-1)
    if len(ref) != len(pts):
        raise ValueError(f"ref_ids has {len(ref)} entries for {len(pts)} points")
    out = pts.copy()
    for k in np.unique(ref):
        k = int(k)
        if k < 0 or k not in old_poses or k not in new_poses:
            continue
        M = np.asarray(new_poses[k], np.float64) @ invert(np.asarray(old_poses[k], np.float64))  # [4, 4]
        sel = ref == k
        out[sel] = pts[sel] @ M[:3, :3].T + M[:3, 3]
    return out
