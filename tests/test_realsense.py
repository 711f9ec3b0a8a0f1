"""RealSense input without a camera: frames of a synthetic sequence injected into pyrealsense2's software device,
recorded by librealsense's own recorder, and played back through the pipeline a camera goes through (colour and
depth streams, alignment of depth to colour, intrinsics and depth scale read from the device)."""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from ggfslam.cli import app

runner = CliRunner()


def record_sequence(dataset, path: Path, fps: int = 30, slower: float = 1.0) -> Path:
    """Write ``dataset``'s frames as a RealSense recording through a software device (colour rgb8, depth z16 in
    millimetres, the dataset's pinhole intrinsics for both, registered), its timestamps stretched ``slower``
    times. Frames are injected on that clock: the recorder stores when each frame reached it, and a real-time
    playback replays those times."""
    import pyrealsense2 as rs

    cam = dataset.camera
    dev = rs.software_device()
    sensors, profiles = [], []
    for uid, (name, stream, fmt, bpp) in enumerate([("Depth", rs.stream.depth, rs.format.z16, 2),
                                                     ("Color", rs.stream.color, rs.format.rgb8, 3)]):
        intr = rs.intrinsics()
        intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy = cam.width, cam.height, cam.fx, cam.fy, \
            cam.cx, cam.cy
        intr.model, intr.coeffs = rs.distortion.none, [0.0] * 5
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid, vs.width, vs.height, vs.fps, vs.bpp, vs.fmt, vs.intrinsics = \
            stream, 0, uid, cam.width, cam.height, fps, bpp, fmt, intr
        sensor = dev.add_sensor(name)
        profiles.append(sensor.add_video_stream(vs))
        sensors.append(sensor)
    sensors[0].add_read_only_option(rs.option.depth_units, 0.001)
    profiles[0].register_extrinsics_to(profiles[1], _identity_extrinsics(rs))
    dev.create_matcher(rs.matchers.dlr_c)
    recorder = rs.recorder(str(path), dev)
    sync = rs.syncer()
    for sensor, profile in zip(sensors, profiles):
        sensor.open(profile)
        sensor.start(sync)
    t0, stamps = time.perf_counter(), np.asarray(dataset.timestamps)
    for i in range(len(dataset)):
        time.sleep(max(0.0, t0 + slower * (stamps[i] - stamps[0]) - time.perf_counter()))
        f = dataset[i]
        depth = np.round(f.depth * 1000.0).astype(np.uint16)  # [H, W] mm
        rgb = np.round(f.rgb * 255.0).astype(np.uint8)  # [H, W, 3]
        for sensor, profile, pixels, bpp in zip(sensors, profiles, (depth, rgb), (2, 3)):
            vf = rs.software_video_frame()
            vf.pixels, vf.bpp, vf.stride = np.ascontiguousarray(pixels), bpp, bpp * cam.width
            vf.timestamp, vf.domain, vf.frame_number = 1000.0 * slower * f.timestamp, rs.timestamp_domain.hardware_clock, i
            vf.profile = profile.as_video_stream_profile()
            sensor.on_video_frame(vf)
        sync.wait_for_frames(2000)
    for sensor in sensors:
        sensor.stop()
        sensor.close()
    del recorder  # closes the file
    return path


def _identity_extrinsics(rs):
    e = rs.extrinsics()
    e.rotation, e.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0, 0.0, 0.0]
    return e


SLOWER = 2.0  # the 30 frames last 2 s (15 Hz)


@pytest.fixture(scope="module")
def recording(tmp_path_factory, sequence):
    pytest.importorskip("pyrealsense2")
    path = tmp_path_factory.mktemp("rs") / "synthetic.db3"  # librealsense 2.57+ records ROS 2 bags
    return record_sequence(sequence, path, fps=15, slower=SLOWER)


def test_without_pyrealsense2_the_error_says_how_to_install_it(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import fails as if not installed
    res = runner.invoke(app, ["live", "--source", "realsense", "--out", str(tmp_path / "run")])
    assert res.exit_code == 2 and "pip install 'ggfslam[realsense]'" in res.output, res.output
    assert not (tmp_path / "run").exists()


def test_without_a_camera_the_error_is_one_line(tmp_path):
    rs = pytest.importorskip("pyrealsense2")
    if len(rs.context().query_devices()):
        pytest.skip("a RealSense camera is connected")
    for source, expect in (("realsense", "no RealSense camera found"),
                           ("realsense:123456", "no RealSense camera found"),
                           (f"realsense:{tmp_path / 'missing.bag'}", "recording not found")):
        res = runner.invoke(app, ["live", "--source", source, "--out", str(tmp_path / "run")])
        assert res.exit_code == 2 and expect in res.output, res.output
        assert len(res.output.strip().splitlines()) <= 2  # one message (wrapped at most once), no traceback
    assert not (tmp_path / "run").exists()


def test_injected_frames_come_out_of_the_camera_path_as_they_went_in(recording, sequence, tmp_path):
    from ggfslam.config import config_from_dict
    from ggfslam.sources.realsense import RealSenseSource

    src = RealSenseSource(recording=recording, capacity=len(sequence) + 1)  # the test takes every frame
    cfg = config_from_dict({"dataset": {"kind": "synthetic"}}, "test")
    seq, cfg2 = src.open(cfg, tmp_path / "run")
    try:
        cam, ref = seq.camera, sequence.camera
        assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == pytest.approx(
            (ref.fx, ref.fy, ref.cx, ref.cy, ref.width, ref.height), rel=1e-6)
        assert src.depth_scale == pytest.approx(0.001)
        assert cfg2.dataset.kind == "tum" and Path(cfg2.dataset.path) == tmp_path / "run" / "input"
        got = list(src.start())
    finally:
        src.close()
    # librealsense's syncer may pass over framesets of a recording: frames are matched by timestamp
    stamps = SLOWER * np.asarray(sequence.timestamps)
    assert len(got) >= 0.8 * len(sequence) and src.stats.dropped == []  # librealsense may skip a few
    for a in got:
        j = int(np.argmin(np.abs(stamps - a.frame.timestamp)))
        assert a.frame.timestamp == pytest.approx(stamps[j], abs=1e-6)
        f = sequence[j]
        np.testing.assert_allclose(a.frame.rgb, np.round(f.rgb * 255) / 255, atol=1e-6)
        valid = f.depth > 0
        # aligned to colour by librealsense (identical cameras): the same pixels in millimetre steps, but for a
        # rim its pixel-corner projection leaves empty
        close = np.abs(a.frame.depth - f.depth) <= 0.0006
        assert close[valid].mean() > 0.95
        assert close[valid & (a.frame.depth > 0)].mean() > 0.995
        assert (a.frame.depth[~valid] == 0).all()


def test_a_live_run_on_a_recording_tracks_and_leaves_a_folder_that_reads_back(recording, sequence, tmp_path,
                                                                              monkeypatch):
    from ggfslam.data.tum import TUMDataset
    from ggfslam.data.trajectory_io import read_tum_trajectory
    from ggfslam.eval.trajectory import trajectory_metrics

    monkeypatch.setenv("GGFSLAM_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "run"
    res = runner.invoke(app, ["live", "--source", f"realsense:{recording}", "--out", str(out), "--no-progress",
                              "--set", "mapping.iterations_per_keyframe=10", "--set", "mapping.final_seconds=5",
                              "--set", "mapping.eval_stride=4"])
    assert res.exit_code == 0, res.output
    m = json.loads((out / "metrics.json").read_text())
    live = m["live"]
    assert "RealSense recording" in live["source"] and live["frames_received"] >= 0.8 * len(sequence)
    assert live["frames_processed"] + live["frames_dropped"] == live["frames_received"]
    assert live["frames_processed"] >= 10
    # the frames the run took are recorded in TUM layout; the run's config reads them
    rec = TUMDataset(out / "input")
    assert len(rec) == live["frames_processed"] and rec.camera.fx == pytest.approx(sequence.camera.fx)
    stamps, poses = read_tum_trajectory(out / "trajectory.txt")
    np.testing.assert_allclose(stamps, rec.timestamps, atol=1e-6)
    # against the synthetic ground truth at the same timestamps
    ate = trajectory_metrics(stamps / SLOWER, poses, np.asarray(sequence.timestamps), sequence.gt_poses, 0.01, 1)
    assert ate["ate_rmse_cm"] < 2.0, ate
    assert m["rendering"]["frames"] >= 1 and m["rendering"]["psnr"] > 15
    res = runner.invoke(app, ["render", str(out), "--out", str(tmp_path / "renders")])
    assert res.exit_code == 0, res.output
