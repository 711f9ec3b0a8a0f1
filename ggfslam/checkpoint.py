"""Resumable checkpoints of a run: tracker + backend state, the Gaussian map and its optimizer, RNGs.

``checkpoint.pt`` in the run directory (``torch.save``; written to a temporary file and renamed, so an
interrupted write never destroys the previous checkpoint). The tracker (with its SLAM map and factor-graph
state) is stored as a pickle inside it; the map as tensors. ``ggfslam render`` needs only the map part and the
poses. Reading never executes what the file contains: the file is read with ``torch.load(weights_only=True)``
and the tracker with an allow-list unpickler (``ggfslam.safe_load``), so a run folder someone sent you is safe
to open; a file asking for anything else is refused with ``RunDirError``.
"""
from __future__ import annotations

import pickle
import random
from pathlib import Path

import numpy as np
import torch

from ggfslam.atomic import atomic_path
from ggfslam.errors import RunDirError
from ggfslam.safe_load import UnsafeCheckpoint, load_tracker_pickle, torch_load_safely

CHECKPOINT_FILE = "checkpoint.pt"
FORMAT = "ggfslam-checkpoint/1"


def rng_state() -> dict:
    """States of the python, numpy and torch global generators."""
    return {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}


def set_rng_state(st: dict) -> None:
    """Restore ``rng_state()``."""
    random.setstate(st["python"])
    np.random.set_state(st["numpy"])
    torch.set_rng_state(st["torch"])


def save_checkpoint(run_dir: Path, *, next_frame: int, tracker, mapper=None, pending=None, lines=None,
                    timer=None, finished: bool = False, rss=None, skipped=None) -> Path:
    """Write ``checkpoint.pt``: everything needed to continue the run at frame ``next_frame``."""
    backend = getattr(tracker, "backend", None)
    if backend is not None:
        backend.drain()  # a keyframe half-way through bundle adjustment cannot be pickled consistently
    lock = tracker.map.lock if getattr(tracker, "map", None) is not None else None
    if lock is not None:
        with lock:
            tracker_blob = pickle.dumps(tracker, protocol=pickle.HIGHEST_PROTOCOL)
            kf_poses = tracker.map.poses()
    else:
        tracker_blob = pickle.dumps(tracker, protocol=pickle.HIGHEST_PROTOCOL)
        kf_poses = {}
    state = {
        "format": FORMAT, "next_frame": int(next_frame), "finished": finished, "tracker": tracker_blob,
        "keyframe_poses": kf_poses, "lines": list(lines or []), "rng": rng_state(),
        "timer": None if timer is None else {"total": dict(timer.total), "calls": dict(timer.calls)},
        "mapper": None if mapper is None else mapper.state(),
        "kf_frames": {} if mapper is None else {k: mapper.store.frame_index(k) for k in mapper.store.ids()},
        "pending": {} if pending is None else {int(k): v for k, v in pending.items()},
        "rss": list(rss or []),
        "skipped": list(skipped or []),  # bad frames passed over so far: {"index", "error"}
    }
    path = Path(run_dir) / CHECKPOINT_FILE
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    return path


def load_checkpoint(run_dir: Path) -> dict:
    """Read ``checkpoint.pt`` of a run (the tracker stays pickled: ``unpickle_tracker``)."""
    path = Path(run_dir) / CHECKPOINT_FILE
    if not path.is_file():
        raise RunDirError(f"{path}: no checkpoint (the run wrote none: mapping.checkpoint_every, or it never "
                          "reached its first checkpoint)")
    try:
        st = torch_load_safely(path)
    except pickle.UnpicklingError as e:  # what weights_only raises for a global outside the allow-list
        # torch's message is a paragraph: keep the line naming what the file asked for
        what = next((line.strip() for line in str(e).splitlines() if "GLOBAL" in line), "")
        raise RunDirError(f"{path}: refused: it asks for more than tensors and arrays (not a ggfslam checkpoint, or "
                          f"one crafted to run code on load){': ' + what if what else ''}") from None
    except Exception as e:  # torch raises many types for a damaged archive
        raise RunDirError(f"{path}: damaged checkpoint ({e.__class__.__name__}: {e})") from None
    if not isinstance(st, dict) or "format" not in st:
        raise RunDirError(f"{path}: not a ggfslam checkpoint (no format field)")
    if st["format"] != FORMAT:
        raise RunDirError(f"{path}: checkpoint format {st['format']!r}, this ggfslam reads {FORMAT!r}: resume or "
                          "render it with the ggfslam version that wrote it")
    st["_path"] = str(path)  # for unpickle_tracker's messages
    return st


def unpickle_tracker(st: dict):
    """The tracker stored in a checkpoint (threads restarted by the objects themselves), read with the
    allow-list unpickler; RunDirError when the pickle asks for anything else."""
    try:
        return load_tracker_pickle(st["tracker"])
    except UnsafeCheckpoint as e:
        raise RunDirError(f"{st.get('_path', CHECKPOINT_FILE)}: refused: {e} (crafted to run code on load?)") from None
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, KeyError, AttributeError) as e:
        raise RunDirError(f"{st.get('_path', CHECKPOINT_FILE)}: damaged tracker state ({e.__class__.__name__}: "
                          f"{e})") from None
