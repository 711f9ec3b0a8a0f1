"""The SLAM map the backend owns: keyframes (poses, features) and landmarks (positions, observations)."""
from __future__ import annotations

import threading
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from ggfslam.frontend.features import Features


@dataclass
class KeyFrame:
    """A keyframe: its pose estimate and features; ``landmark_ids[i]`` is the map point seen at keypoint i (-1: none)."""

    id: int
    frame_index: int
    timestamp: float
    T_wc: np.ndarray  # [4, 4] camera-to-world, updated by bundle adjustment and loop closure
    features: Features
    landmark_ids: np.ndarray  # [N] int64
    meta: dict = field(default_factory=dict)


class SlamMap:
    """Keyframes and landmarks with covisibility queries; every mutation happens under ``lock``."""

    def __init__(self, capacity: int = 4096):
        self.lock = threading.RLock()
        self.keyframes: dict[int, KeyFrame] = {}
        self.positions = np.zeros((capacity, 3))  # [C, 3] world coordinates
        self.descriptors = np.zeros((capacity, 32), dtype=np.uint8)  # [C, 32] representative ORB descriptor
        self.alive = np.zeros(capacity, dtype=bool)  # [C]
        self.created_by = np.full(capacity, -1, dtype=np.int64)  # [C] keyframe that created the point
        self.n_visible = np.zeros(capacity, dtype=np.int64)  # [C] frames where tracking predicted it in view
        self.n_found = np.zeros(capacity, dtype=np.int64)  # [C] frames where tracking matched it
        self.ref_distance = np.ones(capacity)  # [C] camera distance when created (predicts its pyramid level)
        self.ref_octave = np.zeros(capacity, dtype=np.int64)  # [C] pyramid level when created
        self.observations: list[dict[int, int]] = [{} for _ in range(capacity)]  # kf id -> keypoint index
        self.size = 0
        # closed loops: (match kf, query kf, T_match_query [4, 4], covariance [6, 6] of the loop edge)
        self.loops: list[tuple[int, int, np.ndarray, np.ndarray]] = []
        # plane landmarks (see backend/plane_map.py): id -> world coefficients [4] (n, d), n . x + d = 0
        self.planes: dict[int, np.ndarray] = {}
        self.plane_observations: dict[int, dict[int, np.ndarray]] = {}  # plane id -> {kf id: camera coefficients [4]}

    def __getstate__(self) -> dict:  # checkpoints: the lock is per process
        state = self.__dict__.copy()
        del state["lock"]
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.lock = threading.RLock()

    # --- landmarks --------------------------------------------------------------------------------
    def _grow(self) -> None:
        cap = 2 * len(self.alive)
        for name in ("positions", "descriptors", "alive", "created_by", "n_visible", "n_found", "ref_distance",
                     "ref_octave"):
            old = getattr(self, name)
            new = np.zeros((cap,) + old.shape[1:], dtype=old.dtype)
            if name == "created_by":
                new[:] = -1
            new[: len(old)] = old
            setattr(self, name, new)
        self.observations.extend({} for _ in range(cap - len(self.observations)))

    def add_landmarks(self, positions: np.ndarray, descriptors: np.ndarray, kf: KeyFrame, kp_idx: np.ndarray) -> np.ndarray:
        """Create landmarks at positions [K, 3] observed by keyframe ``kf`` at keypoints kp_idx [K]; returns ids [K]."""
        with self.lock:
            while self.size + len(positions) > len(self.alive):
                self._grow()
            ids = np.arange(self.size, self.size + len(positions))
            self.positions[ids] = positions
            self.descriptors[ids] = descriptors
            self.alive[ids] = True
            self.created_by[ids] = kf.id
            self.n_visible[ids] = 1
            self.n_found[ids] = 1
            self.ref_distance[ids] = np.linalg.norm(positions - kf.T_wc[:3, 3], axis=1)
            self.ref_octave[ids] = kf.features.octave[kp_idx]
            for lm, k in zip(ids, kp_idx):
                self.observations[lm] = {kf.id: int(k)}
            kf.landmark_ids[kp_idx] = ids
            self.size += len(positions)
            return ids

    def add_observation(self, lm: int, kf: KeyFrame, kp: int) -> None:
        """Record that keyframe ``kf`` sees landmark ``lm`` at keypoint ``kp``."""
        with self.lock:
            old = kf.landmark_ids[kp]
            if old >= 0 and old != lm:
                self.observations[old].pop(kf.id, None)
            self.observations[lm][kf.id] = int(kp)
            kf.landmark_ids[kp] = lm

    def remove_observation(self, lm: int, kf_id: int) -> None:
        """Forget that keyframe ``kf_id`` sees landmark ``lm`` (an outlier); a landmark seen by nobody dies."""
        with self.lock:
            kp = self.observations[lm].pop(kf_id, None)
            if kp is not None and kf_id in self.keyframes:
                self.keyframes[kf_id].landmark_ids[kp] = -1
            if not self.observations[lm]:
                self.alive[lm] = False

    def remove_landmark(self, lm: int) -> None:
        """Delete a landmark and its observations."""
        with self.lock:
            for kf_id, kp in self.observations[lm].items():
                if kf_id in self.keyframes:
                    self.keyframes[kf_id].landmark_ids[kp] = -1
            self.observations[lm] = {}
            self.alive[lm] = False

    def merge_landmarks(self, keep: int, drop: int) -> None:
        """Fuse landmark ``drop`` into ``keep`` (same physical point found twice)."""
        with self.lock:
            if keep == drop or not (self.alive[keep] and self.alive[drop]):
                return
            for kf_id, kp in list(self.observations[drop].items()):
                if kf_id in self.observations[keep] or kf_id not in self.keyframes:
                    continue
                self.observations[keep][kf_id] = kp
                self.keyframes[kf_id].landmark_ids[kp] = keep
            self.n_visible[keep] += self.n_visible[drop]
            self.n_found[keep] += self.n_found[drop]
            for kf_id, kp in self.observations[drop].items():
                if kf_id in self.keyframes and self.keyframes[kf_id].landmark_ids[kp] == drop:
                    self.keyframes[kf_id].landmark_ids[kp] = -1
            self.observations[drop] = {}
            self.alive[drop] = False

    def alive_ids(self) -> np.ndarray:
        """Ids [L] of living landmarks."""
        return np.nonzero(self.alive[: self.size])[0]

    # --- keyframes --------------------------------------------------------------------------------
    def add_keyframe(self, kf: KeyFrame) -> None:
        """Insert a keyframe (its observations are added by the caller)."""
        with self.lock:
            self.keyframes[kf.id] = kf

    def covisibility(self, kf_id: int) -> Counter:
        """Keyframe id -> number of landmarks shared with keyframe ``kf_id``."""
        with self.lock:
            kf = self.keyframes[kf_id]
            count: Counter = Counter()
            for lm in kf.landmark_ids[kf.landmark_ids >= 0]:
                count.update(self.observations[lm].keys())
            count.pop(kf_id, None)
            return count

    def local_keyframes(self, kf_id: int, n: int, min_shared: int = 15, temporal: int = 0) -> list[int]:
        """``kf_id``, up to ``n - 1`` keyframes sharing the most landmarks with it, and the ``temporal`` keyframes
        created just before it (which may share few points where texture is poor, yet are its closest views)."""
        cov = self.covisibility(kf_id)
        out = [kf_id] + [k for k, c in cov.most_common(n - 1) if c >= min_shared]
        with self.lock:
            earlier = sorted(k for k in self.keyframes if k < kf_id)[::-1][:temporal]
        return out + [k for k in earlier if k not in out]

    def landmarks_of(self, kf_ids: list[int]) -> np.ndarray:
        """Sorted ids of living landmarks observed by any of the keyframes."""
        with self.lock:
            ids = [self.keyframes[k].landmark_ids for k in kf_ids if k in self.keyframes]
            if not ids:
                return np.zeros(0, dtype=np.int64)
            lm = np.unique(np.concatenate(ids))
            lm = lm[lm >= 0]
            return lm[self.alive[lm]]

    def poses(self) -> dict[int, np.ndarray]:
        """Copy of every keyframe pose (id -> T_wc)."""
        with self.lock:
            return {k: kf.T_wc.copy() for k, kf in self.keyframes.items()}
