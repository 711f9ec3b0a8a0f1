"""``ggfslam batch`` on a local Ray instance with 2 CPUs: tiny synthetic runs equal to the same runs made one by
one, a broken config as one failed row, a second invocation that skips everything, a failing run retried and later
resumed from its checkpoint."""
from __future__ import annotations

import contextlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from ggfslam.cli import app

REPO = Path(__file__).parents[1]
TINY = {"name": "tiny", "dataset": {"kind": "synthetic", "synthetic": {
            "n_frames": 12, "width": 160, "height": 120, "depth_noise": False}},
        "mapping": {"iterations_per_keyframe": 5, "iterations_per_frame": 0, "final_iterations": 5, "eval_stride": 3,
                    "mesh": False}}
# four runs of the tiny sequence, differing in what they compute
ENTRIES = [("tiny-800", ["tracking.n_features=800"]), ("tiny-1200", ["tracking.n_features=1200"]),
           ("tiny-seed1", ["runtime.seed=1"]), ("tiny-ggf-off", ["ggf.enabled=false"])]
BAD = 13  # frame whose depth PNG the damaged sequence truncates


def _write_yaml(path: Path, data: dict) -> Path:
    import yaml

    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _rows(out: Path) -> list[dict]:
    """The rows of a batch's results.json."""
    return json.loads((out / "results.json").read_text())["rows"]


@contextlib.contextmanager
def _one_thread():
    """torch, numba and OpenCV of this process pinned to one thread, as a batch task with num_cpus 1 has them."""
    import cv2
    import numba
    import torch

    from ggfslam.batch.task import pin_threads

    before = torch.get_num_threads(), numba.get_num_threads(), cv2.getNumThreads()
    try:
        pin_threads(1)
        yield
    finally:
        torch.set_num_threads(before[0])
        numba.set_num_threads(before[1])
        cv2.setNumThreads(before[2])


@pytest.fixture(scope="module")
def batch_dir(tmp_path_factory):
    """A folder with the plan (4 tiny runs and a broken config), its own sequence cache, and the batch run there
    once through the command line."""
    root = tmp_path_factory.mktemp("batch")
    mp = pytest.MonkeyPatch()
    mp.setenv("GGFSLAM_CACHE", str(root / "cache"))
    _write_yaml(root / "tiny.yaml", TINY)
    (root / "broken.yaml").write_text("name: broken\ndataset: {kind: synthetic, synthetic: {n_frames: -3}}\n")
    plan = {"name": "tiny-plan",
            "sequences": [{"config": "tiny.yaml", "name": n, "set": s} for n, s in ENTRIES] + ["broken.yaml"],
            "num_cpus": 1}
    _write_yaml(root / "plan.yaml", plan)
    res = CliRunner().invoke(app, ["batch", str(root / "plan.yaml"), "--out", str(root / "out"), "--ray", "local",
                                   "--cpus", "2"])
    yield root, res
    mp.undo()


def test_every_run_has_its_row_and_the_broken_config_one_failed_row(batch_dir):
    root, res = batch_dir
    assert res.exit_code == 1, res.output  # a failed run is reported in the exit code
    assert "5 runs into" in res.output and "1 run(s) failed" in res.output
    rows = _rows(root / "out")
    assert [r["sequence"] for r in rows] == [n for n, _ in ENTRIES] + ["broken"]
    assert [r["status"] for r in rows] == ["finished"] * 4 + ["failed"]
    broken = rows[4]
    assert "broken.yaml: dataset.synthetic: n_frames must be at least 2" in broken["error"] and "\n" not in broken["error"]
    assert "[1/5] broken/default: failed: " in res.output  # sorted out before any task starts
    for r in rows[:4]:
        assert r["action"] == "ran" and r["attempts"] == 1
        assert r["threads"] == {"torch": 1, "numba": 1, "omp_env": 1}  # pinned to num_cpus inside the task
        assert r["resolution"] == "160x120" and r["frames"] == 12
        assert r["ate_rmse_cm"] < 2.0 and r["psnr"] > 10 and r["peak_rss_mb"] > 100 and r["wall_s"] > 0
        run = Path(r["run_dir"])
        assert run == root / "out" / r["sequence"] / "default"
        assert json.loads((run / "run.json").read_text())["status"] == "finished"
    csv_lines = (root / "out" / "results.csv").read_text().splitlines()
    assert len(csv_lines) == 6 and csv_lines[0].startswith("sequence,variant,seed,status")
    # the synthetic sequence was rendered once, by whichever task came first
    assert len([p for p in (root / "cache" / "sequences").iterdir() if not p.name.startswith(".")]) == 1


def test_the_rows_equal_the_same_runs_made_one_by_one(batch_dir, tmp_path):
    from ggfslam import slam
    from ggfslam.config import load_config

    root, _ = batch_dir
    rows = _rows(root / "out")
    with _one_thread():
        for (name, sets), row in zip(ENTRIES, rows):
            cfg = load_config(root / "tiny.yaml", sets + ["runtime.num_threads=1"])
            metrics = slam.run(cfg, tmp_path / name, progress=False)
            batch_run = Path(row["run_dir"])
            np.testing.assert_array_equal(np.loadtxt(batch_run / "trajectory.txt"),
                                          np.loadtxt(tmp_path / name / "trajectory.txt"))
            assert row["ate_rmse_cm"] == metrics["trajectory"]["ate_rmse_cm"]
            assert row["psnr"] == metrics["rendering"]["psnr"]
            assert row["depth_l1_cm"] == metrics["rendering"]["depth_l1_cm"]


def test_a_second_invocation_skips_every_finished_run_without_starting_ray(batch_dir, monkeypatch):
    from ggfslam.batch import engine

    root, _ = batch_dir

    def no_ray(*args, **kwargs):
        raise AssertionError("Ray was started although every run had finished")

    monkeypatch.setattr(engine.RayEngine, "__init__", no_ray)
    before = {p: p.stat().st_mtime_ns for p in (root / "out").glob("*/default/metrics.json")}
    res = CliRunner().invoke(app, ["batch", str(root / "plan.yaml"), "--out", str(root / "out")])
    assert res.exit_code == 1, res.output
    rows = _rows(root / "out")
    assert [r["action"] for r in rows[:4]] == ["skipped"] * 4 and rows[4]["status"] == "failed"
    assert "tiny-800/default: finished earlier: ATE" in res.output
    assert before == {p: p.stat().st_mtime_ns for p in (root / "out").glob("*/default/metrics.json")}


def test_a_failing_run_is_retried_then_resumed_from_its_checkpoint_by_the_next_invocation(tmp_path, monkeypatch):
    from ggfslam import slam
    from ggfslam.batch import load_plan, run_batch
    from ggfslam.config import load_config
    from ggfslam.data.synthetic import write_synthetic_sequence

    seq = write_synthetic_sequence(tmp_path / "room", n_frames=24, width=160, height=120)
    depth = sorted((seq / "depth").iterdir())[BAD]
    good = depth.read_bytes()
    depth.write_bytes(good[: len(good) // 2])
    cfg = {"name": "damaged", "dataset": {"kind": "tum", "path": str(seq), "on_bad_frame": "error"},
           "tracking": {"keyframe_max_frames": 5},
           "mapping": {"iterations_per_keyframe": 5, "iterations_per_frame": 0, "final_iterations": 5,
                       "checkpoint_every": 2, "mesh": False, "eval_stride": 3}}
    _write_yaml(tmp_path / "damaged.yaml", cfg)
    _write_yaml(tmp_path / "plan.yaml", {"sequences": ["damaged.yaml"], "num_cpus": 1})
    plan = load_plan(tmp_path / "plan.yaml", tmp_path / "out")
    (row,) = run_batch(plan, tmp_path / "out", cpus=2, retries=1)
    assert row["status"] == "failed" and row["attempts"] == 2
    assert row["error"].startswith("DatasetError: ") and str(depth) in row["error"]
    assert "cannot decode depth image" in Path(row["traceback_file"]).read_text()  # the whole traceback is kept
    run = tmp_path / "out" / "damaged" / "default"
    info = json.loads((run / "run.json").read_text())
    assert info["status"] == "failed" and info["resume_from_frame"] == BAD

    depth.write_bytes(good)  # the user repairs the file; the same command goes on from the checkpoint
    (row,) = run_batch(load_plan(tmp_path / "plan.yaml", tmp_path / "out"), tmp_path / "out", cpus=2)
    assert row["status"] == "finished" and row["action"] == "resumed"
    info = json.loads((run / "run.json").read_text())
    assert info["status"] == "finished" and info["resumed_at_frame"] == BAD
    clean = load_config(tmp_path / "damaged.yaml", ["runtime.num_threads=1"])
    shutil.rmtree(tmp_path / "cache", ignore_errors=True)
    with _one_thread():
        metrics = slam.run(clean, tmp_path / "clean", progress=False)
    np.testing.assert_array_equal(np.loadtxt(run / "trajectory.txt"), np.loadtxt(tmp_path / "clean" / "trajectory.txt"))
    assert row["psnr"] == metrics["rendering"]["psnr"]


def test_a_bad_plan_or_a_busy_folder_is_one_line_before_ray_starts(tmp_path):
    from filelock import FileLock

    (tmp_path / "plan.yaml").write_text("sequences: [missing.yaml]\n")
    res = CliRunner().invoke(app, ["batch", str(tmp_path / "plan.yaml"), "--out", str(tmp_path / "out")])
    assert res.exit_code == 2 and "sequences[0]: config file" in res.output and "not found" in res.output
    _write_yaml(tmp_path / "tiny.yaml", TINY)
    (tmp_path / "plan.yaml").write_text("sequences: [tiny.yaml]\n")
    (tmp_path / "out").mkdir()
    with FileLock(str(tmp_path / "out" / ".batch.lock")):  # another batch holds the folder
        res = CliRunner().invoke(app, ["batch", str(tmp_path / "plan.yaml"), "--out", str(tmp_path / "out")])
    assert res.exit_code == 2 and "another ggfslam batch is running in this folder" in res.output
    res = CliRunner().invoke(app, ["batch", str(tmp_path / "plan.yaml"), "--out", str(tmp_path / "out"),
                                   "--retries", "-1"])
    assert res.exit_code == 2 and "--retries -1: expected 0 or more" in res.output


def _batch_process(plan: Path, out: Path, *args: str):
    import subprocess
    import sys

    return subprocess.Popen([sys.executable, "-c", "from ggfslam.cli import main; main()", "batch", str(plan),
                             "--out", str(out), "--cpus", "1", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def _wait_for(predicate, timeout: float, what: str) -> None:
    import time

    end = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.2)


def _longer_plan(tmp_path: Path) -> Path:
    cfg = {**TINY, "name": "longer", "dataset": {"kind": "synthetic", "synthetic": {"n_frames": 40, "width": 160, "height": 120}},
           "tracking": {"keyframe_max_frames": 5}, "mapping": {**TINY["mapping"], "checkpoint_every": 1}}
    _write_yaml(tmp_path / "longer.yaml", cfg)
    return _write_yaml(tmp_path / "plan.yaml", {"sequences": ["longer.yaml"], "variants": {"a": [], "b": []}})


def _start_longer_batch(tmp_path: Path, monkeypatch) -> tuple[Path, Path, Path, object]:
    """The two-run plan started as a batch process (one CPU), once its first run has written a checkpoint:
    (plan, batch folder, first run's folder, process)."""
    monkeypatch.setenv("GGFSLAM_CACHE", str(tmp_path / "cache"))
    plan, out = _longer_plan(tmp_path), tmp_path / "out"
    proc = _batch_process(plan, out)
    first = out / "longer" / "a"
    _wait_for(lambda: (first / "checkpoint.pt").is_file(), 180, "the first run's checkpoint")
    return plan, out, first, proc


def _status(run: Path) -> str | None:
    try:
        return json.loads((run / "run.json").read_text()).get("status")
    except (FileNotFoundError, json.JSONDecodeError):
        return None


@pytest.mark.slow
def test_a_killed_run_is_a_failed_row_the_batch_goes_on_and_the_next_invocation_resumes_it(tmp_path, monkeypatch):
    import os
    import signal
    import subprocess

    plan, out, first, proc = _start_longer_batch(tmp_path, monkeypatch)
    pids = subprocess.run(["pgrep", "-f", "ray::execute"], capture_output=True, text=True).stdout.split()
    assert pids, "no task process found"
    for pid in pids:
        os.kill(int(pid), signal.SIGKILL)
    text = proc.communicate(timeout=300)[0]
    assert proc.returncode == 1, text
    rows = {r["variant"]: r for r in _rows(out)}
    assert rows["a"]["status"] == "failed" and rows["a"]["error"].startswith("killed")
    assert rows["b"]["status"] == "finished"
    proc = _batch_process(plan, out)
    text = proc.communicate(timeout=300)[0]
    assert proc.returncode == 0, text
    rows = {r["variant"]: r for r in _rows(out)}
    assert rows["a"]["action"] == "resumed" and rows["b"]["action"] == "skipped"
    assert json.loads((first / "run.json").read_text())["resumed_at_frame"] > 0


@pytest.mark.slow
def test_ctrl_c_stops_the_batch_with_checkpoints_and_the_next_invocation_finishes_it(tmp_path, monkeypatch):
    import signal

    plan, out, first, proc = _start_longer_batch(tmp_path, monkeypatch)
    proc.send_signal(signal.SIGINT)
    text = proc.communicate(timeout=120)[0]
    assert proc.returncode == 130, text
    assert _status(first) == "interrupted" and "stopping: 1 running run(s) save a checkpoint" in text
    rows = {r["variant"]: r for r in _rows(out)}
    assert rows["a"]["status"] == "interrupted" and rows["b"]["status"] == "not run"
    proc = _batch_process(plan, out)
    text = proc.communicate(timeout=300)[0]
    assert proc.returncode == 0, text
    rows = {r["variant"]: r for r in _rows(out)}
    assert rows["a"]["action"] == "resumed" and rows["b"]["action"] == "ran"
    assert json.loads((first / "run.json").read_text())["resumed_at_frame"] > 0
