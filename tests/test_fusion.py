"""Landmark fusion: duplicates of the same physical point found by two keyframes become one landmark."""
import numpy as np

from ggfslam.backend.fusion import fuse_neighbours
from ggfslam.backend.slam_map import KeyFrame, SlamMap
from ggfslam.config import TrackingConfig
from ggfslam.frontend.features import Features, backproject_points
from ggfslam.geometry.se3 import invert, make_pose
from tests.test_backend import CAM


def _keyframe(smap, kf_id, T, pts, desc, depth_offset=None):
    p_c = pts @ invert(T)[:3, :3].T + invert(T)[:3, 3]
    uv = np.column_stack([CAM.fx * p_c[:, 0] / p_c[:, 2] + CAM.cx, CAM.fy * p_c[:, 1] / p_c[:, 2] + CAM.cy])
    z = p_c[:, 2].copy() + (0.0 if depth_offset is None else depth_offset)
    feats = Features(uv, np.zeros(len(pts), np.int64), desc.copy(), z, backproject_points(uv, z, CAM))
    kf = KeyFrame(kf_id, kf_id, float(kf_id), T.copy(), feats, np.full(len(pts), -1, np.int64))
    smap.add_keyframe(kf)
    return kf


def test_fusion_merges_duplicates_and_respects_depth():
    rng = np.random.default_rng(1)
    n = 200
    pts = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-0.7, 0.7, n), rng.uniform(2.0, 3.0, n)])
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    smap = SlamMap()
    T1 = make_pose(np.eye(3), [0.1, 0.0, 0.0])
    kf0 = _keyframe(smap, 0, np.eye(4), pts, desc)
    offset = np.zeros(n)
    offset[:20] = 0.5  # kf1 measures another surface behind these 20 points
    kf1 = _keyframe(smap, 1, T1, pts, desc, offset)
    a = smap.add_landmarks(pts, desc, kf0, np.arange(n))
    # kf1 created its own copies of points 100..199 (tracking missed them); points 0..99 it saw nothing of
    b = smap.add_landmarks(pts[100:] + rng.normal(scale=0.002, size=(100, 3)), desc[100:], kf1, np.arange(100, n))
    added, merged = fuse_neighbours(smap, 1, [0], CAM, TrackingConfig())
    assert merged == 100  # every duplicate found its twin
    assert added == 80  # unmatched points of kf0 now observed by kf1, except the 20 with another depth
    assert not smap.alive[b].any()
    for i in range(20, n):
        assert smap.observations[a[i]] == {0: i, 1: i}
    for i in range(20):
        assert smap.observations[a[i]] == {0: i}
    assert (kf1.landmark_ids[20:] == a[20:]).all() and (kf1.landmark_ids[:20] == -1).all()
    # fusing again changes nothing
    assert fuse_neighbours(smap, 1, [0], CAM, TrackingConfig()) == (0, 0)
