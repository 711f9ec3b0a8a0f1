"""Checkpoints are read without executing what they contain; crafted, foreign and old files are refused."""
import os
import pickle

import numpy as np
import pytest
import torch

from ggfslam.checkpoint import CHECKPOINT_FILE, FORMAT, load_checkpoint, unpickle_tracker
from ggfslam.errors import RunDirError


class _RunsCode:
    """Unpickling this runs a shell command (the classic pickle exploit)."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_a_checkpoint_crafted_to_run_code_is_refused(tmp_path):
    marker = tmp_path / "pwned"
    torch.save({"format": FORMAT, "next_frame": 3, "payload": _RunsCode(marker)}, tmp_path / CHECKPOINT_FILE)
    with pytest.raises(RunDirError, match=r"refused: .*GLOBAL (posix|os)\.system"):
        load_checkpoint(tmp_path)
    assert not marker.exists()


def test_a_tracker_pickle_crafted_to_run_code_is_refused(tmp_path):
    marker = tmp_path / "pwned"
    torch.save({"format": FORMAT, "tracker": pickle.dumps(_RunsCode(marker))}, tmp_path / CHECKPOINT_FILE)
    st = load_checkpoint(tmp_path)  # the outer file holds only bytes: fine
    with pytest.raises(RunDirError, match=r"refused: it refers to (posix|os)\.system"):
        unpickle_tracker(st)
    assert not marker.exists()


def test_a_tracker_pickle_may_not_call_even_an_allowed_class(tmp_path):
    from ggfslam.backend.slam_map import SlamMap

    class CallsConstructor:
        def __reduce__(self):
            return SlamMap, ()  # REDUCE on an allowed class would run its constructor

    torch.save({"format": FORMAT, "tracker": pickle.dumps(CallsConstructor())}, tmp_path / CHECKPOINT_FILE)
    with pytest.raises(RunDirError, match="refused: it calls 'SlamMap'"):
        unpickle_tracker(load_checkpoint(tmp_path))


def test_numpy_arrays_and_enums_still_load(tmp_path):
    from ggfslam.frontend.types import TrackingState
    from ggfslam.safe_load import load_tracker_pickle

    data = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "s": TrackingState(list(TrackingState)[0].value),
            "ids": {1, 2}, "u16": np.zeros(3, np.uint16)}
    back = load_tracker_pickle(pickle.dumps(data, protocol=pickle.HIGHEST_PROTOCOL))
    np.testing.assert_array_equal(back["a"], data["a"])
    assert back["s"] is data["s"] and back["ids"] == {1, 2} and back["u16"].dtype == np.uint16


@pytest.mark.parametrize("content, message", [
    ({"format": "ggfslam-checkpoint/0", "tracker": b"old"}, "format 'ggfslam-checkpoint/0'"),
    ({"weights": torch.zeros(3)}, "not a ggfslam checkpoint"),
])
def test_old_and_foreign_files_get_a_clear_error(tmp_path, content, message):
    torch.save(content, tmp_path / CHECKPOINT_FILE)
    with pytest.raises(RunDirError, match=message):
        load_checkpoint(tmp_path)


def test_a_truncated_checkpoint_is_reported_as_damaged(tmp_path):
    torch.save({"format": FORMAT, "x": torch.zeros(1000)}, tmp_path / CHECKPOINT_FILE)
    data = (tmp_path / CHECKPOINT_FILE).read_bytes()
    (tmp_path / CHECKPOINT_FILE).write_bytes(data[: len(data) // 2])
    with pytest.raises(RunDirError, match="damaged checkpoint"):
        load_checkpoint(tmp_path)
