"""Local bundle adjustment: a window of covisible keyframes and their landmarks, older observers held fixed."""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from factors.gcgr_linear import labelled_factors
from ggfslam.backend.graph import (
    L, P, X, calibrations, observation_errors, observation_factor, odometry_link_factor, plane_factor,
)
from ggfslam.backend.slam_map import SlamMap
from ggfslam.config import BackendConfig, TrackingConfig
from ggfslam.data.types import Camera


_FIXED_NOISE = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)


# GTSAM's IndeterminantLinearSystemException reaches Python as a bare RuntimeError; its message tells it apart
# from errors raised inside custom factors (a torch or numba failure in a GCGR render), which must propagate
_INDETERMINATE = ("Indeterminate linear system", "Indeterminant linear system")


class IndeterminateSystem(Exception):
    """The linearized system is ill-posed (an under-constrained variable): the optimization did not run."""


def optimize_lm(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, iterations: int) -> gtsam.Values:
    """Levenberg-Marquardt; raises ``IndeterminateSystem`` for an ill-posed system, anything else as raised."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    try:
        return gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    except RuntimeError as e:
        if not any(m in str(e) for m in _INDETERMINATE):
            raise
        raise IndeterminateSystem(" ".join(str(e).split()[:8])) from e


@dataclass
class BAStats:
    """What one bundle adjustment did."""

    keyframes: int
    fixed: int
    landmarks: int
    factors: int
    outliers: int
    error_before: float
    error_after: float
    seconds: float
    plane_factors: int = 0  # plane observations in the graph
    gcgr_factors: int = 0  # GCGR depth + normal factors in the graph
    failed: str = ""  # why the optimization did not run ("": it ran); the map then keeps its estimate


@dataclass
class BAProblem:
    """One bundle adjustment as plain arrays, read from the map under its lock: picklable, so it can be solved in
    another process (``solver_process``) while tracking goes on."""

    camera: Camera
    tcfg: TrackingConfig
    bcfg: BackendConfig
    iterations: int
    window: list[int]  # keyframes optimized (the fixed ones among them hold the gauge)
    fixed: set[int]  # keyframes held by stiff priors
    poses: dict[int, np.ndarray]  # keyframe id -> T_wc [4, 4] of every keyframe in the graph
    lms: np.ndarray  # [L] landmark ids
    positions: np.ndarray  # [L, 3] their world positions
    obs: list[tuple[int, int, int]]  # (keyframe, landmark, keypoint) of each observation factor
    uv: np.ndarray  # [M, 2] keypoint of each observation
    depth: np.ndarray  # [M] its depth (m, 0 = none)
    sigmas: np.ndarray  # [M] its pixel sigma
    links: list  # (keyframe, other keyframe, T_other_keyframe [4, 4]) dense-odometry links
    plane_obs: list  # (keyframe, plane id, camera-frame coefficients [4])
    planes_w: dict  # plane id -> world coefficients [4]
    gcgr: list = field(default_factory=list)  # factors.gcgr_linear.LinearGCGR of optimized keyframes
    generations: np.ndarray | None = None  # [L] the landmarks' slot generations (a slot reused since is passed over)


@dataclass
class BASolution:
    """What a bundle adjustment found (picklable): applied to the map by ``apply_solution``."""

    stats: BAStats
    poses: dict[int, np.ndarray]  # optimized (not fixed) keyframe id -> T_wc [4, 4]
    positions: np.ndarray  # [L] landmarks' new positions [L, 3], in the problem's order
    planes: dict[int, np.ndarray]  # plane id -> world coefficients [4]
    outliers: list[tuple[int, int]]  # (landmark, keyframe) observations to drop


@dataclass
class LocalGraph:
    """The factor graph of one local bundle adjustment and what its outlier pass needs."""

    problem: BAProblem
    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    obs_factors: list  # the observation factors, last in the graph, in the order of problem.obs
    gcgr_labels: dict[int, tuple[int, str]]  # graph index -> (keyframe, kind) of each GCGR factor

    @property
    def window(self) -> list[int]:
        """Keyframes optimized (the fixed ones among them hold the gauge)."""
        return self.problem.window

    @property
    def fixed(self) -> set[int]:
        """Keyframes held by stiff priors."""
        return self.problem.fixed

    @property
    def n_gcgr(self) -> int:
        """GCGR factors in the graph (a depth and a normal one per keyframe that has them)."""
        return len(self.gcgr_labels)


def ba_problem(smap: SlamMap, kf_id: int, camera: Camera, tcfg: TrackingConfig, bcfg: BackendConfig,
               window: list[int] | None = None, iterations: int | None = None) -> BAProblem | None:
    """The local BA around keyframe ``kf_id`` at the map's current estimates; None if too small.

    ``window``: the keyframes to optimize (default: ``kf_id``'s covisible window); keyframes outside it that see
    its landmarks are held fixed, and without any the oldest of the window is."""
    level_scale = tcfg.scale_factor ** np.arange(tcfg.n_levels)
    with smap.lock:  # snapshot, so tracking can go on while the optimizer runs
        if window is None:
            window = smap.local_keyframes(kf_id, bcfg.window, temporal=bcfg.temporal_window)
        else:
            window = [k for k in window if k in smap.keyframes]
        lms = smap.landmarks_of(window)
        obs = []  # (kf, lm, kp)
        for lm in lms:
            for k, kp in smap.observations[lm].items():
                obs.append((k, int(lm), kp))
        plane_obs = []  # (kf, plane id, camera coefficients [4])
        if bcfg.planes:
            pids = {p for k in window for p in smap.keyframes[k].meta.get("plane_ids", [])}
            in_window = set(window)
            for pid in sorted(pids):
                seen = [k for k in sorted(smap.plane_observations[pid]) if k in smap.keyframes]
                outside = [k for k in seen if k not in in_window]
                # a floor seen by every keyframe would put the whole history into each local BA: hold the plane
                # with a few fixed observers spread over its history (the first one anchors it, the last ones
                # keep it locally consistent)
                if len(outside) > bcfg.plane_fixed_observers:
                    pick = np.linspace(0, len(outside) - 1, bcfg.plane_fixed_observers).round().astype(int)
                    outside = [outside[i] for i in np.unique(pick)]
                for k in sorted(set(outside) | (in_window & set(seen))):
                    plane_obs.append((k, pid, smap.plane_observations[pid][k].copy()))
        planes_w = {pid: smap.planes[pid].copy() for _, pid, _ in plane_obs}
        observers = {k for k, _, _ in obs} | {k for k, _, _ in plane_obs}
        fixed = observers - set(window)
        if not fixed:  # the gauge: hold the oldest keyframe so the window cannot drift as a whole
            fixed = {min(window)}
        # dense-odometry links (keyframe, other keyframe, T_other_keyframe) hold textureless keyframes in place
        links = [(k, *smap.keyframes[k].meta["odometry_link"]) for k in window
                 if "odometry_link" in smap.keyframes[k].meta]
        for _, other, _ in links:
            if other not in observers and other not in window:
                fixed.add(other)
        observers |= {other for _, other, _ in links} | set(window)
        poses = {k: smap.keyframes[k].T_wc.copy() for k in observers}
        feats = {k: smap.keyframes[k].features for k in observers}
        positions = smap.positions[lms].copy()
        generations = smap.generation[lms].copy()
    if len(window) - len(fixed & set(window)) < 1 or len(lms) < 10:
        return None
    uv = np.array([feats[k].uv[kp] for k, _, kp in obs], np.float64).reshape(-1, 2)  # [M, 2]
    depth = np.array([feats[k].depth[kp] for k, _, kp in obs], np.float64)  # [M]
    sigmas = tcfg.pixel_sigma * level_scale[np.array([feats[k].octave[kp] for k, _, kp in obs], np.int64)]  # [M]
    return BAProblem(camera, tcfg, bcfg, bcfg.iterations if iterations is None else iterations, window, fixed,
                     poses, lms, positions, obs, uv, depth, sigmas, links, plane_obs, planes_w, generations=generations)


def build_graph(problem: BAProblem, gcgr=None) -> LocalGraph:
    """The GTSAM factor graph of a BA problem; with a ``GCGRSource`` every optimized (not fixed) keyframe also gets
    its GCGR depth and normal factors (rendering this process's map), else the problem's own first-order GCGR
    models give them."""
    pr, tcfg, bcfg = problem, problem.tcfg, problem.bcfg
    mono, stereo = calibrations(pr.camera, tcfg.virtual_baseline)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k, T in pr.poses.items():
        values.insert(X(k), gtsam.Pose3(T))
        if k in pr.fixed:
            # a stiff prior rather than NonlinearEquality: a constrained noise model forces slow QR elimination
            graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(T), _FIXED_NOISE))
    for lm, p in zip(pr.lms, pr.positions):
        values.insert(L(int(lm)), gtsam.Point3(*p))
    for k, other, T_other_k in pr.links:
        graph.add(odometry_link_factor(other, k, T_other_k, tcfg.dense_link_sigmas))
    for pid, pw in pr.planes_w.items():
        values.insert(P(pid), gtsam.OrientedPlane3(*pw))
    for k, pid, z in pr.plane_obs:
        graph.add(plane_factor(k, pid, z, bcfg.plane_sigmas))
    gcgr_labels = {}
    gcgr_factors = labelled_factors(pr.gcgr) if gcgr is None else gcgr.window_factors(optimized_poses(pr))
    for k, kind, f in gcgr_factors:  # before the observations: the outlier pass keeps the graph's head as it is
        gcgr_labels[graph.size()] = (k, kind)
        graph.add(f)
    factors = []
    for (k, lm, _), uv, z, sigma in zip(pr.obs, pr.uv, pr.depth, pr.sigmas):
        factor = observation_factor(k, lm, uv, z, sigma, mono, stereo, bcfg.huber_stereo, bcfg.huber_mono)
        graph.add(factor)
        factors.append(factor)
    return LocalGraph(pr, graph, values, factors, gcgr_labels)


def optimized_poses(problem: BAProblem) -> dict[int, np.ndarray]:
    """Keyframe id -> T_wc [4, 4] of the keyframes a BA problem optimizes (in its window, not fixed)."""
    return {k: problem.poses[k] for k in problem.window if k not in problem.fixed}


def local_graph(smap: SlamMap, kf_id: int, camera: Camera, tcfg: TrackingConfig, bcfg: BackendConfig,
                gcgr=None, window: list[int] | None = None, iterations: int | None = None) -> LocalGraph | None:
    """The local BA graph around keyframe ``kf_id`` at the map's current estimates (``ba_problem``, ``build_graph``);
    None if too small."""
    problem = ba_problem(smap, kf_id, camera, tcfg, bcfg, window, iterations)
    return None if problem is None else build_graph(problem, gcgr)


def solve_graph(lg: LocalGraph) -> BASolution:
    """Optimize a local graph with LM and drop outlier observations (whitened error above the chi-square bound, or
    behind the camera), optimizing again without them."""
    t0 = time.perf_counter()
    pr, graph, values, factors = lg.problem, lg.graph, lg.values, lg.obs_factors
    bcfg = pr.bcfg
    err0 = graph.error(values)

    def stats(outliers: int, err1: float, failed: str = "") -> BAStats:
        return BAStats(len(pr.window), len(pr.fixed), len(pr.lms), len(pr.obs), outliers, err0, err1,
                       time.perf_counter() - t0, len(pr.plane_obs), lg.n_gcgr, failed)

    try:
        result = optimize_lm(graph, values, pr.iterations)
    except IndeterminateSystem as e:  # e.g. a landmark seen once without depth: keep the old estimate
        return BASolution(stats(0, err0, f"indeterminate system: {e}"), {}, pr.positions, {}, [])
    kf_of = np.array([k for k, _, _ in pr.obs], dtype=np.int64)  # [M]
    lm_of = np.array([lm for _, lm, _ in pr.obs], dtype=np.int64)  # [M]
    T_now = {k: result.atPose3(X(k)).matrix() for k in set(kf_of.tolist())}
    _, chi2 = observation_errors(np.stack([T_now[k] for k in kf_of]).reshape(-1, 4, 4),
                                 np.array([result.atPoint3(L(int(lm))) for lm in lm_of]).reshape(-1, 3),
                                 pr.uv, pr.depth, pr.sigmas, pr.camera, pr.tcfg.virtual_baseline,
                                 bcfg.huber_stereo, bcfg.huber_mono)
    keep = chi2 <= np.where(pr.depth > 0, bcfg.outlier_chi2_stereo, bcfg.outlier_chi2_mono)  # [M]
    outliers = [(int(lm_of[i]), int(kf_of[i])) for i in np.nonzero(~keep)[0]]
    if outliers:
        # optimize again without them: even Huber-weighted, a gross mismatch drags its landmark off (ORB-SLAM does the same)
        clean = gtsam.NonlinearFactorGraph()
        for i in range(graph.size() - len(factors)):
            clean.add(graph.at(i))
        for factor, ok in zip(factors, keep):
            if ok:
                clean.add(factor)
        graph = clean
        try:
            result = optimize_lm(graph, result, max(pr.iterations // 2, 3))
        except IndeterminateSystem:  # removing the outliers left a variable free: keep the first solution
            pass
    err1 = graph.error(result)
    poses = {k: result.atPose3(X(k)).matrix() for k in pr.window if k not in pr.fixed}
    positions = np.array([result.atPoint3(L(int(lm))) for lm in pr.lms]).reshape(-1, 3)  # [L, 3]
    planes = {pid: result.atOrientedPlane3(P(pid)).planeCoefficients() for pid in pr.planes_w}
    return BASolution(stats(len(outliers), err1), poses, positions, planes, outliers)


def solve(problem: BAProblem) -> BASolution:
    """Build and solve a BA problem, with its first-order GCGR models if it has them (what the solver process runs)."""
    return solve_graph(build_graph(problem))


def apply_solution(smap: SlamMap, problem: BAProblem, sol: BASolution) -> None:
    """Write a solution into the map: keyframes and planes moved, landmarks still alive moved, outlier observations
    dropped (tracking may have changed the map meanwhile: keyframes and landmarks it removed are passed over)."""
    if sol.stats.failed:
        return
    with smap.lock:
        for k, T in sol.poses.items():
            if k in smap.keyframes:
                smap.keyframes[k].T_wc = T
        same = smap.alive[problem.lms]  # [L] still alive and (below) still the same landmark
        if problem.generations is not None:
            same &= smap.generation[problem.lms] == problem.generations
        smap.positions[problem.lms[same]] = sol.positions[same]
        unchanged = set(problem.lms[same].tolist())
        for lm, k in sol.outliers:
            if lm in unchanged:
                smap.remove_observation(lm, k)
        for pid, coeffs in sol.planes.items():
            smap.planes[pid] = coeffs


def local_bundle_adjustment(smap: SlamMap, kf_id: int, camera: Camera, tcfg: TrackingConfig,
                            bcfg: BackendConfig, gcgr=None, window: list[int] | None = None,
                            iterations: int | None = None, solver=None) -> BAStats | None:
    """Optimize the window around keyframe ``kf_id`` (or ``window``, see ``ba_problem``) with LM for
    ``iterations`` (default ``backend.iterations``), drop outlier observations and write the result into the map;
    None if too small.

    With a ``GCGRSource`` every optimized (not fixed) keyframe also gets its GCGR depth and normal factors. With a
    ``solver`` (``solver_process.SolverProcess``) the problem is solved in its process (``solve_with_gcgr`` with
    GCGR), else in this one."""
    t0 = time.perf_counter()
    if solver is not None:
        problem = ba_problem(smap, kf_id, camera, tcfg, bcfg, window, iterations)
        if problem is None:
            return None
        sol = solver.solve(problem) if gcgr is None else solve_with_gcgr(problem, gcgr, solver.solve)
    else:
        lg = local_graph(smap, kf_id, camera, tcfg, bcfg, gcgr, window, iterations)
        if lg is None:
            return None
        problem, sol = lg.problem, solve_graph(lg)
    apply_solution(smap, problem, sol)
    sol.stats.seconds = time.perf_counter() - t0  # snapshot, graph and write-back included, as before
    return sol.stats


def solve_with_gcgr(problem: BAProblem, gcgr, solve) -> BASolution:
    """A BA problem with the GCGR models of ``gcgr`` (a ``GCGRSource``) solved by ``solve`` (another process's):
    the models travel as their first-order models (``LinearGCGR``); keyframes the solution moved past the
    relinearization threshold render again there and the problem is solved once more from that solution (what
    the models do by themselves at LM's linearizations when the BA runs in this process)."""
    models = gcgr.window_models(optimized_poses(problem))
    problem.gcgr = [m.frozen() for m in models]
    sol = solve(problem)
    moved = [m for m in models if m.relinearizes and m.key in sol.poses and m.moved_past(sol.poses[m.key])]
    if sol.stats.failed or not moved:
        return sol
    for m in moved:
        m.relinearize(sol.poses[m.key])
    gcgr.ba_relinearized += 1
    again = solve(continued_problem(problem, sol, [m.frozen() for m in models]))
    if again.stats.failed:
        return sol
    again.stats.error_before = sol.stats.error_before
    again.outliers = sol.outliers + again.outliers
    again.stats.outliers = len(again.outliers)
    return again


def continued_problem(problem: BAProblem, sol: BASolution, gcgr: list) -> BAProblem:
    """The problem again, started from ``sol`` (its outlier observations dropped), with the GCGR models ``gcgr``."""
    dropped = set(sol.outliers)  # (landmark, keyframe)
    keep = np.array([(lm, k) not in dropped for k, lm, _ in problem.obs], bool)  # [M]
    return dataclasses.replace(
        problem, poses={**problem.poses, **sol.poses}, positions=sol.positions.copy(),
        obs=[o for o, ok in zip(problem.obs, keep) if ok], uv=problem.uv[keep], depth=problem.depth[keep],
        sigmas=problem.sigmas[keep], planes_w={**problem.planes_w, **sol.planes}, gcgr=gcgr)


def global_bundle_adjustment(smap: SlamMap, camera: Camera, tcfg: TrackingConfig, bcfg: BackendConfig,
                             gcgr=None, solver=None) -> BAStats | None:
    """Bundle-adjust every keyframe and landmark, the oldest keyframe held (after a loop closure, at the end), with
    the GCGR factors of ``gcgr`` (a ``GCGRSource``) when given, else in ``solver``'s process when given."""
    with smap.lock:
        every = sorted(smap.keyframes)
    if len(every) < 2:
        return None
    return local_bundle_adjustment(smap, every[-1], camera, tcfg, bcfg, gcgr=gcgr, window=every,
                                   iterations=bcfg.global_ba_iterations, solver=solver)
