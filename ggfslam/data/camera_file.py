"""The ``camera.yaml`` intrinsics file: written beside every sequence ggfslam generates, read by the readers."""
from __future__ import annotations

import math
from pathlib import Path

import yaml

from ggfslam.atomic import write_text_atomic
from ggfslam.data.types import DISTORTION_LENGTHS, Camera
from ggfslam.errors import DatasetError

CAMERA_FILE = "camera.yaml"
_CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height", "depth_scale", "distortion")


def write_camera_yaml(path: str | Path, camera: Camera) -> None:
    """Save intrinsics as YAML (fx, fy, cx, cy, width, height, depth_scale, distortion)."""
    write_text_atomic(path, yaml.safe_dump(camera.to_dict(), sort_keys=False))


def _number(path: Path, data: dict, key: str, positive: bool) -> float:
    v = data[key]
    # bool is an int subclass; "true" for a focal length is a typo, not 1.0
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (positive and v <= 0):
        kind = "a positive finite number" if positive else "a finite number"
        raise DatasetError(path, f"field '{key}' must be {kind}, got {v!r}")
    return float(v)


def _size(path: Path, data: dict, key: str) -> int:
    v = data[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not float(v).is_integer() or v <= 0:
        raise DatasetError(path, f"field '{key}' must be a positive integer, got {v!r}")
    return int(v)


def read_camera_yaml(path: str | Path, default_depth_scale: float | None = None) -> Camera:
    """Read and validate intrinsics from a camera.yaml as written by ``writer.write_camera_yaml``.

    ``depth_scale`` may be omitted when ``default_depth_scale`` is given; ``distortion`` defaults to none.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "camera file not found")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise DatasetError(path, f"not valid YAML ({problem})", None if mark is None else mark.line + 1) from None
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(path, f"cannot read camera file ({e})") from None
    expected = "a mapping with fx, fy, cx, cy, width, height, depth_scale and optional distortion"
    if not isinstance(data, dict):
        raise DatasetError(path, f"expected {expected}, got {type(data).__name__}")
    unknown = sorted(str(k) for k in data if k not in _CAMERA_KEYS)
    if unknown:  # a misspelt optional key would otherwise silently fall back to its default
        raise DatasetError(path, f"unknown field '{unknown[0]}': expected {expected}")
    required = ("fx", "fy", "cx", "cy", "width", "height") + (("depth_scale",) if default_depth_scale is None else ())
    for key in required:
        if key not in data:
            raise DatasetError(path, f"field '{key}' is missing: expected {expected}")
    dist = data.get("distortion") or []
    if not isinstance(dist, (list, tuple)) or len(dist) not in DISTORTION_LENGTHS or not all(
        isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in dist
    ):
        raise DatasetError(path, f"field 'distortion' must be a list of {', '.join(map(str, DISTORTION_LENGTHS))} "
                                 f"finite numbers (OpenCV order k1 k2 p1 p2 [k3 ...]), got {dist!r}")
    depth_scale = _number(path, data, "depth_scale", True) if "depth_scale" in data else float(default_depth_scale)
    return Camera(
        fx=_number(path, data, "fx", True), fy=_number(path, data, "fy", True),
        cx=_number(path, data, "cx", False), cy=_number(path, data, "cy", False),
        width=_size(path, data, "width"), height=_size(path, data, "height"),
        depth_scale=depth_scale, distortion=tuple(float(x) for x in dist),
    )
