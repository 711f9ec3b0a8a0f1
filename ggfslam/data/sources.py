"""Open the dataset a configuration names: a reader on a folder, or a generated (synthetic) sequence."""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path

from ggfslam.config import DatasetConfig, SyntheticConfig, expand_path
from ggfslam.data.base import RGBDDataset
from ggfslam.data.types import Camera

SYNTHETIC_FORMAT = 2  # bump when generated sequences change, so stale caches are not reused (2: depth_gt/)


def cache_root() -> Path:
    """Where generated sequences are cached (``GGFSLAM_CACHE``, default ``~/.cache/ggfslam``)."""
    return Path(os.environ.get("GGFSLAM_CACHE", Path.home() / ".cache" / "ggfslam"))


def camera_from_config(cfg: DatasetConfig) -> Camera | None:
    """The configured intrinsics override, or None."""
    c = cfg.camera
    if c is None:
        return None
    return Camera(c.fx, c.fy, c.cx, c.cy, c.width, c.height, c.depth_scale, tuple(c.distortion))


def _synthetic_key(syn: SyntheticConfig, camera: Camera | None) -> str:
    spec = {"format": SYNTHETIC_FORMAT, "synthetic": syn.model_dump(mode="json")}
    if syn.source != "procedural":
        spec["camera"] = None if camera is None else camera.to_dict()
        for k in ("replica_root", "mesh_path", "trajectory_path"):
            v = spec["synthetic"].get(k)
            spec["synthetic"][k] = None if v is None else str(expand_path(v).resolve())
    text = json.dumps(spec, sort_keys=True)
    return f"{syn.source}-{hashlib.sha1(text.encode()).hexdigest()[:12]}"


def generate_synthetic(syn: SyntheticConfig, camera: Camera | None = None, out_dir: Path | None = None) -> Path:
    """Render the configured synthetic sequence in TUM layout, reusing a cached copy when one exists."""
    target = out_dir or cache_root() / "sequences" / _synthetic_key(syn, camera)
    if _complete(target):
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    if out_dir is not None:
        return _render_synthetic(syn, camera, target)
    from filelock import FileLock

    # runs started together (a batch's tasks on one node) render the sequence once: the others wait, then read it
    with FileLock(str(target.parent / f".{target.name}.lock")):
        return target if _complete(target) else _render_synthetic(syn, camera, target)


def _complete(target: Path) -> bool:
    return (target / "rgb.txt").is_file() and (target / "camera.yaml").is_file()


def _render_synthetic(syn: SyntheticConfig, camera: Camera | None, target: Path) -> Path:
    from ggfslam.data import synthetic

    # render into a scratch folder and rename, so an interrupted render never leaves a half sequence
    scratch = Path(tempfile.mkdtemp(prefix=".partial-", dir=target.parent))
    try:
        if syn.source == "procedural":
            synthetic.write_synthetic_sequence(
                scratch, n_frames=syn.n_frames, width=syn.width, height=syn.height, trajectory=syn.trajectory,
                seed=syn.seed, depth_noise=syn.depth_noise, textureless_wall=syn.textureless_wall, overwrite=True,
            )
        elif syn.source == "replica":
            synthetic.render_replica_sequence(
                expand_path(syn.replica_root), scratch, n_frames=syn.n_frames, width=syn.width,
                height=syn.height, stride=syn.stride, depth_noise=syn.depth_noise, seed=syn.seed, overwrite=True,
            )
        else:
            from ggfslam.data.trajectory_io import read_tum_trajectory

            if camera is None:
                from ggfslam.errors import ConfigError

                raise ConfigError("dataset.camera is required for synthetic source 'mesh'")
            stamps, poses = read_tum_trajectory(expand_path(syn.trajectory_path))
            synthetic.render_mesh_sequence(
                expand_path(syn.mesh_path), poses[: syn.n_frames], camera, scratch,
                timestamps=stamps[: syn.n_frames], depth_noise=syn.depth_noise, seed=syn.seed, overwrite=True,
            )
        if target.exists():
            shutil.rmtree(target)
        scratch.rename(target)
    finally:
        if scratch.exists():
            shutil.rmtree(scratch, ignore_errors=True)
    return target


def open_dataset_from_config(cfg: DatasetConfig) -> RGBDDataset:
    """The dataset a DatasetConfig describes (generating a synthetic sequence first when asked)."""
    from ggfslam.data.registry import detect_kind, open_dataset

    camera = camera_from_config(cfg)
    if cfg.kind == "synthetic":
        root, kind, camera_arg = generate_synthetic(cfg.synthetic, camera), "tum", None
    else:
        root, kind, camera_arg = expand_path(cfg.path), cfg.kind, camera
        if kind == "auto":
            kind = detect_kind(root)
    # a listed image that is missing is one bad frame, skipped at its turn (dataset.on_bad_frame), not a refusal
    kwargs = {"max_time_diff": cfg.max_time_diff, "check_files": cfg.on_bad_frame == "error"} if kind == "tum" else {}
    ds = open_dataset(kind, root, camera=camera_arg, start=cfg.start, stop=cfg.stop, stride=cfg.stride,
                      resize=cfg.resize, **kwargs)
    reg = cfg.depth_registration
    if reg is not None:
        ds.set_depth_registration((reg.fx, reg.fy, reg.cx, reg.cy), reg.T_color_depth(),
                                 ground_truth_of_depth=reg.ground_truth == "depth")
    return ds
