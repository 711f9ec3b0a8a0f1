"""The system: wires dataset, tracker and evaluation, runs a sequence and writes the run directory."""
from __future__ import annotations

import logging
import platform
import random
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

from ggfslam import __version__
from ggfslam.config import Config, load_config, save_config
from ggfslam.data.base import RGBDDataset
from ggfslam.data.sources import open_dataset_from_config
from ggfslam.data.trajectory_io import read_tum_trajectory, write_tum_trajectory
from ggfslam.errors import RunDirError
from ggfslam.eval.perf import StageTimer, peak_rss_mb
from ggfslam.eval.trajectory import trajectory_metrics
from ggfslam.rundir import (
    CONFIG_FILE, GRAPH_FILE, GROUNDTRUTH_FILE, KEYFRAMES_FILE, LOG_FILE, METRICS_FILE, RUN_INFO_FILE, TRACKING_LOG_FILE, TRAJECTORY_FILE,
    prepare_run_dir, read_json, require_run_dir, write_json,
)

log = logging.getLogger("ggfslam")


def setup_runtime(config: Config) -> None:
    """Seed every RNG and set the thread budget (explicit budgets avoid oversubscribing 2 cores)."""
    seed = config.runtime.seed
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    if config.runtime.num_threads > 0:
        torch.set_num_threads(config.runtime.num_threads)


def make_tracker(config: Config, dataset: RGBDDataset):
    """The tracker named by ``tracking.method``."""
    if config.tracking.method == "o3d_odometry":
        from ggfslam.frontend.odometry_baseline import OdometryBaselineTracker

        return OdometryBaselineTracker(dataset.camera, config.tracking)
    from ggfslam.backend.backend import Backend
    from ggfslam.frontend.tracker import OrbTracker

    backend = Backend(dataset.camera, config.tracking, config.backend)
    return OrbTracker(dataset.camera, config.tracking, backend)


def _progress(enabled: bool):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
        TextColumn("{task.fields[fps]:.1f} frames/s"), TimeRemainingColumn(),
        disable=not enabled, transient=False,
    )


def _attach_log(run_dir: Path) -> logging.Handler:
    handler = logging.FileHandler(run_dir / LOG_FILE)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    return handler


def run(config: Config, out_dir: str | Path, overwrite: bool = False, progress: bool | None = None) -> dict:
    """Run the system on the configured sequence, write the run directory and return its metrics."""
    setup_runtime(config)
    dataset = open_dataset_from_config(config.dataset)  # fails on bad input before the run folder is touched
    n = len(dataset)
    run_dir = prepare_run_dir(out_dir, overwrite)
    save_config(config, run_dir / CONFIG_FILE)
    handler = _attach_log(run_dir)
    started = datetime.now(timezone.utc).isoformat(timespec="seconds")
    write_json(run_dir / RUN_INFO_FILE, {
        "ggfslam_version": __version__, "started": started, "command": sys.argv,
        "dataset": dataset.describe(), "camera": dataset.camera.to_dict(), "python": platform.python_version(),
        "torch": torch.__version__, "status": "running",
    })
    try:
        log.info("run %s on %s", config.name, dataset.describe())
        tracker = make_tracker(config, dataset)
        timer = StageTimer()
        lines = ["# index timestamp state keyframe matches fitness ms"]
        show = config.runtime.progress if progress is None else progress
        t_start = time.perf_counter()
        with _progress(show and sys.stderr.isatty()) as bar:
            task = bar.add_task("tracking", total=n, fps=0.0)
            for i in range(n):
                with timer("load"):
                    frame = dataset[i]
                t0 = time.perf_counter()
                with timer("tracking"):
                    res = tracker.track(frame)
                ms = 1000 * (time.perf_counter() - t0)
                lines.append(f"{frame.index} {frame.timestamp:.6f} {res.state.value} {int(res.keyframe)} "
                             f"{res.matches} {res.fitness:.4f} {ms:.1f}")
                bar.update(task, advance=1, fps=timer.fps("tracking"))
        with timer("finish"):
            tracker.finish()  # the backend's queued keyframes: their corrections belong in the trajectory
        wall = time.perf_counter() - t_start
        stamps_a, poses_a, lost_a = tracker.trajectory()  # every frame, through its optimized reference keyframe
        write_tum_trajectory(run_dir / TRAJECTORY_FILE, stamps_a, poses_a,
                             header=f"ggfslam {__version__} {tracker.name}: camera-to-world, all frames")
        kf_traj = tracker.keyframe_trajectory()
        if kf_traj is not None:
            write_tum_trajectory(run_dir / KEYFRAMES_FILE, *kf_traj,
                                 header=f"ggfslam {__version__} {tracker.name}: camera-to-world, keyframes")
        if getattr(tracker, "backend", None) is not None:  # the factor graph (the odometry baseline has none)
            from ggfslam.backend.export import write_graph_json

            write_graph_json(run_dir / GRAPH_FILE, tracker.backend.map, dataset.camera, config.tracking,
                             config.backend)
        (run_dir / TRACKING_LOG_FILE).write_text("\n".join(lines) + "\n")
        gt = dataset.gt_poses
        if gt is not None:
            write_tum_trajectory(run_dir / GROUNDTRUTH_FILE, dataset.timestamps, gt,
                                 header="ground truth of the frames of this run")
        metrics = {
            "sequence": {"dataset": dataset.describe(), "frames": n, "width": dataset.camera.width,
                         "height": dataset.camera.height},
            "tracking": {"method": tracker.name, "frames": n, "frames_lost": int(lost_a.sum()),
                         "fps": timer.fps("tracking")},
            "backend": tracker.summary(),
            "system": {"wall_seconds": wall, "peak_rss_mb": peak_rss_mb(), "stages": timer.summary()},
        }
        if gt is not None:
            metrics["trajectory"] = _trajectory_metrics(stamps_a, poses_a, dataset.timestamps, gt, config)
        write_json(run_dir / METRICS_FILE, metrics)
        info = read_json(run_dir / RUN_INFO_FILE)
        info.update(status="finished", finished=datetime.now(timezone.utc).isoformat(timespec="seconds"))
        write_json(run_dir / RUN_INFO_FILE, info)
        log.info("finished: %s", metrics.get("trajectory", {}))
        return metrics
    except BaseException:
        info = read_json(run_dir / RUN_INFO_FILE)
        info.update(status="failed")
        write_json(run_dir / RUN_INFO_FILE, info)
        raise
    finally:
        log.removeHandler(handler)
        handler.close()


def _trajectory_metrics(est_stamps, est_poses, gt_stamps, gt_poses, config: Config) -> dict:
    """ATE/RPE of a run; a trajectory that cannot be scored (e.g. never left the origin) says why instead."""
    try:
        return trajectory_metrics(est_stamps, est_poses, gt_stamps, gt_poses, config.eval.max_time_diff,
                                  config.eval.rpe_delta)
    except ValueError as e:
        log.warning("trajectory not scored: %s", e)
        return {"ate_rmse_cm": float("nan"), "error": str(e)}


def evaluate(run_dir: str | Path) -> dict:
    """Recompute a run's trajectory metrics from its files, update ``metrics.json`` and return it."""
    run_dir = require_run_dir(run_dir)
    config = load_config(run_dir / CONFIG_FILE)
    traj = run_dir / TRAJECTORY_FILE
    if not traj.is_file():
        raise RunDirError(f"{run_dir}: {TRAJECTORY_FILE} missing (the run did not finish)")
    est_stamps, est_poses = read_tum_trajectory(traj)
    if (run_dir / GROUNDTRUTH_FILE).is_file():
        gt_stamps, gt_poses = read_tum_trajectory(run_dir / GROUNDTRUTH_FILE)
    else:
        dataset = open_dataset_from_config(config.dataset)
        if dataset.gt_poses is None:
            raise RunDirError(f"{run_dir}: the sequence has no ground truth, so there is no ATE to compute")
        gt_stamps, gt_poses = dataset.timestamps, dataset.gt_poses
    metrics = read_json(run_dir / METRICS_FILE)
    metrics["trajectory"] = _trajectory_metrics(est_stamps, est_poses, gt_stamps, gt_poses, config)
    write_json(run_dir / METRICS_FILE, metrics)
    return metrics
