"""``ggfslam render``: views of a run's Gaussian map at its frames' poses or along a new path, as PNGs."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ggfslam.data.imageio import write_depth, write_rgb
from ggfslam.data.trajectory_io import read_tum_trajectory
from ggfslam.errors import ConfigError, RunDirError
from ggfslam.rundir import TRAJECTORY_FILE


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


def render_run(run_dir: str | Path, frames: str = "keyframes", path: str | Path | None = None,
               out: str | Path | None = None, width: int | None = None, overwrite: bool = False) -> dict:
    """Render views of a run's map to ``out`` (default RUN_DIR/renders); returns {'count', 'folder'}."""
    from ggfslam.mapping.keyframe_store import scaled_intrinsics
    from ggfslam.slam import load_mapper

    run_dir = Path(run_dir)
    config, mapper, ckpt = load_mapper(run_dir)
    if path is not None:
        _, poses = read_tum_trajectory(path)
        indices = np.arange(len(poses))
        names = [f"view_{i:06d}" for i in indices]
    else:
        traj = run_dir / TRAJECTORY_FILE
        if not traj.is_file():
            raise RunDirError(f"{run_dir}: {TRAJECTORY_FILE} missing (the run did not finish); pass --path")
        _, poses = read_tum_trajectory(traj)
        indices = _frame_selection(frames, len(poses), list(ckpt["kf_frames"].values()))
        names = [f"frame_{i:06d}" for i in indices]
    if len(indices) == 0:
        raise ConfigError(f"--frames {frames!r} selects no frame of the {len(poses)} in the run")
    folder = Path(out) if out is not None else run_dir / "renders"
    folder.mkdir(parents=True, exist_ok=True)
    clash = [nm for nm in names if (folder / f"{nm}_rgb.png").exists()]
    if clash and not overwrite:
        raise RunDirError(f"{folder}: {len(clash)} render(s) already there (e.g. {clash[0]}_rgb.png); pass "
                          "--overwrite or choose another --out")
    intr = mapper.intr if width is None else scaled_intrinsics(run_camera(run_dir), width)
    from ggfslam.eval.rendering import nearest_keyframes

    exposure = nearest_keyframes(indices, ckpt["kf_frames"]) if path is None else np.full(len(indices), -1)
    for i, nm, e in zip(indices, names, exposure):
        res = mapper.render(poses[int(i)], intr, exposure_kf=int(e) if e >= 0 else None)
        write_rgb(folder / f"{nm}_rgb.png", res.color.numpy())
        write_depth(folder / f"{nm}_depth.png", res.depth.numpy(), 1000.0)
    return {"count": len(indices), "folder": str(folder)}


def run_camera(run_dir: Path):
    """The camera a run was made with (from its run.json)."""
    from ggfslam.data.types import Camera
    from ggfslam.rundir import RUN_INFO_FILE, read_json

    cam = dict(read_json(run_dir / RUN_INFO_FILE)["camera"])
    return Camera(**{**cam, "distortion": tuple(cam.get("distortion", ()))})
