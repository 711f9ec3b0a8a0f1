"""Keyframe culling (ORB-SLAM's rule): retire keyframes whose points other keyframes already see.

Checked among a new keyframe's covisible keyframes after its bundle adjustment. A keyframe is redundant when more
than ``backend.culling_redundancy`` of its living points are each seen by ``backend.culling_observers`` other
keyframes at the same or a finer scale (a pyramid level at most one above its own). Never retired: the first
keyframe (it holds the gauge), keyframes of closed loops (their edges stay in every pose graph), tracking's
reference keyframe, targets of dense-odometry links, and keyframes not processed by the backend yet (the new one
and, in concurrent mode, those queued behind it).
"""
from __future__ import annotations

import numpy as np

from ggfslam.backend.slam_map import KeyFrame, SlamMap


def protected_keyframes(smap: SlamMap) -> set[int]:
    """Keyframes that must stay in the graph whatever their redundancy (see the module docstring)."""
    with smap.lock:
        keep = {min(smap.keyframes)} if smap.keyframes else set()
        keep |= {k for m, q, _, _ in smap.loops for k in (m, q)}
        keep.add(smap.tracking_ref)
        keep |= {kf.meta["odometry_link"][0] for kf in smap.keyframes.values() if "odometry_link" in kf.meta}
        return keep


def _redundant(smap: SlamMap, kf: KeyFrame, share: float, observers: int) -> bool:
    """Whether more than ``share`` of the keyframe's living points are seen by ``observers`` other keyframes at the
    same or a finer scale."""
    kps = np.nonzero(kf.landmark_ids >= 0)[0]  # [P]
    lms = kf.landmark_ids[kps]
    alive = smap.alive[lms]
    kps, lms = kps[alive], lms[alive]
    if len(lms) == 0:
        return False  # a keyframe placed by dense odometry alone: no point vouches for its removal
    need = share * len(lms)
    n_obs = np.fromiter((len(smap.observations[lm]) for lm in lms.tolist()), np.int64, len(lms))  # [P]
    if int((n_obs > observers).sum()) <= need:  # cannot be redundant: skip the per-observation scale check
        return False
    octave = kf.features.octave
    octaves: dict[int, np.ndarray] = {}  # other keyframes' octaves, each read from the feature store once
    redundant = 0
    for lm, kp, n in zip(lms.tolist(), kps.tolist(), n_obs.tolist()):
        if n <= observers:
            continue
        finest = int(octave[kp]) + 1
        seen = 0
        for other, okp in smap.observations[lm].items():
            if other == kf.id:
                continue
            oct_other = octaves.get(other)
            if oct_other is None:
                oct_other = octaves[other] = smap.keyframes[other].features.octave
            if int(oct_other[okp]) <= finest:
                seen += 1
                if seen >= observers:
                    redundant += 1
                    break
    return redundant > need


def cull_keyframes(smap: SlamMap, kf_id: int, share: float, observers: int) -> list[int]:
    """Retire the redundant keyframes among those covisible with keyframe ``kf_id`` (older than it), each onto a
    keyframe in the graph that shares many points with it (``_parent``); returns the retired ids, in order."""
    retired = []
    with smap.lock:
        if kf_id not in smap.keyframes:
            return retired
        keep = protected_keyframes(smap)
        for k in sorted(smap.covisibility(kf_id)):
            if k >= kf_id or k in keep or k not in smap.keyframes:
                continue
            if not _redundant(smap, smap.keyframes[k], share, observers):
                continue
            parent = _parent(smap, k)
            if parent is None:
                continue
            smap.retire_keyframe(k, parent)
            retired.append(k)
    return retired


def _parent(smap: SlamMap, kf_id: int) -> int | None:
    """The keyframe a retired one rides on: the nearest in time among those sharing at least half as many points
    with it as the one sharing most. Not simply the one sharing most: after a revisit that may be a keyframe of
    an earlier lap, and the relative pose frozen now would keep the drift between the laps that a later loop
    closure removes from the retired keyframe's neighbours."""
    shared = smap.covisibility(kf_id)
    if not shared:
        return None
    most = max(shared.values())
    return min((k for k, n in shared.items() if 2 * n >= most), key=lambda k: (abs(k - kf_id), -shared[k], k))
