"""Reading checkpoints without executing what they contain.

A pickle can name any importable callable and call it while loading, so ``pickle.load`` of a file someone sent
you runs their code. ggfslam's ``checkpoint.pt`` is read in two restricted steps instead:

- the file itself with ``torch.load(weights_only=True)``: tensors, numbers, strings, lists, dicts, and numpy
  arrays (``NUMPY_GLOBALS``), nothing else;
- the tracker inside it (a pickle of the ORB tracker, its SLAM map and place-recognition database) with
  ``RestrictedUnpickler``: every global it names must be one of the classes in ``tracker_classes()`` (looked up
  by module and name, never imported on the file's say), and the only calls it may make are numpy's array
  and dtype reconstruction and the lookup of an enum member. Objects are otherwise rebuilt the way pickle
  rebuilds them (``cls.__new__`` plus their state), so no constructor runs.

Anything else is refused with ``UnsafeCheckpoint`` naming what the file asked for.
"""
from __future__ import annotations

import enum
import io
import pickle
from functools import cache

import numpy as np
import torch

# what numpy arrays need: reconstruction from bytes, the array type and its dtype (and dtype classes)
NUMPY_GLOBALS = [np._core.multiarray._reconstruct, np.ndarray, np.dtype, np._core.numeric._frombuffer,
                 *{type(np.dtype(t)) for t in np.sctypeDict.values() if t is not np.void}]


class UnsafeCheckpoint(Exception):
    """A checkpoint asked for a global or a call outside the allow-list."""


@cache
def tracker_classes() -> dict[tuple[str, str], type]:
    """The classes a pickled tracker may contain: (module, name) -> class."""
    from ggfslam.backend.backend import Backend, BackendStats
    from ggfslam.backend.feature_store import FeatureStore
    from ggfslam.backend.loop_closure import LoopClosureConfig, LoopDetector, _Keyframe
    from ggfslam.backend.place_recognition import BowVector, KeyframeDatabase, Vocabulary
    from ggfslam.backend.slam_map import KeyFrame, RetiredKeyFrame, SlamMap
    from ggfslam.config import BackendConfig, TrackingConfig
    from ggfslam.data.types import Camera, Frame
    from ggfslam.frontend.dense_odometry import DenseOdometry
    from ggfslam.frontend.features import Features, OrbExtractor
    from ggfslam.frontend.planes import Plane
    from ggfslam.frontend.tracker import FrameRecord, OrbTracker
    from ggfslam.frontend.types import TrackingState

    classes = [Backend, BackendStats, LoopClosureConfig, LoopDetector, _Keyframe, BowVector, KeyframeDatabase,
               Vocabulary, KeyFrame, RetiredKeyFrame, SlamMap, BackendConfig, TrackingConfig, Camera, Frame,
               DenseOdometry, Features, FeatureStore, OrbExtractor, Plane, FrameRecord, OrbTracker, TrackingState, set,
               frozenset]
    out = {(c.__module__, c.__qualname__): c for c in classes}
    out.update({(g.__module__, g.__qualname__): g for g in NUMPY_GLOBALS})
    # numpy pickles record the module that defined a function at save time (numpy 1.x: numpy.core)
    out.update({(m.replace("_core", "core"), n): g for (m, n), g in list(out.items()) if m.startswith("numpy._core")})
    return out


_CALLABLE = (np._core.multiarray._reconstruct, np._core.numeric._frombuffer, np.dtype)


class RestrictedUnpickler(pickle._Unpickler):
    """A pickle reader that resolves only allow-listed globals and calls nothing but numpy/enum reconstruction."""

    dispatch = dict(pickle._Unpickler.dispatch)

    def __init__(self, data: bytes, allowed: dict[tuple[str, str], type]):
        super().__init__(io.BytesIO(data))
        self.allowed = allowed

    def find_class(self, module: str, name: str):
        """The allowed class or function (module, name); anything else is refused."""
        try:
            return self.allowed[(module, name)]
        except KeyError:
            raise UnsafeCheckpoint(f"it refers to {module}.{name}, which a ggfslam checkpoint never contains") from None

    def _load_reduce(self):
        args = self.stack.pop()
        func = self.stack[-1]
        allowed = func in _CALLABLE or (isinstance(func, type) and (
            issubclass(func, enum.Enum) or issubclass(func, np.dtype)))
        if not allowed:
            raise UnsafeCheckpoint(f"it calls {getattr(func, '__qualname__', func)!r}, which loading a ggfslam "
                                   "checkpoint never does")
        self.stack[-1] = func(*args)

    def _refuse(self):
        raise UnsafeCheckpoint("it uses a pickle opcode that calls a constructor (INST/OBJ)")

    dispatch[pickle.REDUCE[0]] = _load_reduce
    dispatch[pickle.INST[0]] = _refuse
    dispatch[pickle.OBJ[0]] = _refuse


def load_tracker_pickle(data: bytes):
    """Unpickle a tracker written by ``pickle.dumps`` with ``RestrictedUnpickler``."""
    return RestrictedUnpickler(data, tracker_classes()).load()


def torch_load_safely(path) -> object:
    """``torch.load`` of tensors, plain containers and numpy arrays only (``weights_only=True``)."""
    with torch.serialization.safe_globals(NUMPY_GLOBALS):
        return torch.load(path, map_location="cpu", weights_only=True)
