"""Keyframes' ORB features: in memory, or on disk with a bounded in-memory cache.

A keyframe's features (~1500 keypoints: pixels, octaves, descriptors, depths, camera-frame points; ~130 KB) are
read when it is tracked against, bundle-adjusted, fused, culled or verified as a loop candidate: mostly the recent
keyframes, the old ones again when the camera comes back. Kept in memory for the whole run they are what made a long
run's memory grow with every keyframe. Attached to a folder (``attach``: the run directory's
``keyframe_features/``), the store writes each keyframe's features once as ``kf_<id>.npy`` when it is added and keeps
only the ``cache_size`` most recently used in memory; the rest are read back on demand. Features never change after
a keyframe is made, so the file is the only copy needed and a checkpoint pickles the store as its folder and ids.
Without a folder (unit tests, notebooks, a map built by hand) every keyframe's features stay in memory.
"""
from __future__ import annotations

import dataclasses
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from ggfslam.atomic import atomic_path
from ggfslam.errors import RunDirError
from ggfslam.frontend.features import Features

_FIELDS = tuple(f.name for f in dataclasses.fields(Features))  # uv, octave, descriptors, depth, points_cam


class FeatureStore:
    """Features by keyframe id; ``attach`` moves them to disk behind an LRU cache of ``cache_size`` keyframes."""

    def __init__(self, cache_size: int = 64):
        self.cache_size = cache_size
        self.dir: Path | None = None  # None: everything in memory
        self._ids: set[int] = set()
        self._cache: OrderedDict[int, Features] = OrderedDict()
        self._lock = threading.Lock()
        self.reads = 0  # features read back from disk (cache misses), for the run's metrics

    def __contains__(self, kf_id: int) -> bool:
        return int(kf_id) in self._ids

    def __len__(self) -> int:
        return len(self._ids)

    def path(self, kf_id: int) -> Path:
        """The file of keyframe kf_id's features (attached stores only)."""
        if self.dir is None:
            raise ValueError("this feature store keeps everything in memory: attach() it to a folder first")
        return self.dir / f"kf_{int(kf_id):06d}.npy"

    def attach(self, directory: str | Path, cache_size: int | None = None) -> None:
        """Keep features in ``directory`` from now on (those held so far are written there); a store from a
        checkpoint is pointed at the run's folder again (the folder may have moved) and checks its files."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        with self._lock:
            if cache_size is not None:
                self.cache_size = cache_size
            self.dir = directory
            for kf_id, f in self._cache.items():
                self._write(kf_id, f)
            missing = [k for k in sorted(self._ids) if k not in self._cache and not self.path(k).is_file()]
            if missing:
                raise RunDirError(f"{directory}: the features of {len(missing)} keyframe(s) the checkpoint refers to "
                                  f"are missing (first: {self.path(missing[0]).name}); the run folder is incomplete")
            for f in directory.glob("kf_*.npy"):  # keyframes made after the checkpoint are made again when resumed
                if int(f.stem[3:]) not in self._ids:
                    f.unlink()
            self._trim()

    def put(self, kf_id: int, features: Features) -> None:
        """Store a new keyframe's features (written through to disk when attached)."""
        kf_id = int(kf_id)
        if self.dir is not None:
            self._write(kf_id, features)
        with self._lock:
            self._ids.add(kf_id)
            self._cache[kf_id] = features
            self._cache.move_to_end(kf_id)
            self._trim()

    def get(self, kf_id: int) -> Features:
        """Keyframe kf_id's features (read back from disk when not cached)."""
        kf_id = int(kf_id)
        with self._lock:
            f = self._cache.get(kf_id)
            if f is not None:
                self._cache.move_to_end(kf_id)
                return f
            if kf_id not in self._ids:
                raise KeyError(f"keyframe {kf_id}: no features stored")
            f = self._read(kf_id)
            self.reads += 1
            self._cache[kf_id] = f
            self._trim()
            return f

    def _trim(self) -> None:
        if self.dir is None:
            return
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)

    def _write(self, kf_id: int, f: Features) -> None:
        # one .npy of a structured array, a row per keypoint: read back in ~0.2 ms where an .npz took 0.65
        arrays = [np.asarray(getattr(f, name)) for name in _FIELDS]
        rows = np.empty(len(f), np.dtype([(n, a.dtype, a.shape[1:]) for n, a in zip(_FIELDS, arrays)]))  # [N]
        for n, a in zip(_FIELDS, arrays):
            rows[n] = a
        with atomic_path(self.path(kf_id)) as tmp:
            np.save(tmp, rows)

    def _read(self, kf_id: int) -> Features:
        path = self.path(kf_id)
        try:
            rows = np.load(path, allow_pickle=False)  # [N] structured
            return Features(**{name: np.ascontiguousarray(rows[name]) for name in _FIELDS})
        except (OSError, KeyError, ValueError) as e:
            raise RunDirError(f"{path}: keyframe {kf_id}'s features cannot be read ({e.__class__.__name__}: "
                              f"{e})") from None

    def __getstate__(self) -> dict:  # checkpoints: an attached store is its folder and ids; the files hold the rest
        with self._lock:
            state = {"cache_size": self.cache_size, "dir": None if self.dir is None else str(self.dir),
                     "ids": sorted(self._ids), "reads": self.reads}
            if self.dir is None:
                state["features"] = dict(self._cache)
            return state

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["cache_size"])
        self.dir = None if state["dir"] is None else Path(state["dir"])
        self._ids = set(state["ids"])
        self.reads = state.get("reads", 0)
        self._cache.update(state.get("features", {}))
