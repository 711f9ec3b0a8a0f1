"""Run directories: one folder per run, never overwritten by accident."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

from ggfslam.atomic import write_text_atomic
from ggfslam.errors import RunDirError

CONFIG_FILE = "config.yaml"
METRICS_FILE = "metrics.json"
TRAJECTORY_FILE = "trajectory.txt"
KEYFRAMES_FILE = "keyframes.txt"
GRAPH_FILE = "graph.json"
GROUNDTRUTH_FILE = "groundtruth.txt"
TRACKING_LOG_FILE = "tracking.txt"
RUN_INFO_FILE = "run.json"
LOG_FILE = "log.txt"
GAUSSIANS_FILE = "gaussians.ply"
PLANARITY_FILE = "gaussians_planarity.ply"  # the same Gaussians coloured by P_2D (red = 2D, blue = 3D)
MESH_FILE = "mesh.ply"
KEYFRAME_IMAGES_DIR = "keyframes"
KEYFRAME_FEATURES_DIR = "keyframe_features"  # tracking's per-keyframe ORB features (backend/feature_store.py)


def is_run_dir(path: Path) -> bool:
    """True when ``path`` looks like a folder ggfslam made (it holds our run.json or config.yaml)."""
    return (path / RUN_INFO_FILE).is_file() or (path / CONFIG_FILE).is_file()


def prepare_run_dir(path: str | Path, overwrite: bool = False) -> Path:
    """Create an empty run directory; replace an old run only with ``overwrite`` and only if ggfslam made it."""
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise RunDirError(f"{path}: exists and is not a folder")
        if any(path.iterdir()):
            if not overwrite:
                raise RunDirError(f"{path}: run directory exists and is not empty; pass --overwrite to replace it "
                                  "or choose another --out")
            if not is_run_dir(path):
                # never delete a folder of the user's that is not one of our runs, even when asked to
                raise RunDirError(f"{path}: not a ggfslam run directory (no {RUN_INFO_FILE}); refusing to delete it "
                                  "even with --overwrite")
            shutil.rmtree(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise RunDirError(f"{path}: cannot create run directory ({e.strerror})") from None
    return path


def require_run_dir(path: str | Path) -> Path:
    """Check that ``path`` is an existing run directory with a saved config."""
    path = Path(path)
    if not path.is_dir():
        raise RunDirError(f"{path}: run directory not found")
    if not (path / CONFIG_FILE).is_file():
        raise RunDirError(f"{path}: not a ggfslam run directory ({CONFIG_FILE} missing)")
    return path


def read_json(path: Path) -> dict:
    """Read a JSON file of a run, with a one-line error when it is damaged."""
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except json.JSONDecodeError as e:
        raise RunDirError(f"{path}:{e.lineno}: not valid JSON ({e.msg})") from None


def write_json(path: Path, data: dict) -> None:
    """Write JSON atomically (temp file + rename) so an interrupted write never leaves half a file."""
    write_text_atomic(path, json.dumps(data, indent=2, sort_keys=False, default=float) + "\n")
