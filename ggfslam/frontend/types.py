"""Result types shared by every tracker."""
from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np


class TrackingState(enum.Enum):
    """Tracking state of a frame."""

    NOT_INITIALIZED = "not_initialized"
    OK = "ok"
    LOST = "lost"
    RELOCALIZED = "relocalized"


@dataclass
class TrackResult:
    """Outcome of tracking one frame."""

    T_wc: np.ndarray  # [4, 4] camera-to-world estimate at the time of tracking
    ok: bool  # the pose was estimated from this frame's data
    fitness: float  # tracker-specific quality in [0, 1]
    state: TrackingState = TrackingState.OK
    keyframe: bool = False
    matches: int = 0
    keyframe_id: int = -1  # id of the keyframe this frame became (when ``keyframe``)
    rests_at: int = -1  # a keyframe due by time was not made: the camera rests at this keyframe's view
