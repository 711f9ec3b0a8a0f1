"""What a run directory gives back to the tools that read it (render, evaluate, view, notebooks): the camera its
frames were seen with and its trained Gaussian map. The run itself (``slam.py``) and the tools both import from
here, so neither imports the other."""
from __future__ import annotations

from pathlib import Path

from ggfslam.config import load_config
from ggfslam.data.types import Camera
from ggfslam.errors import RunDirError
from ggfslam.rundir import CONFIG_FILE, KEYFRAME_IMAGES_DIR, RUN_INFO_FILE, read_json, require_run_dir


def run_camera(run_dir: Path) -> Camera:
    """The pinhole camera a run's frames were seen with (from its run.json)."""
    cam = dict(read_json(run_dir / RUN_INFO_FILE)["camera"])
    if cam.get("distortion"):
        # runs now record the camera of the undistorted frames; this one read distorted images as pinhole ones
        raise RunDirError(f"{run_dir / RUN_INFO_FILE}: camera has lens distortion {cam['distortion']}: the run was made "
                          "before ggfslam undistorted frames (2026-12-04), so its map and poses do not match the frames "
                          "read now; run the sequence again")
    return Camera(**{**cam, "distortion": ()})


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
    camera = run_camera(run_dir)
    poses = ckpt["keyframe_poses"]
    mapper = Mapper(config.mapping, camera, RenderSettings(backend=config.render.backend), lambda: dict(poses),
                    run_dir / KEYFRAME_IMAGES_DIR, config.runtime.seed, ggf=config.ggf)
    mapper.load_state(ckpt["mapper"])
    return config, mapper, ckpt
