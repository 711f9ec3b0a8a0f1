"""Pick a dataset reader by name or by looking at a folder's layout."""
from __future__ import annotations

import inspect
from pathlib import Path

from ggfslam.data.base import RGBDDataset
from ggfslam.data.folder import ImageFolderDataset
from ggfslam.data.replica import ReplicaDataset
from ggfslam.data.scannet import ScanNetDataset
from ggfslam.data.tum import TUMDataset
from ggfslam.data.types import Camera
from ggfslam.errors import ConfigError, DatasetError

DATASET_KINDS = ("tum", "replica", "scannet", "folder")

READERS: dict[str, type[RGBDDataset]] = {
    "tum": TUMDataset,
    "replica": ReplicaDataset,
    "scannet": ScanNetDataset,
    "folder": ImageFolderDataset,
}

_LAYOUTS = ("tum: rgb.txt + depth.txt", "replica: results/ + traj.txt", "scannet: color/ + pose/ (or intrinsic/)",
            "folder: rgb/ + depth/")


def detect_kind(root: str | Path) -> str:
    """Dataset kind of a folder from its layout (one of DATASET_KINDS); DatasetError if none fits."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(root, "dataset folder not found")
    if (root / "rgb.txt").is_file() and (root / "depth.txt").is_file():
        return "tum"
    if (root / "results").is_dir() and (root / "traj.txt").is_file():
        return "replica"
    if (root / "color").is_dir() and ((root / "pose").is_dir() or (root / "intrinsic").is_dir()):
        return "scannet"
    if (root / "rgb").is_dir() and (root / "depth").is_dir():
        return "folder"
    raise DatasetError(root, f"cannot tell the dataset format of this folder: expected one of {'; '.join(_LAYOUTS)}")


def open_dataset(
    kind: str,
    root: str | Path,
    camera: Camera | None = None,
    start: int = 0,
    stop: int | None = None,
    stride: int = 1,
    resize: tuple[int, int] | None = None,
    **kwargs,
) -> RGBDDataset:
    """Open ``root`` with the reader for ``kind`` ("auto" detects it); reader options go in ``kwargs``."""
    name = str(kind).lower()
    if name == "auto":
        name = detect_kind(root)
    if name not in READERS:
        raise DatasetError(root, f"unknown dataset kind {kind!r}: expected one of auto, {', '.join(DATASET_KINDS)}")
    cls = READERS[name]
    params = inspect.signature(cls.__init__).parameters
    options = [p for p in params if p not in ("self", "root", "camera", "start", "stop", "stride", "resize")]
    for key in kwargs:
        if key not in options:  # a config typo should say what the reader accepts, not raise a bare TypeError
            raise ConfigError(f"dataset kind {name!r} has no option {key!r} (options: {', '.join(options) or 'none'})")
    return cls(root, camera=camera, start=start, stop=stop, stride=stride, resize=resize, **kwargs)
