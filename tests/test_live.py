"""Live input: a run fed by a replay on time (frames dropped while the system is busy) writes a complete, consistent
run folder; Ctrl-C ends the input and the run still finishes with every output."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from ggfslam.cli import app

runner = CliRunner()
CONFIG = Path(__file__).parents[1] / "configs" / "synthetic" / "default.yaml"
SMALL = ["--set", "dataset.synthetic.n_frames=30", "--set", "dataset.synthetic.width=160",
         "--set", "dataset.synthetic.height=120", "--set", "mapping.iterations_per_keyframe=10",
         "--set", "mapping.final_iterations=10", "--set", "mapping.eval_stride=4"]


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("GGFSLAM_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache"


def test_a_fast_replay_drops_frames_and_the_run_folder_accounts_for_every_one(cache, tmp_path):
    out = tmp_path / "live"
    res = runner.invoke(app, ["live", str(CONFIG), "--source", "replay", "--rate", "8", "--queue", "1",
                              "--out", str(out), "--no-progress", *SMALL])
    assert res.exit_code == 0, res.output
    m = json.loads((out / "metrics.json").read_text())
    live = m["live"]
    assert live["frames_received"] == 30 and live["stopped_by"] is None
    saved = (out / "config.yaml").read_text()  # the live defaults beneath the config; concurrency forced
    assert "n_offsets: 5" in saved and "train_width: 320" in saved and "realtime: true" in saved
    assert live["frames_dropped"] > 0, live  # 240 Hz is more than this machine tracks
    assert live["frames_processed"] + live["frames_dropped"] + live["frames_skipped"] == 30
    assert 0 < live["latency_ms_p50"] <= live["latency_ms_p95"]
    rows = [r.split() for r in (out / "tracking.txt").read_text().splitlines() if not r.startswith("#")]
    assert sorted(int(r[0]) for r in rows) == list(range(30))  # every frame has a row: processed or dropped
    assert sum(r[2] == "dropped" for r in rows) == live["frames_dropped"]
    stamps = np.loadtxt(out / "trajectory.txt", usecols=0)
    assert len(stamps) == live["frames_processed"] == m["trajectory"]["ate_pairs"]
    dropped = {int(r[0]) for r in rows if r[2] == "dropped"}
    expect = np.loadtxt(out / "groundtruth.txt", usecols=0)[[i for i in range(30) if i not in dropped]]
    np.testing.assert_allclose(stamps, expect, atol=1e-6)  # the poses are the processed frames', in order
    # eval reads the folder back to the same ATE and renders the processed frames
    before = m["trajectory"]["ate_rmse_cm"]
    res = runner.invoke(app, ["eval", str(out)])
    assert res.exit_code == 0, res.output
    assert json.loads((out / "metrics.json").read_text())["trajectory"]["ate_rmse_cm"] == pytest.approx(before)


def test_bad_sources_are_one_line(tmp_path):
    for bad, expect in (("camera", "replay[:PATH]"), ("replay:", "replay[:PATH]"), ("folder", "folder:PATH"),
                        (f"folder:{tmp_path / 'nothing'}", "folder to watch not found")):
        res = runner.invoke(app, ["live", "--source", bad, "--out", str(tmp_path / "x")])
        assert res.exit_code == 2 and expect in res.output, res.output
    assert not (tmp_path / "x").exists()


def test_ctrl_c_ends_the_input_and_the_run_finishes(tmp_path):
    """SIGINT in the middle of a slow replay: exit status 0, a complete folder that eval and render read, and the
    frames after the stop never arrived."""
    out = tmp_path / "live"
    env = {**os.environ, "GGFSLAM_CACHE": str(tmp_path / "cache")}
    cmd = [sys.executable, "-m", "ggfslam.cli", "live", str(CONFIG), "--source", "replay", "--rate", "0.2",
           "--out", str(out), "--no-progress", *SMALL]  # 1 s of sequence at 30 Hz: 5 s of replay
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    log = out / "log.txt"
    try:
        deadline = time.time() + 300
        while not (log.is_file() and "decoding" in log.read_text()):  # the replay starts (kernels are loaded)
            assert time.time() < deadline and proc.poll() is None, proc.stdout.read() if proc.poll() else "slow"
            time.sleep(0.2)
        time.sleep(2.0)  # about 12 of the 30 frames
        proc.send_signal(signal.SIGINT)
        output, _ = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, output[-3000:]
    assert "the input ends at frame" in (out / "log.txt").read_text() and "input ended by" in output
    m = json.loads((out / "metrics.json").read_text())
    assert m["live"]["stopped_by"] == "SIGINT" and 0 < m["live"]["frames_received"] < 30
    assert json.loads((out / "run.json").read_text())["status"] == "finished"
    for name in ("trajectory.txt", "keyframes.txt", "graph.json", "gaussians.ply", "mesh.ply", "checkpoint.pt"):
        assert (out / name).is_file(), name
    assert runner.invoke(app, ["eval", str(out)]).exit_code == 0
    res = runner.invoke(app, ["render", str(out), "--out", str(tmp_path / "renders")])
    assert res.exit_code == 0, res.output
    assert list((tmp_path / "renders").glob("*_rgb.png"))


def test_a_second_ctrl_c_during_the_final_training_saves_a_checkpoint_and_stops(tmp_path):
    out = tmp_path / "live"
    env = {**os.environ, "GGFSLAM_CACHE": str(tmp_path / "cache")}
    cmd = [sys.executable, "-m", "ggfslam.cli", "live", str(CONFIG), "--source", "replay", "--rate", "0.5",
           "--out", str(out), "--no-progress", *SMALL, "--set", "mapping.final_seconds=120"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    log = out / "log.txt"
    try:
        deadline = time.time() + 300
        while not (log.is_file() and "decoding" in log.read_text()):
            assert time.time() < deadline and proc.poll() is None, proc.stdout.read() if proc.poll() else "slow"
            time.sleep(0.2)
        time.sleep(1.5)
        proc.send_signal(signal.SIGINT)  # ends the input
        while "final global BA" not in log.read_text():  # the backend has finished: the final training follows
            assert time.time() < deadline and proc.poll() is None, "slow"
            time.sleep(0.2)
        time.sleep(2.0)
        started = time.time()
        proc.send_signal(signal.SIGINT)  # stops at once, saving a checkpoint
        output, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, output[-3000:]
    assert time.time() - started < 60  # not the 120 s of final training
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "interrupted" and "checkpoint" in info["saved"], info
    assert (out / "checkpoint.pt").is_file() and (out / "gaussians.ply").is_file()
