"""Every bad dataset input raises DatasetError naming the file (and line for text files)."""
from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest

from ggfslam.data.folder import ImageFolderDataset
from ggfslam.data.registry import detect_kind, open_dataset
from ggfslam.data.replica import ReplicaDataset
from ggfslam.data.scannet import ScanNetDataset
from ggfslam.data.tum import TUMDataset
from ggfslam.data.types import Camera
from ggfslam.errors import DatasetError

TOY_CAM = Camera(10.0, 10.0, 3.5, 2.5, 8, 6, depth_scale=1000.0)


def raises(fn, *fragments: str) -> DatasetError:
    """Call ``fn``, expect DatasetError, and check its message holds every fragment."""
    with pytest.raises(DatasetError) as info:
        fn()
    msg = str(info.value)
    for frag in fragments:
        assert frag in msg, f"{frag!r} not in {msg!r}"
    return info.value


def replace_line(path, lineno: int, text: str) -> None:
    """Overwrite line ``lineno`` (1-based) of a text file."""
    lines = path.read_text().splitlines()
    lines[lineno - 1] = text
    path.write_text("\n".join(lines) + "\n")


# --- any reader ------------------------------------------------------------------------------------------

def test_missing_dataset_folder(tmp_path):
    raises(lambda: TUMDataset(tmp_path / "nope"), "nope", "not found")


# --- TUM -------------------------------------------------------------------------------------------------

def test_dataset_error_survives_a_worker_process():
    """Benchmarks and batch runs raise it in worker processes: it must pickle with its message intact."""
    import pickle

    e = pickle.loads(pickle.dumps(DatasetError("/data/x/rgb.txt", "malformed timestamp", line=7)))
    assert isinstance(e, DatasetError) and str(e) == "/data/x/rgb.txt:7: malformed timestamp"
    assert (e.path, e.line) == ("/data/x/rgb.txt", 7)


def test_tum_missing_rgb_list(make_tum):
    root = make_tum()
    (root / "rgb.txt").unlink()
    raises(lambda: TUMDataset(root), "rgb.txt", "not found")


def test_tum_missing_depth_list(make_tum):
    root = make_tum()
    (root / "depth.txt").unlink()
    raises(lambda: TUMDataset(root), "depth.txt", "not found")


def test_tum_listed_image_missing(make_tum):
    root = make_tum()
    (root / "rgb" / "100.033333.png").unlink()  # the second frame, on line 4 of rgb.txt
    raises(lambda: TUMDataset(root), "rgb.txt:4", "rgb/100.033333.png", "not found")


def test_tum_malformed_timestamp(make_tum):
    root = make_tum()
    replace_line(root / "rgb.txt", 4, "10O.0 rgb/100.033333.png")
    raises(lambda: TUMDataset(root), "rgb.txt:4", "timestamp", "10O.0")


def test_tum_missing_file_column(make_tum):
    root = make_tum()
    replace_line(root / "depth.txt", 5, "100.066667")
    raises(lambda: TUMDataset(root), "depth.txt:5", "at least 2 columns")


def test_tum_non_finite_timestamp(make_tum):
    root = make_tum()
    replace_line(root / "rgb.txt", 5, "nan rgb/100.066667.png")
    raises(lambda: TUMDataset(root), "rgb.txt:5", "finite")


def test_tum_duplicate_timestamp(make_tum):
    root = make_tum()
    replace_line(root / "rgb.txt", 5, "100.033333 rgb/100.066667.png")
    raises(lambda: TUMDataset(root), "rgb.txt:5", "appears twice")


def test_tum_groundtruth_bad_quaternion(make_tum):
    root = make_tum()
    replace_line(root / "groundtruth.txt", 3, "100.033333 0 0 0 0 0 0 0.5")
    raises(lambda: TUMDataset(root), "groundtruth.txt:3", "unit length")


def test_tum_groundtruth_non_finite(make_tum):
    root = make_tum()
    replace_line(root / "groundtruth.txt", 2, "100.000000 inf 0 0 0 0 0 1")
    raises(lambda: TUMDataset(root), "groundtruth.txt:2", "non-finite")


def test_tum_groundtruth_span_misses_every_frame(make_tum):
    root = make_tum()
    (root / "groundtruth.txt").write_text("200.0 0 0 0 0 0 0 1\n201.0 0 0 0 0 0 0 1\n")
    raises(lambda: TUMDataset(root), "groundtruth.txt", "no colour frame lies within")


def test_tum_no_depth_partner(make_tum):
    root = make_tum(depth_stamps=[50.0, 51.0, 52.0])
    raises(lambda: TUMDataset(root), "rgb.txt", "depth.txt", "max_time_diff")


def test_tum_corrupt_colour_image(make_tum):
    root = make_tum()
    bad = root / "rgb" / "100.000000.png"
    bad.write_bytes(b"not a png at all")
    ds = TUMDataset(root)  # lazily streaming: the image is only decoded when the frame is read
    raises(lambda: ds[0], "100.000000.png", "cannot decode")


def test_tum_eight_bit_depth(make_tum):
    root = make_tum()
    cv2.imwrite(str(root / "depth" / "100.033333.png"), np.full((6, 8), 200, np.uint8))
    raises(lambda: TUMDataset(root)[1], "depth/100.033333.png", "16-bit", "8-bit")


def test_tum_colour_depth_size_mismatch(make_tum):
    root = make_tum()
    cv2.imwrite(str(root / "depth" / "100.000000.png"), np.full((3, 4), 5000, np.uint16))
    raises(lambda: TUMDataset(root)[0], "depth/100.000000.png", "depth image is 4x3", "colour image",
           "rgb/100.000000.png")


def test_tum_image_size_differs_from_camera(make_tum):
    root = make_tum()
    raises(lambda: TUMDataset(root, camera=Camera(10, 10, 5, 5, 10, 10))[0], "100.000000.png", "expected 10x10")


def test_camera_yaml_missing_field(make_tum):
    root = make_tum()
    text = (root / "camera.yaml").read_text()
    (root / "camera.yaml").write_text(text.replace("fy: 11.0\n", ""))
    raises(lambda: TUMDataset(root), "camera.yaml", "'fy'", "missing")


def test_camera_yaml_bad_value(make_tum):
    root = make_tum()
    text = (root / "camera.yaml").read_text()
    (root / "camera.yaml").write_text(text.replace("fx: 10.0", "fx: -3"))
    raises(lambda: TUMDataset(root), "camera.yaml", "'fx'", "positive")


def test_camera_yaml_unknown_field(make_tum):
    root = make_tum()
    (root / "camera.yaml").write_text((root / "camera.yaml").read_text() + "depthscale: 1000\n")
    raises(lambda: TUMDataset(root), "camera.yaml", "unknown field 'depthscale'")


def test_camera_yaml_bad_distortion(make_tum):
    root = make_tum()
    text = (root / "camera.yaml").read_text()
    (root / "camera.yaml").write_text(text.replace("distortion: []", "distortion: [0.1, 0.2, 0.3]"))
    raises(lambda: TUMDataset(root), "camera.yaml", "'distortion'")


def test_camera_yaml_syntax_error(make_tum):
    root = make_tum()
    (root / "camera.yaml").write_text("fx: 10\nfy: [11\ncx: 3\n")
    raises(lambda: TUMDataset(root), "camera.yaml:", "not valid YAML")


def test_camera_yaml_not_a_mapping(make_tum):
    root = make_tum()
    (root / "camera.yaml").write_text("- 10\n- 11\n")
    raises(lambda: TUMDataset(root), "camera.yaml", "expected a mapping")


def test_tum_no_intrinsics(make_tum):
    root = make_tum(camera_yaml=False, name="office")
    raises(lambda: TUMDataset(root), "office", "no intrinsics", "dataset.camera", "camera.yaml")


# --- Replica ---------------------------------------------------------------------------------------------

def test_replica_missing_results_folder(make_replica):
    root = make_replica()
    shutil.rmtree(root / "results")
    raises(lambda: ReplicaDataset(root), "results", "not found")


def test_replica_missing_cam_params(make_replica):
    root = make_replica()
    (root / "cam_params.json").unlink()
    raises(lambda: ReplicaDataset(root), "cam_params.json", "not found")


def test_replica_cam_params_missing_key(make_replica):
    root = make_replica()
    (root / "cam_params.json").write_text('{"camera": {"w": 8, "h": 6, "fx": 10, "fy": 10, "cx": 3.5, "cy": 2.5}}')
    raises(lambda: ReplicaDataset(root), "cam_params.json", "camera.scale")


def test_replica_cam_params_invalid_json(make_replica):
    root = make_replica()
    (root / "cam_params.json").write_text('{\n  "camera": {"w": 8,,}\n}')
    raises(lambda: ReplicaDataset(root), "cam_params.json:2", "not valid JSON")


def test_replica_depth_count_mismatch(make_replica):
    root = make_replica()
    (root / "results" / "depth000001.png").unlink()
    raises(lambda: ReplicaDataset(root), "depth000001.png", "frame000001.jpg", "3 colour vs 2 depth")


def test_replica_fewer_poses_than_images(make_replica):
    root = make_replica(n=3, n_poses=2)
    raises(lambda: ReplicaDataset(root), "traj.txt", "2 poses", "frame000002.jpg")


def test_replica_non_rigid_pose(make_replica):
    root = make_replica()
    replace_line(root / "traj.txt", 2, " ".join(["2", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", "0",
                                                 "0", "0", "0", "1"]))
    raises(lambda: ReplicaDataset(root), "traj.txt:2", "orthonormal")


def test_replica_non_finite_pose(make_replica):
    root = make_replica()
    replace_line(root / "traj.txt", 3, " ".join(["nan"] * 16))
    raises(lambda: ReplicaDataset(root), "traj.txt:3", "non-finite")


def test_replica_malformed_pose_line(make_replica):
    root = make_replica()
    replace_line(root / "traj.txt", 1, "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0")
    raises(lambda: ReplicaDataset(root), "traj.txt:1", "expected 16 numbers")


# --- ScanNet ---------------------------------------------------------------------------------------------

def test_scannet_depth_missing(make_scannet):
    root = make_scannet()
    (root / "depth" / "2.png").unlink()
    raises(lambda: ScanNetDataset(root), "depth/2.png", "2.jpg", "3 colour vs 2 depth")


def test_scannet_non_numeric_name(make_scannet):
    root = make_scannet()
    shutil.copy(root / "color" / "0.jpg", root / "color" / "frame_a.jpg")
    raises(lambda: ScanNetDataset(root), "frame_a.jpg", "frame-number")


def test_scannet_pose_file_missing(make_scannet):
    root = make_scannet()
    (root / "pose" / "10.txt").unlink()
    raises(lambda: ScanNetDataset(root), "pose/10.txt", "missing")


def test_scannet_partly_non_finite_pose(make_scannet):
    root = make_scannet()
    replace_line(root / "pose" / "2.txt", 1, "1 0 0 -inf")
    raises(lambda: ScanNetDataset(root), "pose/2.txt", "partly non-finite")


def test_scannet_non_rigid_pose(make_scannet):
    root = make_scannet()
    replace_line(root / "pose" / "2.txt", 4, "0 0 1 1")
    raises(lambda: ScanNetDataset(root), "pose/2.txt", "last row")


def test_scannet_malformed_pose_line(make_scannet):
    root = make_scannet()
    replace_line(root / "pose" / "0.txt", 2, "0 1 zero 0")
    raises(lambda: ScanNetDataset(root), "pose/0.txt:2", "expected 4 numbers")


def test_scannet_every_pose_invalid(make_scannet):
    root = make_scannet(invalid=(0, 2, 10))
    raises(lambda: ScanNetDataset(root), "pose", "every pose is invalid")


def test_scannet_intrinsics_missing(make_scannet):
    root = make_scannet(intrinsics=False)
    raises(lambda: ScanNetDataset(root), "intrinsic_depth.txt", "not found")


def test_scannet_intrinsics_malformed(make_scannet):
    root = make_scannet()
    (root / "intrinsic" / "intrinsic_depth.txt").write_text("10 0 3.5 0\n0 10 2.5 0\n0 0 1 0\n")
    raises(lambda: ScanNetDataset(root), "intrinsic_depth.txt", "4x4 matrix", "got 3 lines")


# --- image folder ----------------------------------------------------------------------------------------

def test_folder_depth_missing_for_colour(make_folder):
    root = make_folder()
    (root / "depth" / "img2.png").unlink()
    raises(lambda: ImageFolderDataset(root, TOY_CAM), "depth/img2.png", "img2.png", "3 colour vs 2 depth")


def test_folder_colour_missing_for_depth(make_folder):
    root = make_folder()
    shutil.copy(root / "depth" / "img1.png", root / "depth" / "img0.png")
    raises(lambda: ImageFolderDataset(root, TOY_CAM), "rgb/img0.*", "3 colour vs 4 depth")


def test_folder_missing_rgb_dir(make_folder):
    root = make_folder()
    raises(lambda: ImageFolderDataset(root, TOY_CAM, rgb_dir="colour"), "colour", "not found")


def test_folder_without_camera(make_folder):
    root = make_folder()
    raises(lambda: ImageFolderDataset(root), "camera.yaml", "no intrinsics")


# --- registry --------------------------------------------------------------------------------------------

def test_unknown_dataset_format(tmp_path):
    (tmp_path / "stuff").mkdir()
    raises(lambda: detect_kind(tmp_path), "cannot tell the dataset format", str(tmp_path), "rgb.txt")
    raises(lambda: open_dataset("auto", tmp_path), "cannot tell the dataset format")


def test_unknown_dataset_kind(make_tum):
    root = make_tum()
    raises(lambda: open_dataset("kitti", root), "unknown dataset kind 'kitti'", "tum, replica, scannet, folder")
