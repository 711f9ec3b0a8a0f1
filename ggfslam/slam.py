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
from ggfslam.atomic import write_text_atomic
from ggfslam.config import Config, load_config, save_config
from ggfslam.data.base import RGBDDataset
from ggfslam.data.sources import open_dataset_from_config
from ggfslam.data.trajectory_io import read_tum_trajectory, write_tum_trajectory
from ggfslam.errors import GGFSlamError, RunDirError
from ggfslam.eval.perf import StageTimer, current_rss_mb, peak_rss_mb
from ggfslam.eval.trajectory import trajectory_metrics
from ggfslam.rundir import (
    CONFIG_FILE,
    GAUSSIANS_FILE,
    GRAPH_FILE,
    GROUNDTRUTH_FILE,
    KEYFRAME_IMAGES_DIR,
    KEYFRAMES_FILE,
    LOG_FILE,
    MESH_FILE,
    METRICS_FILE,
    PLANARITY_FILE,
    RUN_INFO_FILE,
    TRACKING_LOG_FILE,
    TRAJECTORY_FILE,
    prepare_run_dir,
    read_json,
    require_run_dir,
    write_json,
)

log = logging.getLogger("ggfslam")
RSS_EVERY = 100  # frames between memory samples (metrics.json system.rss_mb_by_frame)


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


def make_mapper(config: Config, camera, tracker, run_dir: Path):
    """The Gaussian mapper for a run (None when ``mapping.enabled`` is off), reading poses from the SLAM map."""
    if not config.mapping.enabled:
        return None
    from ggfslam.mapping.mapper import Mapper
    from ggfslam.render.types import RenderSettings

    settings = RenderSettings(backend=config.render.backend)
    slam_map = tracker.map
    return Mapper(config.mapping, camera, settings, lambda: slam_map.poses(), run_dir / KEYFRAME_IMAGES_DIR,
                  config.runtime.seed, ggf=config.ggf)


def attach_gcgr(config: Config, tracker, mapper, camera) -> None:
    """With ``gcgr.enabled``, give the backend the map's GCGR factors (and per-frame refinement where asked)."""
    if not config.gcgr.enabled or mapper is None:
        return
    from ggfslam.backend.gcgr_source import GCGRSource
    from ggfslam.render.api import select_backend

    per_frame = config.gcgr.per_frame == "on" or (
        config.gcgr.per_frame == "auto" and select_backend(config.render.backend) == "gsplat")
    source = GCGRSource(mapper, camera, config.gcgr, per_frame)
    tracker.backend.attach_gcgr(source)
    mapper.view_sink = source  # training renders become GCGR models (gcgr.harvest_every)


def _keyframe_landmarks(tracker, kf_id: int) -> np.ndarray:
    """World positions [L, 3] of the live landmarks a keyframe observes."""
    m = tracker.map
    with m.lock:
        ids = m.keyframes[kf_id].landmark_ids
        ids = ids[ids >= 0]
        ids = ids[m.alive[ids]]
        return m.positions[ids].copy()


def _check_resume_config(config: Config, run_dir: Path) -> None:
    saved = load_config(run_dir / CONFIG_FILE)
    a, b = saved.model_dump(), config.model_dump()
    diff = [f"{sec}.{k}" for sec in a if isinstance(a[sec], dict)
            for k in a[sec] if a[sec].get(k) != b.get(sec, {}).get(k)]
    diff += [k for k in a if not isinstance(a[k], dict) and a[k] != b.get(k)]
    if diff:
        raise RunDirError(f"{run_dir}: --resume with a configuration that differs from the run's {CONFIG_FILE} in "
                          f"{', '.join(diff)}; resume without a config (the saved one is used)")


def run(config: Config, out_dir: str | Path, overwrite: bool = False, progress: bool | None = None,
        resume: bool = False) -> dict:
    """Run the system on the configured sequence, write the run directory and return its metrics.

    With ``resume``, ``out_dir`` must be an interrupted run with a checkpoint; the run continues from it."""
    from ggfslam.checkpoint import load_checkpoint, save_checkpoint, set_rng_state, unpickle_tracker

    setup_runtime(config)
    dataset = open_dataset_from_config(config.dataset)  # fails on bad input before the run folder is touched
    n = len(dataset)
    ckpt = None
    if resume:
        run_dir = require_run_dir(out_dir)
        _check_resume_config(config, run_dir)
        if read_json(run_dir / RUN_INFO_FILE).get("status") == "finished":
            raise RunDirError(f"{run_dir}: the run finished; nothing to resume")
        ckpt = load_checkpoint(run_dir)
    else:
        run_dir = prepare_run_dir(out_dir, overwrite)
        save_config(config, run_dir / CONFIG_FILE)
    handler = _attach_log(run_dir)
    info = {"ggfslam_version": __version__, "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "command": sys.argv, "dataset": dataset.describe(), "camera": dataset.camera.to_dict(),
            "python": platform.python_version(), "torch": torch.__version__, "status": "running"}
    if ckpt is not None:
        info = read_json(run_dir / RUN_INFO_FILE)
        info.update(status="running", resumed_at_frame=ckpt["next_frame"],
                    resumed=datetime.now(timezone.utc).isoformat(timespec="seconds"))
    write_json(run_dir / RUN_INFO_FILE, info)
    worker = None
    try:
        log.info("run %s on %s", config.name, dataset.describe())
        timer = StageTimer()
        lines = ["# index timestamp state keyframe matches fitness ms"]
        start = 0
        if ckpt is not None:
            tracker = unpickle_tracker(ckpt)
            lines, start = ckpt["lines"], ckpt["next_frame"]
            if ckpt["timer"] is not None:
                timer.total.update(ckpt["timer"]["total"])
                timer.calls.update(ckpt["timer"]["calls"])
            log.info("resumed at frame %d", start)
        else:
            tracker = make_tracker(config, dataset)
        mapper = make_mapper(config, dataset.camera, tracker, run_dir)
        if mapper is not None:
            from ggfslam.mapping.worker import MappingWorker

            if ckpt is not None and ckpt["mapper"] is not None:
                mapper.load_state(ckpt["mapper"])
                # keyframes stored after the checkpoint are made again, under the same ids, as the run goes on
                mapper.store.retain(ckpt["kf_frames"])
            worker = MappingWorker(mapper, config.mapping.concurrent, config.mapping.threads)
            attach_gcgr(config, tracker, mapper, dataset.camera)
            for kf_id, lms in (ckpt or {}).get("pending", {}).items():
                worker.enqueue(kf_id, lms)
        if ckpt is not None:
            set_rng_state(ckpt["rng"])
        every = config.mapping.checkpoint_every
        rss = [] if ckpt is None else list(ckpt.get("rss", []))  # (frames done, MiB): memory against length
        show = config.runtime.progress if progress is None else progress
        t_start = time.perf_counter()
        with _progress(show and sys.stderr.isatty()) as bar:
            task = bar.add_task("tracking", total=n, completed=start, fps=0.0)
            for i in range(start, n):
                with timer("load"):
                    frame = dataset[i]
                t0 = time.perf_counter()
                with timer("tracking"):
                    res = tracker.track(frame)
                ms = 1000 * (time.perf_counter() - t0)
                lines.append(f"{frame.index} {frame.timestamp:.6f} {res.state.value} {int(res.keyframe)} "
                             f"{res.matches} {res.fitness:.4f} {ms:.1f}")
                if res.keyframe and worker is not None:
                    with timer("mapping"):  # sequential mode: training; concurrent: storing the images
                        worker.submit(res.keyframe_id, frame.index, frame.rgb, frame.depth,
                                      _keyframe_landmarks(tracker, res.keyframe_id))
                    if every and len(mapper.store) % every == 0:
                        with timer("checkpoint"):
                            save_checkpoint(run_dir, next_frame=i + 1, tracker=tracker, mapper=mapper,
                                            pending=worker.pending(), lines=lines, timer=timer, rss=rss)
                if (i + 1) % RSS_EVERY == 0 or i + 1 == n:
                    rss.append((i + 1, round(current_rss_mb(), 1)))
                bar.update(task, advance=1, fps=timer.fps("tracking"))
        with timer("finish"):
            tracker.finish()  # the backend's queued keyframes: their corrections belong in the trajectory
            if worker is not None:
                worker.finish()
        if mapper is not None and config.mapping.final_iterations:
            with timer("final_refinement"):
                mapper.sync_poses()
                mapper.train(config.mapping.final_iterations)
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
                             config.backend, tracker.backend.gcgr)
        write_text_atomic(run_dir / TRACKING_LOG_FILE, "\n".join(lines) + "\n")
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
        }
        if gt is not None:
            metrics["trajectory"] = _trajectory_metrics(stamps_a, poses_a, dataset.timestamps, gt, config)
        if mapper is not None:
            with timer("map_outputs"):
                metrics.update(_map_outputs(config, mapper, tracker, dataset, poses_a, run_dir))
            save_checkpoint(run_dir, next_frame=n, tracker=tracker, mapper=mapper, lines=lines, timer=timer,
                            finished=True, rss=rss)
        metrics["system"] = {"wall_seconds": wall, "peak_rss_mb": peak_rss_mb(), "rss_mb_by_frame": rss,
                             "stages": timer.summary()}
        write_json(run_dir / METRICS_FILE, metrics)
        info = read_json(run_dir / RUN_INFO_FILE)
        info.update(status="finished", finished=datetime.now(timezone.utc).isoformat(timespec="seconds"))
        write_json(run_dir / RUN_INFO_FILE, info)
        log.info("finished: %s", metrics.get("trajectory", {}))
        return metrics
    except BaseException as e:
        info = read_json(run_dir / RUN_INFO_FILE)
        info.update(status="interrupted" if isinstance(e, KeyboardInterrupt) else "failed")
        write_json(run_dir / RUN_INFO_FILE, info)
        raise
    finally:
        if worker is not None:
            worker.abort()  # no-op after finish(); after an error, no training goes on in the background
        log.removeHandler(handler)
        handler.close()


def _map_outputs(config: Config, mapper, tracker, dataset, poses: np.ndarray, run_dir: Path) -> dict:
    """Write gaussians.ply (and gaussians_planarity.ply with the field) and mesh.ply fused from the baked file,
    score the file against the map at the keyframes, render every evaluated frame; returns the
    mapping/rendering metrics."""
    from ggfslam.eval.rendering import ply_fidelity
    from ggfslam.gaussians.explicit import ExplicitGaussians
    from ggfslam.mapping.outputs import write_map_ply, write_planarity_ply, write_rendered_mesh

    out = {"mapping": mapper.stats()}
    g = mapper.bake_gaussians()  # once for both files (with view-dependent decoders it reads every keyframe)
    out["mapping"]["ply_gaussians"] = write_map_ply(mapper, run_dir / GAUSSIANS_FILE, g)
    if mapper.ggf is not None:
        write_planarity_ply(mapper, run_dir / PLANARITY_FILE, g)
    baked = ExplicitGaussians.from_ply(run_dir / GAUSSIANS_FILE)  # what a viewer reads, read back as one does
    out["mapping"]["ply_fidelity"] = ply_fidelity(mapper, baked)
    if config.mapping.mesh:
        kf_poses = [T for _, T in sorted(tracker.map.poses().items())]
        try:
            out["mapping"]["mesh_triangles"] = write_rendered_mesh(baked, kf_poses, mapper.intr,
                                                                   config.mapping.mesh_voxel, run_dir / MESH_FILE)
        except GGFSlamError as e:  # an empty map fuses no surface: the run's other outputs still count
            log.warning("mesh.ply not written: %s", e)
    out["rendering"] = rendering_metrics(config, mapper, dataset, poses)
    return out


def rendering_metrics(config: Config, mapper, dataset, poses: np.ndarray) -> dict:
    """PSNR/SSIM/depth L1 of the map rendered at every ``eval_stride``-th frame's estimated pose."""
    from ggfslam.eval.image import LPIPS
    from ggfslam.eval.rendering import render_metrics
    from ggfslam.mapping.keyframe_store import scaled_intrinsics

    c = config.mapping
    intr = scaled_intrinsics(dataset.camera, c.eval_width)
    idx = np.arange(0, len(dataset), c.eval_stride)
    return render_metrics(mapper, dataset, poses, idx, intr, LPIPS(config.eval.lpips_weights))


def _trajectory_metrics(est_stamps, est_poses, gt_stamps, gt_poses, config: Config) -> dict:
    """ATE/RPE of a run; a trajectory that cannot be scored (e.g. never left the origin) says why instead."""
    try:
        return trajectory_metrics(est_stamps, est_poses, gt_stamps, gt_poses, config.eval.max_time_diff,
                                  config.eval.rpe_delta)
    except ValueError as e:
        log.warning("trajectory not scored: %s", e)
        return {"ate_rmse_cm": float("nan"), "error": str(e)}


def load_mapper(run_dir: str | Path):
    """The trained map of a finished (or checkpointed) run: (config, mapper, checkpoint dict)."""
    from ggfslam.checkpoint import load_checkpoint
    from ggfslam.mapping.mapper import Mapper
    from ggfslam.render.types import RenderSettings

    run_dir = require_run_dir(run_dir)
    config = load_config(run_dir / CONFIG_FILE)
    if not config.mapping.enabled:
        raise RunDirError(f"{run_dir}: the run was made with mapping.enabled: false, so it has no Gaussian map")
    ckpt = load_checkpoint(run_dir)
    if ckpt["mapper"] is None:
        raise RunDirError(f"{run_dir}: the checkpoint holds no Gaussian map")
    from ggfslam.render_run import run_camera

    camera = run_camera(run_dir)
    poses = ckpt["keyframe_poses"]
    mapper = Mapper(config.mapping, camera, RenderSettings(backend=config.render.backend), lambda: dict(poses),
                    run_dir / KEYFRAME_IMAGES_DIR, config.runtime.seed, ggf=config.ggf)
    mapper.load_state(ckpt["mapper"])
    return config, mapper, ckpt


def evaluate(run_dir: str | Path) -> dict:
    """Recompute a run's trajectory (and rendering) metrics from its files, update ``metrics.json`` and return it."""
    run_dir = require_run_dir(run_dir)
    config = load_config(run_dir / CONFIG_FILE)
    traj = run_dir / TRAJECTORY_FILE
    if not traj.is_file():
        raise RunDirError(f"{run_dir}: {TRAJECTORY_FILE} missing (the run did not finish)")
    est_stamps, est_poses = read_tum_trajectory(traj)
    dataset = None
    if (run_dir / GROUNDTRUTH_FILE).is_file():
        gt_stamps, gt_poses = read_tum_trajectory(run_dir / GROUNDTRUTH_FILE)
    else:
        dataset = open_dataset_from_config(config.dataset)
        if dataset.gt_poses is None:
            raise RunDirError(f"{run_dir}: the sequence has no ground truth, so there is no ATE to compute")
        gt_stamps, gt_poses = dataset.timestamps, dataset.gt_poses
    metrics = read_json(run_dir / METRICS_FILE)
    metrics["trajectory"] = _trajectory_metrics(est_stamps, est_poses, gt_stamps, gt_poses, config)
    if config.mapping.enabled:
        _, mapper, _ = load_mapper(run_dir)
        dataset = dataset or open_dataset_from_config(config.dataset)
        if len(est_poses) != len(dataset):
            raise RunDirError(f"{run_dir}: {TRAJECTORY_FILE} has {len(est_poses)} poses for {len(dataset)} frames")
        metrics["rendering"] = rendering_metrics(config, mapper, dataset, est_poses)
    write_json(run_dir / METRICS_FILE, metrics)
    return metrics
