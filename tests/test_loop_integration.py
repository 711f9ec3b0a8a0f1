"""Loop closure inside the running system: a lap around the synthetic room is detected and closed correctly."""
import numpy as np
import pytest

from ggfslam.backend.backend import Backend
from ggfslam.config import BackendConfig, TrackingConfig
from ggfslam.data.synthetic import SyntheticSequence
from ggfslam.eval.trajectory import trajectory_metrics
from ggfslam.frontend.tracker import OrbTracker
from ggfslam.geometry.se3 import invert


@pytest.mark.slow
def test_full_lap_closes_a_correct_loop():
    seq = SyntheticSequence(n_frames=1100, width=320, height=240, trajectory="orbit", seed=5, depth_noise=True)
    idx = list(range(0, 1100, 5))  # one lap of the room, 5 cm between frames
    frames = [seq[i] for i in idx]
    tcfg = TrackingConfig(n_features=1000)
    backend = Backend(seq.camera, tcfg, BackendConfig(loop_closure=True))
    tracker = OrbTracker(seq.camera, tcfg, backend)
    for f in frames:
        tracker.track(f)
    tracker.finish()
    assert backend.map.loops, "the lap back to the start was not detected"
    kfs = backend.map.keyframes
    for match, query, T_mq, _ in backend.map.loops:
        assert kfs[query].frame_index - kfs[match].frame_index > 500  # a real revisit, not a neighbour
        gt = invert(seq.poses[kfs[match].frame_index]) @ seq.poses[kfs[query].frame_index]
        assert np.linalg.norm((invert(gt) @ T_mq)[:3, 3]) < 0.02
    stamps, poses, lost = tracker.trajectory()
    assert not lost.any()
    assert trajectory_metrics(stamps, poses, seq.timestamps[idx], seq.poses[idx])["ate_rmse_cm"] < 1.5
