"""``ggfslam render``: views of a run's Gaussian map at its frames' poses or along a new path, as PNGs."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ggfslam.data.imageio import write_depth, write_rgb
from ggfslam.data.trajectory_io import read_tum_trajectory
from ggfslam.errors import ConfigError, RunDirError
from ggfslam.rundir import TRAJECTORY_FILE
from ggfslam.saved_run import load_mapper, run_camera


def _frame_selection(spec: str, n: int, kf_frames: list[int]) -> np.ndarray:
    """Frame indices for 'keyframes', 'all' or 'start:stop[:step]'."""
    if spec == "keyframes":
        return np.array(sorted(kf_frames), dtype=np.int64)
    if spec == "all":
        return np.arange(n)
    parts = spec.split(":")
    try:
        if len(parts) not in (2, 3):
            raise ValueError
        vals = [int(p) if p else None for p in parts]
    except ValueError:
        raise ConfigError(f"--frames {spec!r}: expected 'keyframes', 'all' or start:stop[:step]") from None
    return np.arange(n)[slice(*vals)]


def keyframe_frames(run_dir: Path) -> list[int]:
    """Frame indices of a run's keyframes, from tracking.txt (index timestamp state keyframe ...)."""
    from ggfslam.rundir import TRACKING_LOG_FILE

    f = run_dir / TRACKING_LOG_FILE
    if not f.is_file():
        raise RunDirError(f"{run_dir}: {TRACKING_LOG_FILE} missing (the run did not finish); pass --frames or --path")
    index, _, keyframe = tracking_log(f)
    return [int(i) for i, k in zip(index, keyframe) if k]


def tracking_log(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame index [N] int, timestamp [N] float and keyframe flag [N] bool of each row of a run's tracking.txt
    (index timestamp state keyframe ...)."""
    rows = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    try:
        return (np.array([int(r[0]) for r in rows], np.int64), np.array([float(r[1]) for r in rows], np.float64),
                np.array([int(r[3]) == 1 for r in rows], bool))
    except (IndexError, ValueError):
        raise RunDirError(f"{path}: expected rows 'index timestamp state keyframe ...'") from None


def render_run(run_dir: str | Path, frames: str = "keyframes", path: str | Path | None = None,
               out: str | Path | None = None, width: int | None = None, overwrite: bool = False,
               ply: bool = False) -> dict:
    """Render views of a run's map to ``out`` (default RUN_DIR/renders, or RUN_DIR/renders_ply with ``ply``);
    returns {'count', 'folder'}. With ``ply`` the baked file gaussians.ply is rendered instead of the neural map
    (what a standard viewer shows)."""
    from ggfslam.config import load_config
    from ggfslam.eval.rendering import nearest_keyframes
    from ggfslam.mapping.keyframe_store import scaled_intrinsics
    from ggfslam.mapping.mapper import REFERENCE_EXPOSURE
    from ggfslam.rundir import CONFIG_FILE, GAUSSIANS_FILE, require_run_dir

    run_dir = require_run_dir(run_dir)
    config = load_config(run_dir / CONFIG_FILE)
    camera = run_camera(run_dir)
    intr = scaled_intrinsics(camera, width or config.mapping.train_width)
    if ply:
        from ggfslam.gaussians.explicit import ExplicitGaussians

        if not (run_dir / GAUSSIANS_FILE).is_file():
            raise RunDirError(f"{run_dir}: {GAUSSIANS_FILE} missing (the run did not finish, or ran without mapping)")
        baked = ExplicitGaussians.from_ply(run_dir / GAUSSIANS_FILE)
        kf_frames = {i: f for i, f in enumerate(keyframe_frames(run_dir))} if path is None else {}

        def render(T, _exposure_kf):
            return baked.render(T, intr)
    else:
        _, mapper, ckpt = load_mapper(run_dir)
        kf_frames = dict(ckpt["kf_frames"])

        def render(T, exposure_kf):
            return mapper.render(T, intr, exposure_kf=exposure_kf, planar=False)
    if path is not None:
        _, poses = read_tum_trajectory(path)
        indices = np.arange(len(poses))
        names = [f"view_{i:06d}" for i in indices]
    else:
        traj = run_dir / TRAJECTORY_FILE
        if not traj.is_file():
            raise RunDirError(f"{run_dir}: {TRAJECTORY_FILE} missing (the run did not finish); pass --path")
        _, poses = read_tum_trajectory(traj)
        indices = _frame_selection(frames, len(poses), list(kf_frames.values()))
        names = [f"frame_{i:06d}" for i in indices]
    if len(indices) == 0:
        raise ConfigError(f"--frames {frames!r} selects no frame of the {len(poses)} in the run")
    folder = Path(out) if out is not None else run_dir / ("renders_ply" if ply else "renders")
    folder.mkdir(parents=True, exist_ok=True)
    clash = [nm for nm in names if (folder / f"{nm}_rgb.png").exists()]
    if clash and not overwrite:
        raise RunDirError(f"{folder}: {len(clash)} render(s) already there (e.g. {clash[0]}_rgb.png); pass "
                          "--overwrite or choose another --out")
    # a frame takes its nearest keyframe's exposure; a new path the keyframes' typical one
    exposure = nearest_keyframes(indices, kf_frames) if path is None else None
    for j, (i, nm) in enumerate(zip(indices, names)):
        e = REFERENCE_EXPOSURE if exposure is None else int(exposure[j]) if exposure[j] >= 0 else None
        res = render(poses[int(i)], e)
        write_rgb(folder / f"{nm}_rgb.png", res.color.clamp(0, 1).numpy())
        write_depth(folder / f"{nm}_depth.png", res.depth.numpy(), 1000.0)
    return {"count": len(indices), "folder": str(folder)}
