"""TUM RGB-D reader: ``rgb.txt`` / ``depth.txt`` lists, optional ``groundtruth.txt`` and ``camera.yaml``."""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from ggfslam.data.base import ImageFileDataset
from ggfslam.data.camera_file import CAMERA_FILE, read_camera_yaml
from ggfslam.data.trajectory_io import parse_numeric_lines, read_tum_trajectory
from ggfslam.data.types import Camera
from ggfslam.errors import DatasetError
from ggfslam.geometry.se3 import interpolate_poses

TUM_DEPTH_SCALE = 5000.0  # raw depth units per metre in every TUM sequence

# Published intrinsics of the three TUM Kinects (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats);
# fr3 images were already undistorted by the sensor, fr1/fr2 carry OpenCV k1 k2 p1 p2 k3.
TUM_CAMERAS = {
    1: Camera(517.3, 516.5, 318.6, 255.3, 640, 480, TUM_DEPTH_SCALE, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    2: Camera(520.9, 521.0, 325.1, 249.7, 640, 480, TUM_DEPTH_SCALE, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    3: Camera(535.4, 539.2, 320.1, 247.6, 640, 480, TUM_DEPTH_SCALE),
}

_TIME_EPS = 1e-6  # seconds; Unix-time stamps (~1.3e9 s) carry float64 rounding of ~2e-7 s


def _fmt_time(t: float) -> str:
    # microsecond precision, like TUM files
    return f"{t:.6f}"


def associate(rgb_stamps: np.ndarray, depth_stamps: np.ndarray, max_diff: float) -> tuple[np.ndarray, np.ndarray]:
    """Pair colour and depth timestamps like TUM's associate.py: greedy by smallest |difference| <= max_diff.

    Each stamp is used at most once. Returns index arrays (rgb_idx [M], depth_idx [M]) sorted by rgb_idx.
    Ties are broken by the smaller rgb index, then the smaller depth index, so the result is deterministic.
    Unlike associate.py (strict ``<``) a difference equal to ``max_diff`` (within 1 us of float rounding) counts.
    """
    if not max_diff >= 0:
        raise ValueError(f"max_diff must be >= 0, got {max_diff}")
    rgb = np.asarray(rgb_stamps, dtype=np.float64).reshape(-1)  # [Nr]
    dep = np.asarray(depth_stamps, dtype=np.float64).reshape(-1)  # [Nd]
    empty = np.zeros(0, dtype=np.int64)
    if len(rgb) == 0 or len(dep) == 0:
        return empty, empty
    # candidate pairs from a sorted window search instead of all Nr x Nd differences (long sequences)
    d_order = np.argsort(dep, kind="stable")
    d_sorted = dep[d_order]
    lo = np.searchsorted(d_sorted, rgb - max_diff - _TIME_EPS, side="left")  # [Nr]
    hi = np.searchsorted(d_sorted, rgb + max_diff + _TIME_EPS, side="right")  # [Nr]
    counts = hi - lo
    total = int(counts.sum())
    if total == 0:
        return empty, empty
    cand_r = np.repeat(np.arange(len(rgb)), counts)  # [C]
    within = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)  # [C] offset inside each window
    cand_d = d_order[np.repeat(lo, counts) + within]  # [C]
    diff = np.abs(rgb[cand_r] - dep[cand_d])  # [C]
    keep = diff <= max_diff + _TIME_EPS
    cand_r, cand_d, diff = cand_r[keep], cand_d[keep], diff[keep]
    order = np.lexsort((cand_d, cand_r, diff))  # primary key: diff
    used_r = np.zeros(len(rgb), dtype=bool)
    used_d = np.zeros(len(dep), dtype=bool)
    pairs = []
    for k in order:  # a handful of candidates per frame: a plain loop is fast enough
        r, d = cand_r[k], cand_d[k]
        if not used_r[r] and not used_d[d]:
            used_r[r] = used_d[d] = True
            pairs.append((r, d))
    pairs.sort()
    out = np.array(pairs, dtype=np.int64).reshape(-1, 2)  # [M, 2]
    return out[:, 0], out[:, 1]


def read_image_list(path: str | Path, root: str | Path, check_files: bool = True) -> tuple[np.ndarray, list[Path]]:
    """Read a TUM image list (``timestamp filename`` per line): timestamps [N] and absolute file paths, by time.

    Paths are relative to ``root``; with ``check_files`` every listed file must exist.
    """
    path, root = Path(path), Path(root)
    stamps, files, linenos = [], [], []
    for lineno, fields in parse_numeric_lines(path, 2):
        t = float(fields[0])
        if not math.isfinite(t):
            raise DatasetError(path, f"timestamp must be finite, got {fields[0]!r}", lineno)
        f = root / fields[1]
        if check_files and not f.is_file():
            raise DatasetError(path, f"listed image {fields[1]} not found (looked for {f})", lineno)
        stamps.append(t)
        files.append(f)
        linenos.append(lineno)
    if not stamps:
        raise DatasetError(path, "image list holds no entries ('timestamp filename' lines)")
    stamps_arr = np.array(stamps)  # [N]
    order = np.argsort(stamps_arr, kind="stable")
    sorted_stamps = stamps_arr[order]
    dup = np.nonzero(np.diff(sorted_stamps) == 0)[0]
    if len(dup):
        lineno = linenos[order[dup[0] + 1]]
        raise DatasetError(path, f"timestamp {_fmt_time(sorted_stamps[dup[0]])} appears twice", lineno)
    return sorted_stamps, [files[i] for i in order]


def tum_default_camera(folder_name: str) -> Camera | None:
    """Published TUM intrinsics if the folder name says freiburg1/2/3 (or fr1/2/3), else None."""
    found = {int(m) for m in re.findall(r"(?<![a-z])(?:freiburg|fr)([123])(?![0-9])", folder_name.lower())}
    return TUM_CAMERAS[found.pop()] if len(found) == 1 else None  # two different sensors named: ambiguous


class TUMDataset(ImageFileDataset):
    """A TUM RGB-D sequence: colour frames paired with the nearest depth frame, ground truth interpolated.

    Frames are the colour images of ``rgb.txt`` that have a depth image in ``depth.txt`` within
    ``max_time_diff`` seconds (associate.py's greedy rule); the rest are dropped (``n_unmatched``).
    When ``groundtruth.txt`` exists, frames further than ``max_time_diff`` outside its time span are dropped
    too (``n_outside_gt``) and every kept frame gets the pose interpolated at its colour timestamp (slerp /
    lerp between the bracketing samples, however far apart they are).

    With ``check_files`` every listed image must exist when the folder is opened; without, a missing one fails
    only when its frame is read (a run then skips that frame, ``dataset.on_bad_frame``).

    Intrinsics: ``camera`` if given (its ``depth_scale`` is used as is), else ``camera.yaml`` in ``root``,
    else the published TUM intrinsics when the folder name says freiburg1/2/3. fr1 and fr2 images carry their
    lens distortion; frames come out undistorted and ``camera`` is the pinhole camera they are then
    (``data/undistort.py``).
    """

    def __init__(
        self,
        root: str | Path,
        camera: Camera | None = None,
        max_time_diff: float = 0.03,
        start: int = 0,
        stop: int | None = None,
        stride: int = 1,
        resize: tuple[int, int] | None = None,
        check_files: bool = True,
    ):
        super().__init__(root, start=start, stop=stop, stride=stride, resize=resize)
        if not (isinstance(max_time_diff, (int, float)) and max_time_diff >= 0):
            raise DatasetError(self.root, f"max_time_diff must be a number >= 0 seconds, got {max_time_diff!r}")
        self._cam, self.camera_source = self._find_camera(camera)
        rgb_list, depth_list = self.root / "rgb.txt", self.root / "depth.txt"
        rgb_stamps, rgb_files = read_image_list(rgb_list, self.root, check_files)  # [Nr]
        depth_stamps, depth_files = read_image_list(depth_list, self.root, check_files)  # [Nd]
        ri, di = associate(rgb_stamps, depth_stamps, max_time_diff)
        if len(ri) == 0:
            raise DatasetError(rgb_list, f"no colour frame has a depth frame in {depth_list.name} within "
                                         f"max_time_diff={max_time_diff} s")
        self.n_unmatched = len(rgb_stamps) - len(ri)
        self.n_outside_gt = 0
        self._gt: np.ndarray | None = None
        gt_path = self.root / "groundtruth.txt"
        if gt_path.exists():
            gt_stamps, gt_poses = read_tum_trajectory(gt_path)  # [G], [G, 4, 4]
            dup = np.nonzero(np.diff(gt_stamps) == 0)[0]
            if len(dup):  # slerp needs strictly increasing times
                raise DatasetError(gt_path, f"timestamp {_fmt_time(gt_stamps[dup[0]])} appears twice")
            t = rgb_stamps[ri]
            inside = (t >= gt_stamps[0] - max_time_diff) & (t <= gt_stamps[-1] + max_time_diff)
            if not inside.any():
                raise DatasetError(gt_path, f"no colour frame lies within the ground-truth time span "
                                            f"[{_fmt_time(gt_stamps[0])}, {_fmt_time(gt_stamps[-1])}] "
                                            f"(+/- {max_time_diff} s)")
            self.n_outside_gt = int((~inside).sum())
            ri, di = ri[inside], di[inside]
            self._gt = interpolate_poses(gt_stamps, gt_poses, rgb_stamps[ri])  # [N, 4, 4]
        self._stamps = rgb_stamps[ri]  # [N]
        self.depth_timestamps = depth_stamps[di]  # [N] stamp of the depth image paired with each frame
        self.rgb_files = [rgb_files[i] for i in ri]
        self.depth_files = [depth_files[i] for i in di]

    def _find_camera(self, camera: Camera | None) -> tuple[Camera, str]:
        if camera is not None:
            return camera, "argument"
        yaml_path = self.root / CAMERA_FILE
        if yaml_path.exists():
            return read_camera_yaml(yaml_path, default_depth_scale=TUM_DEPTH_SCALE), str(yaml_path)
        cam = tum_default_camera(self.root.name)
        if cam is not None:
            return cam, "TUM published intrinsics for the folder name"
        raise DatasetError(self.root, f"no intrinsics: set dataset.camera (fx, fy, cx, cy, width, height), write "
                                      f"{CAMERA_FILE} in the folder, or name the folder after its TUM sensor "
                                      f"(freiburg1/2/3 or fr1/2/3)")
