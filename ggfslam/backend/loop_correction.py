"""Close a detected loop on the map: pose-graph optimization over all keyframes, landmark correction, fusion."""
from __future__ import annotations

import numpy as np

from ggfslam.backend.loop_closure import LoopResult
from ggfslam.backend.pose_graph import PoseEdge, correct_points, optimize_pose_graph
from ggfslam.backend.slam_map import SlamMap
from ggfslam.geometry.se3 import invert, rotation_angle

# a loop's own covariance can be 1-2 mm: floor it so a slightly optimistic loop cannot tear the graph
_LOOP_FLOOR_ROT, _LOOP_FLOOR_TRANS = np.radians(0.5), 0.01
# consecutive-keyframe and covisibility edges (rad, m): a floor, plus a share of the motion between the two
# keyframes (like wheel odometry, the error of visual odometry grows with the motion: ~1 cm and ~1 degree per
# 15-20 cm / 7 degree step on real Kinect data, a few mm per 5 cm step on synthetic frames)
_ODOM_ROT, _ODOM_TRANS = 0.003, 0.005
_ODOM_SHARE = 0.05
_COVIS_MIN_SHARED = 100  # covisibility edges only between keyframes sharing this many landmarks


def loop_edges(smap: SlamMap, loop: LoopResult) -> list[PoseEdge]:
    """Consecutive-keyframe and strong covisibility edges from the current estimates, plus the loop edge."""
    poses = smap.graph_poses()
    ids = sorted(poses)
    covis = {a: smap.covisibility(a) for a in ids}
    edges = [_relative_edge(poses, a, b, "odometry", covis[a].get(b, 0)) for a, b in zip(ids[:-1], ids[1:])]
    consecutive = set(zip(ids[:-1], ids[1:]))
    for a in ids:
        for b, shared in covis[a].items():
            if a < b and shared >= _COVIS_MIN_SHARED and (a, b) not in consecutive and \
                    {a, b} != {loop.match_id, loop.query_id}:
                edges.append(_relative_edge(poses, a, b, "covisibility", shared))
    # earlier loops stay in the graph, or a new loop correction could undo them
    for m, q, T_mq, cov in smap.loops + [(loop.match_id, loop.query_id, loop.T_match_query, loop_covariance(loop))]:
        edges.append(PoseEdge(m, q, T_mq, kind="loop", covariance=cov))
    return edges


def _relative_edge(poses: dict[int, np.ndarray], a: int, b: int, kind: str, shared: int) -> PoseEdge:
    """An edge holding keyframes a and b at their current relative pose; its sigmas grow with the motion and
    shrink with the landmarks both see (a pair tied only by dense odometry is the likeliest place of drift)."""
    T = invert(poses[a]) @ poses[b]
    angle = rotation_angle(T[:3, :3])
    dist = float(np.linalg.norm(T[:3, 3]))
    weak = float(np.clip(np.sqrt(_COVIS_MIN_SHARED / max(shared, 1)), 1.0, 5.0))
    return PoseEdge(a, b, T, weak * (_ODOM_ROT + _ODOM_SHARE * angle), weak * (_ODOM_TRANS + _ODOM_SHARE * dist),
                    kind=kind)


def loop_covariance(loop: LoopResult) -> np.ndarray:
    """Covariance [6, 6] of a loop edge: the verification's own estimate plus a floor."""
    cov = np.diag([_LOOP_FLOOR_ROT ** 2] * 3 + [_LOOP_FLOOR_TRANS ** 2] * 3)
    return cov if loop.covariance is None else cov + loop.covariance


def close_loop(smap: SlamMap, loop: LoopResult, solve=optimize_pose_graph) -> dict[int, np.ndarray]:
    """Correct every keyframe and landmark for a verified loop and fuse the points seen on both sides.

    The matched (older) keyframe is held fixed: its pose predates the drift the loop removes. The pose graph is
    solved (``solve``: ``optimize_pose_graph`` or a ``SolverProcess``'s ``pose_graph``) outside the map's lock, so
    tracking goes on meanwhile; keyframes it made meanwhile move with the keyframe before them.
    Returns the new keyframe poses.
    """
    with smap.lock:
        old = smap.graph_poses()
        edges = loop_edges(smap, loop)
        # the first loop has no other loop to disagree with: after verification it is trusted (as ORB-SLAM does);
        # later ones go through the robust solve, which drops a loop edge the others contradict
        robust = bool(smap.loops)
    new = solve(old, edges, {loop.match_id}, robust)
    with smap.lock:
        for k, T in sorted(smap.graph_poses().items()):
            if k not in new:  # made while the graph was solved: keep its pose relative to its predecessor
                before = max((j for j in new if j < k), default=None)
                if before is None:
                    continue
                old[k], new[k] = T, new[before] @ invert(old[before]) @ T
        for k, T in new.items():
            if k in smap.keyframes:
                smap.keyframes[k].T_wc = T
        smap.loops.append((loop.match_id, loop.query_id, loop.T_match_query.copy(), loop_covariance(loop)))
        ids = smap.alive_ids()
        # a point made by a retired keyframe moves with the keyframe that keyframe rides on
        refs = smap.created_by[ids]
        for k in np.unique(refs).tolist():
            if k in smap.retired:
                refs[refs == k] = smap.living(k)
        smap.positions[ids] = correct_points(smap.positions[ids], refs, old, new)
        q, m = smap.keyframes[loop.query_id], smap.keyframes[loop.match_id]
        for iq, im in loop.inlier_pairs:
            lq, lm = int(q.landmark_ids[iq]), int(m.landmark_ids[im])
            if lq >= 0 and lm >= 0:
                smap.merge_landmarks(keep=lm, drop=lq)
            elif lm >= 0 and smap.alive[lm]:
                smap.add_observation(lm, q, int(iq))
    return new
