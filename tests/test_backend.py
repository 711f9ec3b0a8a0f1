"""GTSAM backend: the RGB-D observation factor and local bundle adjustment on a hand-built map."""
import logging

import gtsam
import numpy as np
import pytest
from gtsam.utils.numerical_derivative import numericalDerivative21, numericalDerivative22
from scipy.spatial.transform import Rotation

from factors.gcgr_linear import LinearGCGR, labelled_factors
from ggfslam.backend import local_ba
from ggfslam.backend.backend import Backend
from ggfslam.backend.graph import L, X, calibrations, observation_factor
from ggfslam.backend.local_ba import global_bundle_adjustment, local_bundle_adjustment
from ggfslam.backend.slam_map import KeyFrame, SlamMap
from ggfslam.config import BackendConfig, GCGRConfig, TrackingConfig
from ggfslam.data.types import Camera
from ggfslam.frontend.features import Features, backproject_points
from ggfslam.geometry.se3 import invert, make_pose

CAM = Camera(300.0, 300.0, 159.5, 119.5, 320, 240, 5000.0)
TCFG = TrackingConfig()


def test_rgbd_factor_zero_at_truth_and_jacobians_match_numerical():
    mono, stereo = calibrations(CAM, TCFG.virtual_baseline)
    T = make_pose(Rotation.from_euler("xyz", [5, -3, 10], degrees=True).as_matrix(), [0.2, -0.1, 0.3])
    p_c = np.array([0.3, -0.2, 2.5])
    p_w = T[:3, :3] @ p_c + T[:3, 3]
    uv = np.array([CAM.fx * p_c[0] / p_c[2] + CAM.cx, CAM.fy * p_c[1] / p_c[2] + CAM.cy])
    for depth in (p_c[2], 0.0):  # with depth: 3-D stereo residual; without: 2-D projection
        f = observation_factor(0, 1, uv, depth, 1.0, mono, stereo, 2.8, 2.4)
        v = gtsam.Values()
        v.insert(X(0), gtsam.Pose3(T))
        v.insert(L(1), gtsam.Point3(*p_w))
        np.testing.assert_allclose(f.unwhitenedError(v), 0, atol=1e-9)
        pose, point = gtsam.Pose3(T).retract(np.full(6, 0.01)), gtsam.Point3(*(p_w + 0.02))
        if depth > 0:
            cam = lambda P, Q: gtsam.StereoCamera(P, stereo).project(Q).vector()  # noqa: E731
        else:
            cam = lambda P, Q: gtsam.PinholeCameraCal3_S2(P, mono).project(Q)  # noqa: E731
        H_pose = numericalDerivative21(cam, pose, point)
        H_point = numericalDerivative22(cam, pose, point)
        v2 = gtsam.Values()
        v2.insert(X(0), pose)
        v2.insert(L(1), point)
        lin = f.linearize(v2)
        A = lin.jacobian()[0]
        # the linear factor is whitened by the noise model (unit sigma) and the robust kernel's weight
        w = np.sqrt(f.noiseModel().robust().weight(np.linalg.norm(f.unwhitenedError(v2))))
        np.testing.assert_allclose(A[:, :6], w * H_pose, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(A[:, 6:9], w * H_point, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("baseline", [0.08, 0.5])
def test_rgbd_factor_depth_sigma_is_pixel_sigma_times_z2_over_fb(baseline):
    """The depth noise a virtual baseline stands for (``TrackingConfig.virtual_baseline``): a landmark moved by dz
    along the keypoint's ray costs a whitened error of dz f b / (z^2 sigma) (first order), nothing in u or v."""
    mono, stereo = calibrations(CAM, baseline)
    sigma, z = 1.5, 2.0
    ray = np.array([0.25, -0.1, 1.0])
    uv = np.array([CAM.fx * ray[0] + CAM.cx, CAM.fy * ray[1] + CAM.cy])
    f = observation_factor(0, 1, uv, z, sigma, mono, stereo, 1e6, 1e6)  # no robust down-weighting
    for dz in (-2e-3, 1e-3):
        v = gtsam.Values()
        v.insert(X(0), gtsam.Pose3())
        v.insert(L(1), gtsam.Point3(*(ray * (z + dz))))
        e = f.whitenedError(v)  # [uL, uR, v] / sigma
        np.testing.assert_allclose(e[[0, 2]], 0, atol=1e-9)
        expected = CAM.fx * baseline * dz / (z * (z + dz)) / sigma  # exact: f b (1/z - 1/(z + dz))
        np.testing.assert_allclose(abs(e[1]), abs(expected), rtol=1e-9)
        np.testing.assert_allclose(abs(e[1]), abs(dz) * CAM.fx * baseline / (z * z * sigma), rtol=2e-3)


def _build_map(rng, n_kf=4, n_pts=400):
    """Keyframes moving along x looking at a wall of points; exact observations from the true poses."""
    smap = SlamMap()
    truth = [make_pose(Rotation.from_euler("y", 2 * k, degrees=True).as_matrix(), [0.1 * k, 0.0, 0.0])
             for k in range(n_kf)]
    pts = np.column_stack([rng.uniform(-1.5, 1.8, n_pts), rng.uniform(-1, 1, n_pts), rng.uniform(2.5, 4.0, n_pts)])
    desc = rng.integers(0, 256, (n_pts, 32), dtype=np.uint8)
    kfs = []
    for k, T in enumerate(truth):
        p_c = pts @ invert(T)[:3, :3].T + invert(T)[:3, 3]
        uv = np.column_stack([CAM.fx * p_c[:, 0] / p_c[:, 2] + CAM.cx, CAM.fy * p_c[:, 1] / p_c[:, 2] + CAM.cy])
        feats = Features(uv, np.zeros(n_pts, np.int64), desc, p_c[:, 2].copy(), backproject_points(uv, p_c[:, 2], CAM))
        kf = KeyFrame(k, 10 * k, float(k), T.copy(), feats, np.full(n_pts, -1, np.int64))
        smap.add_keyframe(kf)
        kfs.append(kf)
    smap.add_landmarks(pts.copy(), desc, kfs[0], np.arange(n_pts))
    for kf in kfs[1:]:
        for i in range(n_pts):
            smap.add_observation(i, kf, i)
    return smap, truth, pts


def test_local_ba_recovers_perturbed_poses_and_points_and_drops_outliers():
    rng = np.random.default_rng(0)
    smap, truth, pts = _build_map(rng)
    for k in (1, 2, 3):  # keyframe 0 is the gauge
        smap.keyframes[k].T_wc = truth[k] @ make_pose(Rotation.from_rotvec(rng.normal(scale=0.01, size=3)).as_matrix(),
                                                      rng.normal(scale=0.02, size=3))
    smap.positions[: len(pts)] += rng.normal(scale=0.01, size=pts.shape)
    bad = 7
    smap.keyframes[3].features.uv[bad] += 30.0  # one gross mismatch
    stats = local_bundle_adjustment(smap, 3, CAM, TCFG, BackendConfig(window=8, iterations=20))
    assert stats is not None and stats.error_after < 1e-3 * stats.error_before  # after: without the outlier
    for k in (1, 2, 3):
        d = invert(truth[k]) @ smap.keyframes[k].T_wc
        assert np.linalg.norm(d[:3, 3]) < 1e-3 and Rotation.from_matrix(d[:3, :3]).magnitude() < 1e-3
    assert np.abs(smap.positions[: len(pts)] - pts).max() < 5e-3
    assert 3 not in smap.observations[bad] and smap.keyframes[3].landmark_ids[bad] == -1
    assert stats.outliers == 1


class _RaisingGCGR:
    """A GCGR source whose factor fails inside the optimizer, as a torch or numba error in a render would."""

    def window_factors(self, poses):
        def error(this, values, H=None):
            if H is None:  # the error alone evaluates; the Jacobian's render fails (inside the optimizer)
                return np.zeros(1)
            raise RuntimeError("numba: failed to render the GCGR view")

        k = max(poses)
        return [(k, "depth", gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(1), [X(k)], error))]


def test_an_error_inside_a_factor_propagates_out_of_local_ba():
    smap, _, _ = _build_map(np.random.default_rng(1))
    with pytest.raises(RuntimeError, match="failed to render the GCGR view"):
        local_bundle_adjustment(smap, 3, CAM, TCFG, BackendConfig(window=8, iterations=5), _RaisingGCGR())


def test_an_indeterminate_system_is_counted_logged_once_and_keeps_the_estimate(monkeypatch, caplog):
    smap, truth, _ = _build_map(np.random.default_rng(2))

    class Indeterminate:
        def __init__(self, *a):
            pass

        def optimize(self):
            raise RuntimeError("\nIndeterminate linear system detected while working near variable\n7 (Symbol: x7).")

    monkeypatch.setattr(local_ba.gtsam, "LevenbergMarquardtOptimizer", Indeterminate)
    before = {k: kf.T_wc.copy() for k, kf in smap.keyframes.items()}
    stats = local_bundle_adjustment(smap, 3, CAM, TCFG, BackendConfig(window=8, iterations=5))
    assert stats.failed.startswith("indeterminate system") and "variable" in stats.failed
    assert all(np.array_equal(kf.T_wc, before[k]) for k, kf in smap.keyframes.items())
    # the backend counts every failure in metrics.json and logs the first one only
    backend = Backend(CAM, TCFG, BackendConfig(loop_closure=False, fusion=False, planes=False))
    backend.map = smap
    with caplog.at_level(logging.WARNING, logger="ggfslam.backend"):
        backend._process(3)
        backend._process(2)
    summary = backend.summary()
    assert summary["ba_failed"] == 2 and summary["ba_runs"] == 0
    assert summary["ba_first_failure"].startswith("keyframe 3: indeterminate system")
    assert sum("local BA skipped" in r.getMessage() for r in caplog.records) == 1


def test_global_ba_optimizes_every_keyframe_with_the_oldest_held():
    rng = np.random.default_rng(3)
    smap, truth, pts = _build_map(rng, n_kf=6)
    for k in range(1, 6):
        smap.keyframes[k].T_wc = truth[k] @ make_pose(Rotation.from_rotvec(rng.normal(scale=0.01, size=3)).as_matrix(),
                                                      rng.normal(scale=0.02, size=3))
    stats = global_bundle_adjustment(smap, CAM, TCFG, BackendConfig(global_ba_iterations=20))
    assert stats.keyframes == 6 and stats.fixed == 1 and not stats.failed
    np.testing.assert_array_equal(smap.keyframes[0].T_wc, truth[0])
    for k in range(1, 6):
        d = invert(truth[k]) @ smap.keyframes[k].T_wc
        assert np.linalg.norm(d[:3, 3]) < 1e-3 and Rotation.from_matrix(d[:3, :3]).magnitude() < 1e-3


def _perturbed_map(seed):
    rng = np.random.default_rng(seed)
    smap, truth, pts = _build_map(rng)
    for k in (1, 2, 3):
        smap.keyframes[k].T_wc = truth[k] @ make_pose(Rotation.from_rotvec(rng.normal(scale=0.01, size=3)).as_matrix(),
                                                      rng.normal(scale=0.02, size=3))
    smap.positions[: len(pts)] += rng.normal(scale=0.01, size=pts.shape)
    smap.keyframes[3].features.uv[7] += 30.0  # one gross mismatch
    return smap


def test_the_solver_process_gives_the_same_bundle_adjustment_as_this_process():
    from ggfslam.backend.solver_process import SolverProcess

    cfg = BackendConfig(window=8, iterations=20)
    here, there = _perturbed_map(5), _perturbed_map(5)
    s_here = local_bundle_adjustment(here, 3, CAM, TCFG, cfg)
    solver = SolverProcess()
    try:
        s_there = local_bundle_adjustment(there, 3, CAM, TCFG, cfg, solver=solver)
        assert solver.solved == 1 and solver.alive
    finally:
        solver.close()
    assert not solver.alive
    assert (s_there.outliers, s_there.landmarks, s_there.keyframes) == (s_here.outliers, s_here.landmarks, s_here.keyframes)
    assert s_there.error_after == pytest.approx(s_here.error_after, rel=1e-9, abs=1e-12)
    for k in here.keyframes:
        np.testing.assert_allclose(there.keyframes[k].T_wc, here.keyframes[k].T_wc, atol=1e-12)
    np.testing.assert_allclose(there.positions, here.positions, atol=1e-12)
    assert 3 not in there.observations[7]  # the outlier found in the child is dropped from this map


class _Pull(LinearGCGR):
    """A stand-in for a keyframe's GCGR model: rows W Log(T_target^-1 T) [32], linearized where it last rendered;
    ``relinearize`` is its render (recorded)."""

    relinearizes = True

    def __init__(self, key, target, T0, relinearize_translation):
        cfg = GCGRConfig(sigma=0.002, relinearize_rotation=1000 * relinearize_translation,
                         relinearize_translation=relinearize_translation)  # 1 mm : 1 degree
        self.target, self.rendered_at = target, []
        self.W = np.random.default_rng(key).normal(size=(32, 6))  # [32, 6]
        super().__init__(key, T0, *self._rows(T0), cfg)

    def _rows(self, T_wc):
        r = self.W @ gtsam.Pose3(self.target).localCoordinates(gtsam.Pose3(np.asarray(T_wc, np.float64)))  # [32]
        return {"depth": r, "normal": 0.1 * r}, {"depth": self.W, "normal": 0.1 * self.W}

    def relinearize(self, T_wc):
        self.rendered_at.append(np.array(T_wc))
        self.T0 = gtsam.Pose3(np.asarray(T_wc, np.float64))
        self.rows0, self.jacobians = self._rows(T_wc)


class _Source:
    """What local BA asks of a ``GCGRSource``."""

    def __init__(self, models):
        self.models, self.ba_relinearized = models, 0

    def window_models(self, poses):
        return [m for m in self.models if m.key in poses]

    def window_factors(self, poses):
        return labelled_factors(self.window_models(poses))


def _pulled_map(seed, relinearize_translation):
    """The perturbed map with GCGR stand-ins pulling keyframes 1-3 2 cm sideways of where they are."""
    smap = _perturbed_map(seed)
    shift = make_pose(np.eye(3), [0.0, 0.02, 0.0])
    models = [_Pull(k, smap.keyframes[k].T_wc @ shift, smap.keyframes[k].T_wc, relinearize_translation) for k in (1, 2, 3)]
    return smap, _Source(models)


def test_gcgr_bundle_adjustment_in_the_solver_process_matches_this_process_and_relinearizes():
    from ggfslam.backend.solver_process import SolverProcess

    cfg = BackendConfig(window=8, iterations=20)
    here, src_here = _pulled_map(5, relinearize_translation=1.0)  # a threshold never passed: no renders
    s_here = local_bundle_adjustment(here, 3, CAM, TCFG, cfg, gcgr=src_here)
    solver = SolverProcess()
    try:
        there, src_there = _pulled_map(5, relinearize_translation=1.0)
        s_there = local_bundle_adjustment(there, 3, CAM, TCFG, cfg, gcgr=src_there, solver=solver)
        # the same problem, but keyframes the first solution moves by over 1 mm (or 1 deg) render again there and it is solved
        # once more from that solution
        again, src_again = _pulled_map(5, relinearize_translation=0.001)
        ref, src_ref = _pulled_map(5, relinearize_translation=1.0)  # its first solve, in this process
        first = local_ba.solve_with_gcgr(local_ba.ba_problem(ref, 3, CAM, TCFG, cfg), src_ref, local_ba.solve)
        s_again = local_bundle_adjustment(again, 3, CAM, TCFG, cfg, gcgr=src_again, solver=solver)
        assert solver.solved == 3 and solver.alive  # one problem, then one solved twice
    finally:
        solver.close()
    assert s_there.gcgr_factors == s_here.gcgr_factors == 6 and src_there.ba_relinearized == 0
    assert (s_there.outliers, s_there.landmarks) == (s_here.outliers, s_here.landmarks)
    assert s_there.error_after == pytest.approx(s_here.error_after, rel=1e-9, abs=1e-12)
    for k in here.keyframes:
        np.testing.assert_allclose(there.keyframes[k].T_wc, here.keyframes[k].T_wc, atol=1e-12)
    np.testing.assert_allclose(there.positions, here.positions, atol=1e-12)
    assert 3 not in there.observations[7]
    # relinearized: each moved keyframe rendered once, at the first solution; the outlier of the first solve stays out
    assert src_again.ba_relinearized == 1 and s_again.outliers == s_there.outliers
    assert s_again.error_before == pytest.approx(s_there.error_before, rel=1e-12)
    moved = {m.key: m.rendered_at for m in src_again.models if m.rendered_at}
    assert moved and all(len(r) == 1 for r in moved.values())
    for k, (T,) in moved.items():
        np.testing.assert_allclose(T, first.poses[k], atol=1e-12)
        assert not np.allclose(again.keyframes[k].T_wc, first.poses[k], atol=1e-9)  # solved again from there
    assert 3 not in again.observations[7]


def test_a_dead_solver_process_falls_back_to_this_process_with_one_warning(caplog):
    from ggfslam.backend.solver_process import SolverProcess

    cfg = BackendConfig(window=8, iterations=20)
    solver = SolverProcess()
    solver._proc.kill()
    solver._proc.wait()
    smap = _perturbed_map(6)
    with caplog.at_level(logging.WARNING, logger="ggfslam.backend"):
        stats = local_bundle_adjustment(smap, 3, CAM, TCFG, cfg, solver=solver)
        local_bundle_adjustment(smap, 3, CAM, TCFG, cfg, solver=solver)
    assert stats is not None and stats.outliers >= 1 and stats.error_after < 1e-3 * stats.error_before
    assert solver.solved == 0
    assert "solver process ended (exit code -9" in solver.fallback
    assert sum("solved in the tracking process" in r.message for r in caplog.records) == 1
    solver.close()


def test_an_error_in_the_solver_process_is_raised_with_its_traceback():
    from ggfslam.backend.local_ba import ba_problem
    from ggfslam.backend.solver_process import SolverError, SolverProcess

    problem = ba_problem(_perturbed_map(7), 3, CAM, TCFG, BackendConfig(window=8, iterations=5))
    problem.uv = problem.uv[:5]  # observations without keypoints: the child's graph building fails
    solver = SolverProcess()
    try:
        with pytest.raises(SolverError, match="Traceback"):
            solver.solve(problem)
        assert solver.alive  # and it goes on serving
    finally:
        solver.close()


def test_a_concurrent_backend_solves_in_its_process_and_stops_it_when_finished():
    smap = _perturbed_map(8)
    cfg = BackendConfig(window=8, iterations=20, concurrent=True, loop_closure=False, fusion=False, planes=False)
    backend = Backend(CAM, TCFG, cfg)
    backend.map = smap
    assert backend._solver is not None and backend._solver.alive
    proc = backend._solver._proc
    backend.insert_keyframe(smap.keyframes[3])
    backend.finish()
    assert proc.poll() == 0  # ended on its own when its input closed
    s = backend.summary()
    assert s["ba_runs"] == 1 and s["solved_in_process"] == 1 and "solver_fallback" not in s
    assert backend.stats.outliers_removed == 1


def test_the_solver_process_solves_pose_graphs_like_this_process():
    from ggfslam.backend.pose_graph import PoseEdge, optimize_pose_graph
    from ggfslam.backend.solver_process import SolverProcess

    rng = np.random.default_rng(9)
    truth = {k: make_pose(Rotation.from_euler("z", 20 * k, degrees=True).as_matrix(), [np.cos(k), np.sin(k), 0.0])
             for k in range(8)}
    noisy = {k: T @ make_pose(Rotation.from_rotvec(rng.normal(scale=0.02, size=3)).as_matrix(),
                               rng.normal(scale=0.03, size=3)) for k, T in truth.items()}
    edges = [PoseEdge(a, a + 1, invert(truth[a]) @ truth[a + 1]) for a in range(7)]
    edges.append(PoseEdge(0, 7, invert(truth[0]) @ truth[7], kind="loop"))
    here = optimize_pose_graph(noisy, edges, {0}, True)
    solver = SolverProcess()
    try:
        there = solver.pose_graph(noisy, edges, {0}, True)
    finally:
        solver.close()
    assert solver.solved == 1 and there.keys() == here.keys()
    for k in here:
        np.testing.assert_allclose(there[k], here[k], atol=1e-12)


def test_a_keyframe_made_while_the_loop_is_solved_moves_with_the_one_before_it():
    from ggfslam.backend.loop_closure import LoopResult
    from ggfslam.backend.loop_correction import close_loop

    smap, truth, _ = _build_map(np.random.default_rng(10))
    late = {}
    shift = make_pose(Rotation.from_euler("z", 5, degrees=True).as_matrix(), [0.1, 0.0, 0.0])

    def solve(poses, edges, fixed, robust):  # the pose graph "moves" keyframes 1..3; meanwhile tracking adds 4
        kf3 = smap.keyframes[3]
        kf = KeyFrame(4, 40, 4.0, kf3.T_wc @ make_pose(np.eye(3), [0.1, 0, 0]), kf3.features,
                      np.full(len(kf3.landmark_ids), -1, np.int64))
        smap.add_keyframe(kf)
        late["before"] = kf.T_wc.copy()
        return {k: (T if k == 0 else shift @ T) for k, T in poses.items()}

    loop = LoopResult(3, 0, invert(truth[0]) @ truth[3], 50, np.zeros((0, 2), np.int64), 0.5)
    old3 = smap.keyframes[3].T_wc.copy()
    new = close_loop(smap, loop, solve=solve)
    assert 4 in new
    # its pose relative to keyframe 3 is what it was when it was made
    np.testing.assert_allclose(invert(smap.keyframes[3].T_wc) @ smap.keyframes[4].T_wc,
                               invert(old3) @ late["before"], atol=1e-12)
    np.testing.assert_allclose(smap.keyframes[3].T_wc, shift @ old3, atol=1e-12)
