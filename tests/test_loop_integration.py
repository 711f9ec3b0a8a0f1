"""Loop closure inside the running system: a lap around the synthetic room is detected, closed correctly, and
lowers the trajectory error compared with the same run without loop closure."""
import numpy as np
import pytest

from ggfslam.backend.backend import Backend
from ggfslam.config import BackendConfig, TrackingConfig
from ggfslam.data.synthetic import SyntheticSequence
from ggfslam.eval.trajectory import trajectory_metrics
from ggfslam.frontend.tracker import OrbTracker
from ggfslam.geometry.se3 import invert

FRAMES = list(range(0, 1100, 5))  # one lap of the room, 5 cm between frames


@pytest.fixture(scope="module")
def lap():
    return SyntheticSequence(n_frames=1100, width=320, height=240, trajectory="orbit", seed=5, depth_noise=True)


def _run(seq, loop_closure: bool, global_ba: bool = True, sparse: bool = True, max_frames: int = 20, **backend):
    # sparse: few features and no landmark fusion: the lap drifts by about a centimetre, which the loop has to
    # remove (with fusion the local map itself re-finds the start of the lap and leaves the loop little to correct).
    # The lap is tracked at every 5th frame and keyframe_max_frames counts the sequence's frames: 20 makes a
    # keyframe at least every 4 tracked frames (the figures below were measured so); 10 every other one
    tcfg = (TrackingConfig(n_features=300, keyframe_max_frames=max_frames) if sparse
            else TrackingConfig(keyframe_max_frames=max_frames))
    backend = Backend(seq.camera, tcfg, BackendConfig(loop_closure=loop_closure, fusion=not sparse,
                                                      global_ba=global_ba, **backend))
    tracker = OrbTracker(seq.camera, tcfg, backend)
    for i in FRAMES:
        tracker.track(seq[i])
    tracker.finish()
    stamps, poses, lost = tracker.trajectory()
    assert not lost.any()
    ate = trajectory_metrics(stamps, poses, seq.timestamps[FRAMES], seq.poses[FRAMES])["ate_rmse_cm"]
    return backend, ate


@pytest.fixture(scope="module")
def runs(lap):
    return {flag: _run(lap, flag) for flag in (False, True)} | {
        f"default{'' if ba else ' without global BA'}": _run(lap, True, global_ba=ba, sparse=False) for ba in (True, False)}


def test_full_lap_closes_a_correct_loop(lap, runs):
    backend, ate = runs[True]
    assert backend.map.loops, "the lap back to the start was not detected"
    kfs = backend.map.keyframes
    for match, query, T_mq, _ in backend.map.loops:
        assert kfs[query].frame_index - kfs[match].frame_index > 500  # a real revisit, not a neighbour
        gt = invert(lap.poses[kfs[match].frame_index]) @ lap.poses[kfs[query].frame_index]
        assert np.linalg.norm((invert(gt) @ T_mq)[:3, 3]) < 0.02
    assert ate < 1.0


def test_loop_closure_lowers_the_trajectory_error(runs):
    (no_loop_backend, ate_without), (_, ate_with) = runs[False], runs[True]
    assert not no_loop_backend.map.loops
    assert ate_with < 0.9 * ate_without, (ate_with, ate_without)  # measured: 0.86 vs 1.01 cm


def test_dense_keyframes_still_close_the_lap(lap):
    # a keyframe every 10 cm: each query's best covisible neighbour is a near-duplicate of it, so a loop threshold
    # relative to the best neighbour let no revisit through (no loop, ATE 1.32 cm); relative to the median it does
    (backend, ate_with), (_, ate_without) = _run(lap, True, max_frames=10), _run(lap, False, max_frames=10)
    assert backend.map.loops, "the lap back to the start was not detected"
    kfs = backend.map.keyframes
    for match, query, T_mq, _ in backend.map.loops:
        assert kfs[query].frame_index - kfs[match].frame_index > 500
        gt = invert(lap.poses[kfs[match].frame_index]) @ lap.poses[kfs[query].frame_index]
        assert np.linalg.norm((invert(gt) @ T_mq)[:3, 3]) < 0.02
    assert ate_with < 0.9 * ate_without, (ate_with, ate_without)  # measured: 1.11 vs 1.32 cm


def test_global_ba_after_the_loop_does_not_undo_it(runs):
    (with_ba, ate_with), (graph_only, ate_graph_only) = runs["default"], runs["default without global BA"]
    assert with_ba.map.loops and with_ba.summary()["global_ba_runs"] == len(with_ba.map.loops)
    assert graph_only.summary()["global_ba_runs"] == 0
    # measured: 0.92 vs 0.93 cm here; on seed 1 0.93 vs 2.36 cm, and on synthetic:2000 0.32 vs 3.18 cm
    assert ate_with <= 1.01 * ate_graph_only, (ate_with, ate_graph_only)
    assert runs[True][0].summary()["global_ba_runs"] == 0  # skipped without fusion


@pytest.mark.parametrize("concurrent", [False, True], ids=["sequential", "concurrent"])
def test_culled_keyframes_keep_following_the_trajectory(lap, concurrent):
    # with keyframe culling (backend.keyframe_culling; in concurrent mode tracking holds a reference keyframe the
    # backend must not cull meanwhile) each retired keyframe's pose, carried by the keyframe it rides on through
    # bundle adjustment, the loop closure and global BA, still agrees with the ground truth. Measured: sequential
    # ATE 0.83 cm (0.78 without culling), 5 of 64 keyframes retired, within 1.9 cm of the ground truth relative to
    # the first keyframe (the kept ones 1.1 cm median, 2.3 cm at most); concurrent (not repeatable) ATE 0.87-0.94 cm
    # over four runs (0.80-0.82 without), retired ones 1.6-1.9 cm median, 2.1-2.5 cm at most
    backend, ate = _run(lap, True, sparse=False, keyframe_culling=True, concurrent=concurrent, solver="thread")
    m = backend.map
    assert m.loops and backend.stats.keyframes_culled == len(m.retired) > 0
    assert all(r.parent in m.keyframes for r in m.retired.values())
    kf0 = min(m.keyframes)
    gt0 = lap.poses[m.keyframes[kf0].frame_index]

    def error_cm(k: int, frame: int) -> float:
        rel_est = invert(m.pose(kf0)) @ m.pose(k)
        rel_gt = invert(gt0) @ lap.poses[frame]
        return 100 * float(np.linalg.norm(rel_est[:3, 3] - rel_gt[:3, 3]))

    retired = [error_cm(k, r.frame_index) for k, r in m.retired.items()]
    kept = [error_cm(k, kf.frame_index) for k, kf in m.keyframes.items()]
    if concurrent:
        assert ate < 1.2 and max(retired) < 4.0, (ate, retired)
    else:
        assert ate < 0.9 and max(retired) < 3.0 and max(kept) < 3.0, (ate, retired, kept)
