"""The SLAM map the backend owns: keyframes (poses, features) and landmarks (positions, observations).

Keyframes culled from the graph (``backend.keyframe_culling``) become ``RetiredKeyFrame``s: their features and
observations are gone, their pose rides rigidly on a parent keyframe, so frames tracked against them and the
mapper's views of them still have a pose that follows every correction.
"""
from __future__ import annotations

import threading
from collections import Counter, deque
from dataclasses import dataclass
from itertools import chain

import numpy as np

from ggfslam.backend.feature_store import FeatureStore
from ggfslam.frontend.features import Features
from ggfslam.geometry.se3 import invert


class KeyFrame:
    """A keyframe: its pose estimate and features; ``landmark_ids[i]`` is the map point seen at keypoint i (-1: none).

    Once in a map, its features live in the map's ``FeatureStore`` (on disk in a run) and ``features`` reads them
    from there."""

    def __init__(self, id: int, frame_index: int, timestamp: float, T_wc: np.ndarray, features: Features,
                 landmark_ids: np.ndarray, meta: dict | None = None):
        self.id = id
        self.frame_index = frame_index
        self.timestamp = timestamp
        self.T_wc = T_wc  # [4, 4] camera-to-world, updated by bundle adjustment and loop closure
        self._features: Features | None = features
        self._store: FeatureStore | None = None
        self.landmark_ids = landmark_ids  # [N] int64
        self.meta = {} if meta is None else meta

    @property
    def features(self) -> Features:
        """The keyframe's keypoints (from the map's feature store once it is in a map)."""
        return self._features if self._store is None else self._store.get(self.id)

    def keep_features_in(self, store: FeatureStore) -> None:
        """Hand the features to ``store``; from now on they are read from there."""
        if self._store is None:
            store.put(self.id, self._features)
            self._store, self._features = store, None

    def __repr__(self) -> str:
        return f"KeyFrame(id={self.id}, frame_index={self.frame_index}, timestamp={self.timestamp})"

    def __setstate__(self, state: dict) -> None:  # checkpoints from before the feature store held the features
        if "features" in state:
            state["_features"], state["_store"] = state.pop("features"), None
        self.__dict__.update(state)


@dataclass
class RetiredKeyFrame:
    """A keyframe culled from the graph: T_wc = T_wc of ``parent`` (a keyframe in the graph) @ T_parent_kf."""

    id: int
    frame_index: int
    timestamp: float
    parent: int
    T_parent_kf: np.ndarray  # [4, 4]


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
        self.generation = np.zeros(capacity, dtype=np.int64)  # [C] times the slot was given to a new landmark
        self.born = np.zeros(capacity, dtype=np.int64)  # [C] creation order (ids are not: slots are reused)
        self.created = 0  # landmarks ever created
        self.observations: list[dict[int, int]] = [{} for _ in range(capacity)]  # kf id -> keypoint index
        self.size = 0  # slots ever used; dead landmarks' slots below it are given to new ones (``_free``)
        # dead slots, oldest death first: no keyframe refers to them, so new landmarks reuse them and the arrays
        # stop growing with every point ever made (a long run culls tens of thousands)
        self._free: deque[int] = deque()
        # closed loops: (match kf, query kf, T_match_query [4, 4], covariance [6, 6] of the loop edge)
        self.loops: list[tuple[int, int, np.ndarray, np.ndarray]] = []
        # plane landmarks (see backend/plane_map.py): id -> world coefficients [4] (n, d), n . x + d = 0
        self.planes: dict[int, np.ndarray] = {}
        self.plane_observations: dict[int, dict[int, np.ndarray]] = {}  # plane id -> {kf id: camera coefficients [4]}
        self.retired: dict[int, RetiredKeyFrame] = {}  # culled keyframes, by id
        self.tracking_ref = -1  # tracking's reference keyframe: never culled while it is one
        self.feature_store = FeatureStore()  # the keyframes' features (in memory until a run attaches a folder)

    def __getstate__(self) -> dict:  # checkpoints: the lock is per process
        state = self.__dict__.copy()
        del state["lock"]
        state["_free"] = list(self._free)  # a plain list: the checkpoint reader calls no constructors
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.__dict__.setdefault("retired", {})  # checkpoints from before keyframe culling
        self.__dict__.setdefault("tracking_ref", -1)
        if "_free" not in state:  # checkpoints from before slots were reused: ids were the creation order
            self.generation = np.zeros(len(self.alive), dtype=np.int64)
            self.born = np.arange(len(self.alive), dtype=np.int64)
            self.created = self.size
            self._free = np.nonzero(~self.alive[: self.size])[0].tolist()
        self._free = deque(self._free)
        self.lock = threading.RLock()
        if "feature_store" not in state:  # checkpoints from before the store: the keyframes held their features
            self.feature_store = FeatureStore()
            for kf in self.keyframes.values():
                kf.keep_features_in(self.feature_store)

    # --- landmarks --------------------------------------------------------------------------------
    def _grow(self) -> None:
        cap = 2 * len(self.alive)
        for name in ("positions", "descriptors", "alive", "created_by", "n_visible", "n_found", "ref_distance",
                     "ref_octave", "generation", "born"):
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
            reused = [self._free.popleft() for _ in range(min(len(positions), len(self._free)))]
            fresh = len(positions) - len(reused)
            while self.size + fresh > len(self.alive):
                self._grow()
            ids = np.concatenate([np.array(reused, np.int64), np.arange(self.size, self.size + fresh)])  # [K]
            self.generation[reused] += 1
            self.born[ids] = self.created + np.arange(len(ids))
            self.created += len(ids)
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
            self.size += fresh
            return ids

    def add_observation(self, lm: int, kf: KeyFrame, kp: int) -> None:
        """Record that keyframe ``kf`` sees landmark ``lm`` at keypoint ``kp`` (nothing if ``lm`` died meanwhile)."""
        with self.lock:
            if not self.alive[lm]:  # culled by the backend after tracking matched it: its slot may be reused
                return
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
            if not self.observations[lm] and self.alive[lm]:
                self._kill(lm)

    def _kill(self, lm: int) -> None:
        """A landmark nobody sees any more dies; its slot waits in ``_free`` for a new landmark."""
        self.alive[lm] = False
        self.observations[lm] = {}  # a fresh dict: a popped one keeps its size
        self._free.append(int(lm))

    def remove_landmark(self, lm: int) -> None:
        """Delete a landmark and its observations."""
        with self.lock:
            for kf_id, kp in self.observations[lm].items():
                if kf_id in self.keyframes:
                    self.keyframes[kf_id].landmark_ids[kp] = -1
            if self.alive[lm]:  # a dead landmark's observations are already empty (_kill)
                self._kill(lm)

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
            self._kill(drop)

    def alive_ids(self) -> np.ndarray:
        """Ids [L] of living landmarks."""
        return np.nonzero(self.alive[: self.size])[0]

    # --- keyframes --------------------------------------------------------------------------------
    def add_keyframe(self, kf: KeyFrame) -> None:
        """Insert a keyframe (its observations are added by the caller); its features go to ``feature_store``."""
        kf.keep_features_in(self.feature_store)
        with self.lock:
            self.keyframes[kf.id] = kf

    def observer_counts(self, lm_ids) -> Counter:
        """Keyframe id -> how many of the landmarks ``lm_ids`` it observes (insertion order: the first landmark's
        observers first, which ``most_common`` keeps among equal counts)."""
        with self.lock:
            obs = self.observations
            # one counting pass over every observer of every point, in the order a loop per point would count
            return Counter(chain.from_iterable(obs[lm].keys() for lm in lm_ids))

    def covisibility(self, kf_id: int) -> Counter:
        """Keyframe id -> number of landmarks shared with keyframe ``kf_id``."""
        with self.lock:
            kf = self.keyframes[kf_id]
            count = self.observer_counts(kf.landmark_ids[kf.landmark_ids >= 0])
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
        """Ids of living landmarks observed by any of the keyframes, oldest first (matching breaks ties by this
        order, so an established point wins over a new one; ids are not the creation order, slots are reused)."""
        with self.lock:
            ids = [self.keyframes[k].landmark_ids for k in kf_ids if k in self.keyframes]
            if not ids:
                return np.zeros(0, dtype=np.int64)
            lm = np.unique(np.concatenate(ids))
            lm = lm[lm >= 0]
            lm = lm[self.alive[lm]]
            return lm[np.argsort(self.born[lm], kind="stable")]

    def graph_poses(self) -> dict[int, np.ndarray]:
        """Copy of the pose of every keyframe in the graph (id -> T_wc [4, 4]), retired ones left out."""
        with self.lock:
            return {k: kf.T_wc.copy() for k, kf in self.keyframes.items()}

    def poses(self) -> dict[int, np.ndarray]:
        """Pose of every keyframe ever made (id -> T_wc [4, 4]): the graph's, and retired ones through their parents."""
        with self.lock:
            out = self.graph_poses()
            for k in sorted(self.retired):
                out[k] = self.pose(k)
            return out

    def pose(self, kf_id: int) -> np.ndarray:
        """T_wc [4, 4] of a keyframe in the graph or retired from it (KeyError for an id never made)."""
        with self.lock:
            living, T_living_kf = self.anchor(kf_id)
            return self.keyframes[living].T_wc @ T_living_kf

    def anchor(self, kf_id: int) -> tuple[int, np.ndarray]:
        """(the keyframe in the graph that keyframe ``kf_id`` rides on, T_that_kf [4, 4]): itself and the identity
        for a keyframe in the graph; KeyError for an id never made."""
        with self.lock:
            if kf_id in self.keyframes:
                return int(kf_id), np.eye(4)
            r = self.retired[int(kf_id)]
            return r.parent, r.T_parent_kf.copy()

    def living(self, kf_id: int) -> int:
        """The keyframe in the graph that keyframe ``kf_id`` rides on (itself when it is in the graph)."""
        return self.anchor(kf_id)[0]

    def retire_keyframe(self, kf_id: int, parent: int) -> KeyFrame:
        """Take keyframe ``kf_id`` out of the graph: its observations go (a landmark it alone saw dies), its pose rides
        on ``parent`` (a keyframe in the graph) from now on; returns the removed keyframe."""
        with self.lock:
            if kf_id == parent or parent not in self.keyframes:
                raise ValueError(f"keyframe {kf_id}: parent {parent} must be another keyframe in the graph")
            kf = self.keyframes.pop(kf_id)
            for lm in kf.landmark_ids[kf.landmark_ids >= 0].tolist():
                self.remove_observation(lm, kf_id)
            for seen in self.plane_observations.values():
                seen.pop(kf_id, None)
            T_parent_kf = invert(self.keyframes[parent].T_wc) @ kf.T_wc
            for r in self.retired.values():  # those that rode on it ride on its parent: every parent is in the graph
                if r.parent == kf_id:
                    r.parent, r.T_parent_kf = parent, T_parent_kf @ r.T_parent_kf
            self.retired[kf_id] = RetiredKeyFrame(kf.id, kf.frame_index, kf.timestamp, parent, T_parent_kf)
            return kf
