"""Shared fixtures: the real data folder (skipped when absent) and builders of tiny datasets in tmp_path."""
from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ggfslam.data.paths import default_data_root
from ggfslam.geometry.se3 import make_pose, pose_to_tum

TOY_SIZE = (8, 6)  # (width, height) of the synthetic images


def toy_pose(i: int) -> np.ndarray:
    """Deterministic camera-to-world pose [4, 4] of synthetic frame ``i`` (a slow turn while moving along x)."""
    R = Rotation.from_rotvec([0.0, 0.05 * i, 0.02 * i]).as_matrix()
    return make_pose(R, [0.1 * i, -0.05 * i, 0.02 * i])


def toy_rgb(i: int, size: tuple[int, int] = TOY_SIZE) -> np.ndarray:
    """Synthetic BGR uint8 image [H, W, 3] whose values encode ``i`` (for cv2.imwrite)."""
    w, h = size
    img = np.zeros((h, w, 3), dtype=np.uint8)
    img[..., 0] = (10 * i) % 256
    img[..., 1] = np.arange(w, dtype=np.uint8)[None, :] * 8
    img[..., 2] = np.arange(h, dtype=np.uint8)[:, None] * 8
    return img


def toy_depth_m(i: int, size: tuple[int, int] = TOY_SIZE) -> np.ndarray:
    """Synthetic metric depth [H, W] of frame ``i``: 1 m + 0.1 m per frame, plus a small column ramp."""
    w, h = size
    return np.tile(1.0 + 0.1 * i + 0.01 * np.arange(w), (h, 1))


def write_depth_png(path: Path, depth_m: np.ndarray, scale: float) -> None:
    """Write metric depth as a 16-bit PNG with ``scale`` units per metre."""
    assert cv2.imwrite(str(path), np.round(depth_m * scale).astype(np.uint16))


def write_camera_yaml_text(path: Path, size: tuple[int, int] = TOY_SIZE, depth_scale: float = 5000.0) -> None:
    """Write a valid camera.yaml for the toy image size."""
    w, h = size
    path.write_text(f"fx: 10.0\nfy: 11.0\ncx: {w / 2 - 0.5}\ncy: {h / 2 - 0.5}\nwidth: {w}\nheight: {h}\n"
                    f"depth_scale: {depth_scale}\ndistortion: []\n")


@pytest.fixture
def toy() -> SimpleNamespace:
    """The synthetic-frame generators the builders use, so tests can compute expected values."""
    return SimpleNamespace(pose=toy_pose, rgb=toy_rgb, depth_m=toy_depth_m, size=TOY_SIZE)


@pytest.fixture(scope="session")
def data_root() -> Path:
    """The shared real data folder; skips the test when it is absent."""
    root = default_data_root()
    if not root.is_dir():
        pytest.skip(f"shared real data not found at {root} (set GGFSLAM_DATA to its folder)")
    return root


@pytest.fixture
def make_tum(tmp_path):
    """Builder of a TUM-layout folder with PNG images, lists, optional ground truth and camera.yaml."""

    def build(n: int = 3, rgb_stamps=None, depth_stamps=None, gt: bool = True, camera_yaml: bool = True,
              name: str = "tum_toy") -> Path:
        root = tmp_path / name
        (root / "rgb").mkdir(parents=True)
        (root / "depth").mkdir()
        rgb_stamps = [100.0 + i / 30 for i in range(n)] if rgb_stamps is None else list(rgb_stamps)
        depth_stamps = list(rgb_stamps) if depth_stamps is None else list(depth_stamps)
        rgb_lines = ["# color images", "# timestamp filename"]
        for i, t in enumerate(rgb_stamps):
            assert cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), toy_rgb(i))
            rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines = ["# depth maps", "# timestamp filename"]
        for i, t in enumerate(depth_stamps):
            write_depth_png(root / "depth" / f"{t:.6f}.png", toy_depth_m(i), 5000.0)
            depth_lines.append(f"{t:.6f} depth/{t:.6f}.png")
        (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
        (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
        if gt:
            gt_lines = ["# timestamp tx ty tz qx qy qz qw"]
            for i, t in enumerate(rgb_stamps):
                gt_lines.append(f"{t:.6f} " + " ".join(f"{v:.9f}" for v in pose_to_tum(toy_pose(i))))
            (root / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
        if camera_yaml:
            write_camera_yaml_text(root / "camera.yaml")
        return root

    return build


@pytest.fixture
def make_replica(tmp_path):
    """Builder of a NICE-SLAM Replica folder (results/, traj.txt, cam_params.json)."""

    def build(n: int = 3, n_poses: int | None = None, scale: float = 6553.5) -> Path:
        root = tmp_path / "replica_toy"
        (root / "results").mkdir(parents=True)
        for i in range(n):
            assert cv2.imwrite(str(root / "results" / f"frame{i:06d}.jpg"), toy_rgb(i))
            write_depth_png(root / "results" / f"depth{i:06d}.png", toy_depth_m(i), scale)
        poses = [toy_pose(i) for i in range(n if n_poses is None else n_poses)]
        (root / "traj.txt").write_text("".join(" ".join(f"{v:.18e}" for v in T.reshape(-1)) + "\n" for T in poses))
        w, h = TOY_SIZE
        cam = {"camera": {"w": w, "h": h, "fx": 10.0, "fy": 10.0, "cx": 3.5, "cy": 2.5, "scale": scale}}
        (root / "cam_params.json").write_text(json.dumps(cam, indent=4))
        return root

    return build


@pytest.fixture
def make_scannet(tmp_path):
    """Builder of an exported ScanNet scene; colour is twice the depth size like the real 1296x968 vs 640x480."""

    def build(numbers=(0, 2, 10), invalid=(), colour_size=(16, 12), depth_size=TOY_SIZE,
              intrinsics: bool = True) -> Path:
        root = tmp_path / "scannet_toy"
        for d in ("color", "depth", "pose", "intrinsic"):
            (root / d).mkdir(parents=True)
        for k in numbers:
            assert cv2.imwrite(str(root / "color" / f"{k}.jpg"), toy_rgb(k, colour_size))
            write_depth_png(root / "depth" / f"{k}.png", toy_depth_m(k, depth_size), 1000.0)
            T = np.full((4, 4), -np.inf) if k in invalid else toy_pose(k)
            (root / "pose" / f"{k}.txt").write_text("\n".join(" ".join(f"{v:.9f}" for v in row) for row in T) + "\n")
        if intrinsics:
            (cw, ch), (dw, dh) = colour_size, depth_size
            Kc = np.array([[20.0, 0, cw / 2 - 0.5, 0], [0, 20.0, ch / 2 - 0.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
            Kd = np.array([[10.0, 0, dw / 2 - 0.5, 0], [0, 10.0, dh / 2 - 0.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
            for name, K in (("intrinsic_color.txt", Kc), ("intrinsic_depth.txt", Kd)):
                (root / "intrinsic" / name).write_text("\n".join(" ".join(f"{v:f}" for v in row) for row in K) + "\n")
        return root

    return build


@pytest.fixture
def make_folder(tmp_path):
    """Builder of a plain rgb/ + depth/ image folder (depth in millimetres) with names in natural order."""

    def build(names=("img1", "img2", "img10"), camera_yaml: bool = False) -> Path:
        root = tmp_path / "folder_toy"
        (root / "rgb").mkdir(parents=True)
        (root / "depth").mkdir()
        for i, name in enumerate(names):
            assert cv2.imwrite(str(root / "rgb" / f"{name}.png"), toy_rgb(i))
            write_depth_png(root / "depth" / f"{name}.png", toy_depth_m(i), 1000.0)
        if camera_yaml:
            write_camera_yaml_text(root / "camera.yaml", depth_scale=1000.0)
        return root

    return build


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    """The procedural room, 30 frames at 320x240 (generated into a per-module cache)."""
    from ggfslam.config import config_from_dict
    from ggfslam.data import sources

    mp = pytest.MonkeyPatch()
    mp.setenv("GGFSLAM_CACHE", str(tmp_path_factory.mktemp("cache")))
    cfg = config_from_dict({"dataset": {"kind": "synthetic", "synthetic": {"n_frames": 30, "width": 320,
                                                                          "height": 240}}}, "test")
    yield sources.open_dataset_from_config(cfg.dataset)
    mp.undo()


def run_synthetic(tmp_path_factory, name: str, config: dict) -> Path:
    """``slam.run`` of a config dict (a synthetic sequence) into a new temporary folder with its own sequence
    cache; returns the run folder (``<tmp>/run``)."""
    from ggfslam import slam
    from ggfslam.config import config_from_dict

    root = tmp_path_factory.mktemp(name)
    mp = pytest.MonkeyPatch()
    mp.setenv("GGFSLAM_CACHE", str(root / "cache"))
    try:
        slam.run(config_from_dict({"name": name, **config}, "test"), root / "run", progress=False)
    finally:
        mp.undo()
    return root / "run"
