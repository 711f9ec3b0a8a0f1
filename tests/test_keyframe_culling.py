"""Keyframe culling: which keyframes are redundant (ORB-SLAM's rule), what retiring one removes, and that a retired
keyframe's pose keeps following its parent through every correction."""
import pickle

import numpy as np
import pytest

from ggfslam.backend.keyframe_culling import cull_keyframes, protected_keyframes
from ggfslam.backend.slam_map import KeyFrame, SlamMap
from ggfslam.config import BackendConfig
from ggfslam.frontend.features import Features
from ggfslam.geometry.se3 import se3_exp
from ggfslam.safe_load import load_tracker_pickle

N_POINTS = 40


def _features(n: int, octave: int = 0) -> Features:
    uv = np.zeros((n, 2))
    z = np.ones(n)
    return Features(uv, np.full(n, octave, np.int64), np.zeros((n, 32), np.uint8), z, np.zeros((n, 3)))


def _keyframe(smap: SlamMap, kf_id: int, x: float, octave: int = 0, n: int = N_POINTS) -> KeyFrame:
    T = np.eye(4)
    T[0, 3] = x
    kf = KeyFrame(kf_id, 10 * kf_id, float(kf_id), T, _features(n, octave), np.full(n, -1, np.int64))
    smap.add_keyframe(kf)
    return kf


def _shared_scene(n_keyframes: int = 6, octaves=None) -> SlamMap:
    """Keyframes 0..n-1 that all see the same N_POINTS landmarks (made by keyframe 0)."""
    smap = SlamMap()
    octaves = octaves or [0] * n_keyframes
    kfs = [_keyframe(smap, k, 0.1 * k, octaves[k]) for k in range(n_keyframes)]
    ids = smap.add_landmarks(np.random.default_rng(0).normal(size=(N_POINTS, 3)) + [0, 0, 3],
                             np.zeros((N_POINTS, 32), np.uint8), kfs[0], np.arange(N_POINTS))
    for kf in kfs[1:]:
        for kp, lm in enumerate(ids):
            smap.add_observation(int(lm), kf, kp)
    return smap


def test_a_keyframe_whose_points_three_others_see_is_retired_and_the_rest_stay():
    smap = _shared_scene(6)
    smap.tracking_ref = 5
    retired = cull_keyframes(smap, 5, share=0.9, observers=3)
    # keyframe 0 holds the gauge and 5 is the new one; 1 and 2 go (each point then still has 0, 3, 4, 5: three
    # others for 3 and 4), after which 3's points are seen by only 0, 4 and 5: three others, so it goes too; 4 is
    # then left with 0 and 5: two
    assert retired == [1, 2, 3]
    assert sorted(smap.keyframes) == [0, 4, 5]
    for lm in smap.alive_ids():
        assert sorted(smap.observations[lm]) == [0, 4, 5]


def test_points_only_coarser_keyframes_see_do_not_count_as_redundant():
    # keyframe 1 sees the points at level 0; the others only at level 2 (farther away): they do not replace it
    smap = _shared_scene(6, octaves=[2, 0, 2, 2, 2, 2])
    retired = cull_keyframes(smap, 5, share=0.9, observers=3)
    assert 1 not in retired and 1 in smap.keyframes
    assert {2, 3} <= set(retired)  # level 2 is seen at level <= 3 by the others


def test_a_keyframe_with_its_own_points_stays():
    smap = _shared_scene(6)
    own = smap.add_landmarks(np.full((10, 3), 2.0), np.zeros((10, 32), np.uint8), smap.keyframes[2],
                             np.arange(N_POINTS - 10, N_POINTS))  # replaces 10 of its 40 shared points: 25% its own
    assert len(own) == 10
    retired = cull_keyframes(smap, 5, share=0.9, observers=3)
    assert 2 not in retired


def test_protected_keyframes_are_never_retired():
    smap = _shared_scene(7)
    smap.tracking_ref = 2
    smap.loops.append((3, 6, np.eye(4), np.eye(6)))
    smap.keyframes[6].meta["odometry_link"] = (4, np.eye(4))
    assert protected_keyframes(smap) == {0, 2, 3, 4, 6}
    retired = cull_keyframes(smap, 5, share=0.9, observers=3)
    assert retired == [1]  # 6 is newer than the keyframe being processed: not processed yet
    assert set(smap.keyframes) == {0, 2, 3, 4, 5, 6}


def test_a_retired_keyframe_rides_on_its_parent_and_chains_collapse():
    smap = _shared_scene(4)
    T1 = smap.keyframes[1].T_wc.copy()
    T2 = smap.keyframes[2].T_wc.copy()
    smap.planes[7] = np.array([0, 0, 1.0, -3.0])
    smap.plane_observations[7] = {1: np.array([0, 0, 1.0, -3.0]), 3: np.array([0, 0, 1.0, -3.0])}
    kf = smap.retire_keyframe(1, parent=2)
    assert kf.id == 1 and 1 not in smap.keyframes and 1 in smap.retired
    assert smap.plane_observations[7].keys() == {3}
    assert all(1 not in smap.observations[lm] for lm in smap.alive_ids())
    np.testing.assert_allclose(smap.pose(1), T1, atol=1e-12)
    # the parent moves (bundle adjustment, a loop closure): the retired keyframe moves rigidly with it
    D = se3_exp(np.array([0.01, -0.02, 0.03, 0.1, 0.2, -0.1]))
    smap.keyframes[2].T_wc = D @ T2
    np.testing.assert_allclose(smap.pose(1), D @ T1, atol=1e-12)
    # the parent is retired in its turn: keyframe 1 now rides on 2's parent, directly
    smap.retire_keyframe(2, parent=3)
    assert smap.retired[1].parent == 3 and smap.anchor(1)[0] == 3 and smap.living(2) == 3
    np.testing.assert_allclose(smap.pose(1), D @ T1, atol=1e-12)
    np.testing.assert_allclose(smap.pose(2), D @ T2, atol=1e-12)
    poses, graph = smap.poses(), smap.graph_poses()
    assert sorted(poses) == [0, 1, 2, 3] and sorted(graph) == [0, 3]
    np.testing.assert_allclose(poses[1], D @ T1, atol=1e-12)
    with pytest.raises(ValueError, match="parent"):
        smap.retire_keyframe(3, parent=2)
    with pytest.raises(KeyError):
        smap.pose(99)
    # checkpoints keep the retired keyframes and the free landmark slots, through the restricted reader
    smap.remove_landmark(int(smap.alive_ids()[0]))
    back = load_tracker_pickle(pickle.dumps(smap))
    np.testing.assert_allclose(back.pose(1), D @ T1, atol=1e-12)
    assert list(back._free) == list(smap._free) and len(back._free) == 1


def test_a_landmark_only_the_retired_keyframe_saw_dies():
    smap = SlamMap()
    a, b = _keyframe(smap, 0, 0.0), _keyframe(smap, 1, 0.1)
    ids = smap.add_landmarks(np.ones((3, 3)), np.zeros((3, 32), np.uint8), b, np.arange(3))
    smap.add_observation(int(ids[0]), a, 0)
    smap.retire_keyframe(1, parent=0)
    assert smap.alive[ids].tolist() == [True, False, False]
    assert smap.observations[ids[0]] == {0: 0}


def test_a_checkpoint_map_from_before_culling_loads():
    smap = _shared_scene(2)
    state = smap.__getstate__()
    del state["retired"], state["tracking_ref"]
    old = SlamMap.__new__(SlamMap)
    old.__setstate__(state)
    assert old.retired == {} and old.tracking_ref == -1
    assert sorted(old.poses()) == [0, 1]


def test_culling_settings_are_checked():
    with pytest.raises(ValueError, match="culling_redundancy"):
        BackendConfig(culling_redundancy=0.0)
    with pytest.raises(ValueError, match="culling_observers"):
        BackendConfig(culling_observers=0)



def test_graph_json_lists_the_retired_keyframes_with_their_parents():
    from ggfslam.backend.export import graph_to_dict
    from ggfslam.config import TrackingConfig
    from ggfslam.data.types import Camera

    smap = _shared_scene(4)
    smap.retire_keyframe(2, parent=3)
    smap.keyframes[3].T_wc = se3_exp(np.array([0.0, 0.1, 0.0, 0.2, 0.0, 0.0])) @ smap.keyframes[3].T_wc
    cam = Camera(500.0, 500.0, 319.5, 239.5, 640, 480, 5000.0, ())
    g = graph_to_dict(smap, cam, TrackingConfig(), BackendConfig())
    assert [k["id"] for k in g["keyframes"]] == [0, 1, 3]
    assert g["meta"]["counts"]["retired_keyframes"] == 1
    (r,) = g["retired_keyframes"]
    assert (r["id"], r["parent"], r["frame_index"]) == (2, 3, 20)
    np.testing.assert_allclose(np.array(r["T_wc"]), np.array(g["keyframes"][2]["T_wc"]) @ np.array(r["T_parent_kf"]),
                               atol=1e-12)
    assert {f["kf"] for f in g["factors"] if "kf" in f} == {0, 1, 3}
