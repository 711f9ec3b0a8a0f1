"""Runs that meet bad frames, errors and kills: nothing done is lost, and a resumed run is the run it would
have been."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from ggfslam import slam
from ggfslam.checkpoint import load_checkpoint
from ggfslam.config import config_from_dict, save_config
from ggfslam.data.synthetic import write_synthetic_sequence
from ggfslam.errors import DatasetError
from ggfslam.gaussians.ply import read_gaussians_ply

BAD = 13  # the frame whose depth PNG gets truncated


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    """A 24-frame rendered sequence in TUM layout (a folder a user would point ggfslam at)."""
    return write_synthetic_sequence(tmp_path_factory.mktemp("seq") / "room", n_frames=24, width=320, height=240)


def _config(path, **dataset):
    return config_from_dict({
        "name": "reliability", "dataset": {"kind": "tum", "path": str(path), **dataset},
        "tracking": {"keyframe_max_frames": 5},
        "mapping": {"iterations_per_keyframe": 5, "iterations_per_frame": 0, "final_iterations": 5,
                    "checkpoint_every": 2, "mesh": False, "train_width": 160, "eval_width": 160}}, "t")


@pytest.fixture(scope="module")
def clean_run(sequence, tmp_path_factory):
    """The uninterrupted run every other run is compared with."""
    out = tmp_path_factory.mktemp("clean") / "run"
    return out, slam.run(_config(sequence), out, progress=False)


def _depth_file(seq, index: int):
    rows = [r.split() for r in (seq / "depth.txt").read_text().splitlines() if r.strip() and not r.startswith("#")]
    return seq / rows[index][1]


def _truncated_copy(sequence, tmp_path):
    """A copy of the sequence whose frame BAD has a truncated depth PNG (half the bytes)."""
    import shutil

    seq = tmp_path / "damaged"
    shutil.copytree(sequence, seq)
    f = _depth_file(seq, BAD)
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2])
    return seq, f, data


def test_a_bad_frame_is_skipped_counted_and_marked(sequence, clean_run, tmp_path):
    seq, bad_file, _ = _truncated_copy(sequence, tmp_path)
    metrics = slam.run(_config(seq), tmp_path / "run", progress=False)
    run = tmp_path / "run"
    t = metrics["tracking"]
    assert t["frames_skipped"] == 1 and t["skipped"][0]["index"] == BAD and t["frames"] == 23
    assert str(bad_file) in t["skipped"][0]["error"]
    rows = [r.split() for r in (run / "tracking.txt").read_text().splitlines() if not r.startswith("#")]
    assert len(rows) == 24 and rows[BAD][0] == str(BAD) and rows[BAD][2] == "skipped"
    assert len(np.loadtxt(run / "trajectory.txt")) == 23
    assert metrics["trajectory"]["ate_pairs"] == 23 and metrics["trajectory"]["ate_rmse_cm"] < 3.0
    scored = [f["index"] for f in metrics["rendering"]["per_frame"]]
    assert BAD not in scored and len(scored) == 23
    assert json.loads((run / "run.json").read_text())["status"] == "finished"
    # `ggfslam eval` pairs the poses with their frames by timestamp, the skipped one left out
    again = slam.evaluate(run)
    assert [f["index"] for f in again["rendering"]["per_frame"]] == scored


def test_a_listed_image_that_is_missing_is_one_skipped_frame(sequence, tmp_path):
    import shutil

    seq = tmp_path / "missing"
    shutil.copytree(sequence, seq)
    gone = _depth_file(seq, 5)
    gone.unlink()
    cfg = _config(seq)
    ds = slam.open_dataset_from_config(cfg.dataset)  # opens: the frame fails only when it is read
    with pytest.raises(DatasetError, match="depth image not found"):
        ds[5]
    with pytest.raises(DatasetError, match="listed image .* not found"):  # ... unless bad frames are errors
        slam.open_dataset_from_config(_config(seq, on_bad_frame="error").dataset)


def test_too_many_bad_frames_end_the_run_with_its_outputs_saved(sequence, clean_run, tmp_path):
    seq, bad_file, _ = _truncated_copy(sequence, tmp_path)
    with pytest.raises(DatasetError, match=r"1 of 24 frames could not be read, more than dataset.max_bad_frames"):
        slam.run(_config(seq, max_bad_frames=0.0), tmp_path / "run", progress=False)


def test_a_run_ending_in_an_error_saves_what_it_has_and_resumes_to_the_same_result(sequence, clean_run, tmp_path):
    seq, bad_file, good_bytes = _truncated_copy(sequence, tmp_path)
    run = tmp_path / "run"
    cfg = _config(seq, on_bad_frame="error")
    with pytest.raises(DatasetError, match="cannot decode depth image"):
        slam.run(cfg, run, progress=False)
    info = json.loads((run / "run.json").read_text())
    assert info["status"] == "failed" and info["stopped_at_frame"] == BAD and str(bad_file) in info["error"]
    assert info["resume_from_frame"] == BAD and {"checkpoint", "trajectory", "map"} <= set(info["saved"])
    # what it had: the trajectory of the frames done, the map, a checkpoint at the frame it stopped at
    assert len(np.loadtxt(run / "trajectory.txt")) == BAD
    assert len(read_gaussians_ply(run / "gaussians.ply")["means"]) > 100
    assert load_checkpoint(run)["next_frame"] == BAD
    bad_file.write_bytes(good_bytes)  # the user repairs the file
    resumed = slam.run(cfg, run, progress=False, resume=True)
    clean, clean_metrics = clean_run
    np.testing.assert_array_equal(np.loadtxt(run / "trajectory.txt"), np.loadtxt(clean / "trajectory.txt"))
    assert (run / "gaussians.ply").read_bytes() == (clean / "gaussians.ply").read_bytes()
    assert resumed["rendering"]["psnr"] == clean_metrics["rendering"]["psnr"]
    info = json.loads((run / "run.json").read_text())
    assert info["status"] == "finished" and "error" not in info and info["resumed_at_frame"] == BAD


def _ggfslam(*args, env=None):
    return subprocess.Popen([sys.executable, "-c", "from ggfslam.cli import main; main()", *args],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow), pytest.param(2, marks=pytest.mark.slow)])
def test_a_run_killed_at_a_random_moment_resumes_to_the_same_result(sequence, clean_run, tmp_path, seed):
    clean, _ = clean_run
    cfg_file = tmp_path / "config.yaml"
    save_config(_config(sequence), cfg_file)
    run = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    start = time.perf_counter()
    p = _ggfslam("run", str(cfg_file), "--out", str(run), "--no-progress", env=env)
    # somewhere between start-up and the end of tracking (a clean run's tracking.txt has 24 rows)
    delay = np.random.default_rng(seed).uniform(0.2, 0.9)
    while p.poll() is None and not (run / "tracking.txt").exists():
        rows = len(load_checkpoint(run)["lines"]) if (run / "checkpoint.pt").exists() else 0
        if rows / 25 >= delay or time.perf_counter() - start > 300:
            break
        time.sleep(0.05)
    p.kill()  # SIGKILL: no handler runs, nothing is saved on the way out
    p.wait()
    info = json.loads((run / "run.json").read_text())
    assert info["status"] == "running"  # what a killed run leaves: it never got to say otherwise
    r = _ggfslam("run", "--resume", "--out", str(run), "--no-progress", env=env)
    _, err = r.communicate(timeout=600)
    assert r.returncode == 0, err.decode()[-2000:]
    np.testing.assert_array_equal(np.loadtxt(run / "trajectory.txt"), np.loadtxt(clean / "trajectory.txt"))
    assert (run / "gaussians.ply").read_bytes() == (clean / "gaussians.ply").read_bytes()
    # every output parses
    assert json.loads((run / "metrics.json").read_text())["tracking"]["frames"] == 24
    graph = json.loads((run / "graph.json").read_text())
    assert graph["keyframes"] and graph["factors"]
    assert load_checkpoint(run)["finished"]
    assert len(read_gaussians_ply(run / "gaussians_planarity.ply")["means"]) > 0
    assert not list(run.glob(".*.tmp-*")) and not list((run / "keyframes").glob(".*.tmp-*"))
    assert not list((run / "keyframe_features").glob(".*.tmp-*"))
    assert sorted(p.name for p in (run / "keyframe_features").iterdir()) == sorted(
        p.name for p in (clean / "keyframe_features").iterdir())


def test_ctrl_c_while_the_kernels_compile_stops_the_run_resumably_and_the_log_keeps_the_compile(
        sequence, clean_run, tmp_path, monkeypatch):
    """A fresh install's run waits for its kernel compile before the first frame: what the compile reports lands in
    the run's log.txt, and Ctrl-C during the wait cancels the compile and leaves a run that resumes from frame 0 to
    the uninterrupted result."""
    import logging

    class Compiling:  # stands in for kernel_warmup.KernelCompile: reports, then the user presses Ctrl-C
        def wait(self):
            logging.getLogger("ggfslam.kernels").info("kernels compiled in 3 s by 2 processes (test)")
            raise KeyboardInterrupt

        def cancel(self):
            pass

    monkeypatch.setattr(slam, "compile_kernels", lambda background: Compiling())
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        slam.run(_config(sequence), run, progress=False)
    assert "kernels compiled in 3 s by 2 processes (test)" in (run / "log.txt").read_text()
    info = json.loads((run / "run.json").read_text())
    assert info["status"] == "interrupted" and info["stopped_at_frame"] == 0 and info["resume_from_frame"] == 0
    monkeypatch.undo()
    slam.run(_config(sequence), run, progress=False, resume=True)
    np.testing.assert_array_equal(np.loadtxt(run / "trajectory.txt"), np.loadtxt(clean_run[0] / "trajectory.txt"))


def test_ctrl_c_stops_after_the_frame_with_everything_saved(sequence, clean_run, tmp_path, monkeypatch):
    import signal

    from ggfslam.data import sources

    real_open = sources.open_dataset_from_config

    def pressing_ctrl_c(c):  # the user presses Ctrl-C while frame 10 is read
        ds = real_open(c)
        cls = ds.__class__

        class Pressed(cls):
            def __getitem__(self, i):
                if i == 10:
                    os.kill(os.getpid(), signal.SIGINT)
                return cls.__getitem__(self, i)

        ds.__class__ = Pressed
        return ds

    monkeypatch.setattr(slam, "open_dataset_from_config", pressing_ctrl_c)
    handler_before = signal.getsignal(signal.SIGINT)  # SIG_IGN, not Python's handler, when pytest runs in the background
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        slam.run(_config(sequence), run, progress=False)
    info = json.loads((run / "run.json").read_text())
    # frame 10 was finished, then the run stopped where its state is whole
    assert info["status"] == "interrupted" and info["stopped_at_frame"] == 11 and info["resume_from_frame"] == 11
    assert len(np.loadtxt(run / "trajectory.txt")) == 11
    monkeypatch.undo()
    slam.run(_config(sequence), run, progress=False, resume=True)
    np.testing.assert_array_equal(np.loadtxt(run / "trajectory.txt"), np.loadtxt(clean_run[0] / "trajectory.txt"))
    assert signal.getsignal(signal.SIGINT) is handler_before  # the handler is put back
