"""Plain image-folder reader: colour images and same-named 16-bit depth PNGs, no lists, no ground truth."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ggfslam.data.base import ImageFileDataset
from ggfslam.data.paths import list_files, natural_key, require_dir
from ggfslam.data.camera_file import CAMERA_FILE, read_camera_yaml
from ggfslam.data.types import Camera
from ggfslam.errors import DatasetError

COLOUR_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def _by_stem(folder: Path, suffixes: tuple[str, ...]) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for p in list_files(folder, suffixes):
        if p.stem in out:
            raise DatasetError(p, f"two images share the name {p.stem!r} (also {out[p.stem].name})")
        out[p.stem] = p
    return out


def folder_camera(root: Path, camera: Camera | None) -> Camera:
    """``camera`` if given, else the intrinsics and depth scale of ``root/camera.yaml``."""
    if camera is not None:
        return camera
    yaml_path = root / CAMERA_FILE
    if not yaml_path.is_file():
        raise DatasetError(yaml_path, "no intrinsics: write this file or set dataset.camera (fx, fy, cx, cy, width, "
                                      "height, and depth_scale: raw depth units per metre)")
    return read_camera_yaml(yaml_path)


class ImageFolderDataset(ImageFileDataset):
    """Frames ``<rgb_dir>/<name>.<png|jpg|...>`` with depth ``<depth_dir>/<name>.png``, in natural name order.

    Intrinsics and depth scale come from ``camera`` (set its ``depth_scale``: raw units per metre), else from
    ``camera.yaml`` in ``root``. Timestamps are ``index / fps``.
    """

    def __init__(
        self,
        root: str | Path,
        camera: Camera | None = None,
        rgb_dir: str = "rgb",
        depth_dir: str = "depth",
        fps: float = 30.0,
        start: int = 0,
        stop: int | None = None,
        stride: int = 1,
        resize: tuple[int, int] | None = None,
    ):
        super().__init__(root, start=start, stop=stop, stride=stride, resize=resize)
        if not fps > 0:
            raise DatasetError(self.root, f"fps must be > 0, got {fps}")
        self._cam = folder_camera(self.root, camera)
        colour_dir = require_dir(self.root / rgb_dir, "colour image")
        depth_folder = require_dir(self.root / depth_dir, "depth image")
        colour = _by_stem(colour_dir, COLOUR_SUFFIXES)
        depth = _by_stem(depth_folder, (".png",))
        if not colour:
            raise DatasetError(colour_dir, f"no colour images ({', '.join(COLOUR_SUFFIXES)}) found")
        for stem in sorted(set(colour) | set(depth), key=natural_key):
            if stem not in depth:
                raise DatasetError(depth_folder / f"{stem}.png", f"depth image missing for {colour[stem].name} "
                                   f"({len(colour)} colour vs {len(depth)} depth images)")
            if stem not in colour:
                raise DatasetError(colour_dir / f"{stem}.*", f"colour image missing for {depth[stem].name} "
                                   f"({len(colour)} colour vs {len(depth)} depth images)")
        stems = sorted(colour, key=natural_key)
        self.rgb_files = [colour[s] for s in stems]
        self.depth_files = [depth[s] for s in stems]
        self._stamps = np.arange(len(stems)) / float(fps)  # [N]
