"""The SLAM map's landmark storage: dead landmarks' slots are reused, without changing what tracking and bundle
adjustment see (creation order, stale solutions)."""
from types import SimpleNamespace

import numpy as np

from ggfslam.backend.local_ba import apply_solution
from ggfslam.backend.slam_map import KeyFrame, SlamMap
from ggfslam.frontend.features import Features


def _keyframe(smap: SlamMap, kf_id: int, n: int = 40) -> KeyFrame:
    feats = Features(np.zeros((n, 2)), np.zeros(n, np.int64), np.zeros((n, 32), np.uint8), np.ones(n), np.zeros((n, 3)))
    kf = KeyFrame(kf_id, kf_id, float(kf_id), np.eye(4), feats, np.full(n, -1, np.int64))
    smap.add_keyframe(kf)
    return kf


def test_dead_landmark_slots_are_reused_and_a_stale_bundle_adjustment_passes_them_over():
    smap = SlamMap(capacity=8)
    a, b = _keyframe(smap, 0), _keyframe(smap, 1)
    first = smap.add_landmarks(np.zeros((6, 3)), np.zeros((6, 32), np.uint8), a, np.arange(6))
    assert first.tolist() == list(range(6)) and smap.size == 6
    for lm in first[:4]:
        smap.add_observation(int(lm), b, int(lm))
    snapshot = SimpleNamespace(lms=first.copy(), generations=smap.generation[first].copy())
    smap.remove_landmark(int(first[1]))  # culled
    smap.remove_observation(int(first[4]), 0)  # its only observer dropped it: dies
    smap.merge_landmarks(keep=int(first[2]), drop=int(first[3]))
    assert smap.alive[first].tolist() == [True, False, True, False, False, True]
    assert a.landmark_ids[[1, 3, 4]].tolist() == [-1, -1, -1] and b.landmark_ids[[1, 3]].tolist() == [-1, -1]
    # new landmarks take the dead slots first (oldest death first), then new ones: the arrays do not grow
    new = smap.add_landmarks(np.ones((4, 3)), np.zeros((4, 32), np.uint8), b, np.array([10, 11, 12, 13]))
    assert new.tolist() == [1, 4, 3, 6] and smap.size == 7 and len(smap.alive) == 8
    assert smap.alive[new].all() and all(smap.observations[lm] == {1: kp} for lm, kp in zip(new, [10, 11, 12, 13]))
    assert smap.generation[[1, 3, 4, 6]].tolist() == [1, 1, 1, 0]
    # a bundle adjustment solved from the snapshot writes only the landmarks that are still the same ones
    sol = SimpleNamespace(stats=SimpleNamespace(failed=""), poses={}, planes={}, positions=np.full((6, 3), 5.0),
                          outliers=[(1, 1), (0, 1)])
    apply_solution(smap, SimpleNamespace(**vars(snapshot)), sol)
    np.testing.assert_array_equal(smap.positions[[0, 2, 5]], 5.0)
    np.testing.assert_array_equal(smap.positions[[1, 3, 4]], 1.0)
    assert smap.observations[1] == {1: 10}  # the reused slot kept its observation; landmark 0 lost keyframe 1's
    assert 1 not in smap.observations[0]
    # tracking matched a point before the backend culled it: the new keyframe does not observe the dead slot
    smap.remove_landmark(5)
    smap.add_observation(5, b, 20)
    assert smap.observations[5] == {} and b.landmark_ids[20] == -1



def test_landmarks_of_lists_the_oldest_first_whatever_their_slots():
    # matching breaks ties by this order (an established point wins over a new one), as it did when ids were the
    # creation order: tracking is the same with reused slots (fr3/cabinet, the 7-Scenes kitchen and 2000 frames of
    # the synthetic room gave the same trajectories to the byte)
    smap = SlamMap(capacity=4)
    a = _keyframe(smap, 0)
    old = smap.add_landmarks(np.zeros((4, 3)), np.zeros((4, 32), np.uint8), a, np.arange(4))
    smap.remove_landmark(int(old[0]))
    smap.remove_landmark(int(old[2]))
    b = _keyframe(smap, 1)
    for lm in old[[1, 3]]:
        smap.add_observation(int(lm), b, int(lm))
    new = smap.add_landmarks(np.ones((3, 3)), np.zeros((3, 32), np.uint8), b, np.array([5, 6, 7]))
    assert new.tolist() == [0, 2, 4]  # two reused slots, then one more (the arrays doubled once)
    assert smap.landmarks_of([0, 1]).tolist() == [1, 3, 0, 2, 4]
    assert smap.born[[1, 3, 0, 2, 4]].tolist() == [1, 3, 4, 5, 6]
