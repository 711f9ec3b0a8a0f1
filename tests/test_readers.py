"""Dataset readers on the shared real data (skipped when absent) and on tiny synthetic folders."""
from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ggfslam.data.folder import ImageFolderDataset
from ggfslam.data.paths import default_data_root, natural_key
from ggfslam.data.registry import DATASET_KINDS, detect_kind, open_dataset
from ggfslam.data.replica import ReplicaDataset
from ggfslam.data.scannet import ScanNetDataset
from ggfslam.data.tum import TUM_CAMERAS, TUMDataset, associate, read_image_list, tum_default_camera
from ggfslam.data.types import Camera, Frame
from ggfslam.data.undistort import Undistortion
from ggfslam.data.writer import write_tum_sequence
from ggfslam.errors import ConfigError
from ggfslam.geometry.se3 import rigidity_error


def _table(path: Path, ncols: int) -> np.ndarray:
    """First ``ncols`` numeric columns [N, ncols] of a TUM text file, read independently of the reader."""
    rows = [ln.split() for ln in path.read_text().splitlines()]
    return np.array([[float(x) for x in r[:ncols]] for r in rows if r and r[0][0].isdigit()])


def _reference_associate(first: np.ndarray, second: np.ndarray, max_difference: float) -> list[tuple[int, int]]:
    """TUM's associate.py, transcribed: all pairs within max_difference, taken greedily by difference."""
    diffs = np.abs(first[:, None] - second[None, :])  # [Nr, Nd]
    potential = sorted((diffs[a, b], a, b) for a, b in zip(*np.nonzero(diffs < max_difference)))
    free_a, free_b, matches = set(range(len(first))), set(range(len(second))), []
    for _, a, b in potential:
        if a in free_a and b in free_b:
            free_a.remove(a)
            free_b.remove(b)
            matches.append((int(a), int(b)))
    return sorted(matches)


# --- paths ------------------------------------------------------------------------------------------------

def test_default_data_root_env_and_fallback(monkeypatch, tmp_path):
    monkeypatch.setenv("GGFSLAM_DATA", str(tmp_path))
    assert default_data_root() == tmp_path
    monkeypatch.delenv("GGFSLAM_DATA")
    repo = Path(__file__).resolve().parents[1]
    assert default_data_root() == repo.parent / "shared" / "data"


def test_natural_key_orders_numbers_by_value():
    assert sorted(["img10", "img2", "Img1", "img2b"], key=natural_key) == ["Img1", "img2", "img2b", "img10"]


# --- association ----------------------------------------------------------------------------------------

def test_associate_is_greedy_by_smallest_difference():
    # rgb 0 is nearest to depth 0, but rgb 1 is nearer still: depth 0 goes to rgb 1, rgb 0 takes depth 1
    rgb = np.array([1.00, 1.02])
    depth = np.array([1.019, 1.035])
    ri, di = associate(rgb, depth, 0.04)
    assert ri.tolist() == [0, 1] and di.tolist() == [1, 0]
    ri, di = associate(rgb, depth, 0.01)  # only rgb 1 has a partner this close
    assert ri.tolist() == [1] and di.tolist() == [0]
    ri, di = associate(rgb, np.zeros(0), 0.03)
    assert ri.shape == (0,) and di.shape == (0,)


def test_associate_matches_tum_script_on_fr1_xyz_lists(data_root):
    lists = data_root / "tum_fr1_xyz_lists"
    rgb, _ = read_image_list(lists / "rgb.txt", lists, check_files=False)
    depth, _ = read_image_list(lists / "depth.txt", lists, check_files=False)
    assert len(rgb) == 798 and len(depth) == 798
    for max_diff, expected in ((0.02, 792), (0.03, 793)):
        ri, di = associate(rgb, depth, max_diff)
        assert len(ri) == expected
        assert list(zip(ri.tolist(), di.tolist())) == _reference_associate(rgb, depth, max_diff)
        assert np.all(np.abs(rgb[ri] - depth[di]) <= max_diff)
        assert len(set(di.tolist())) == len(di)  # each depth image used once


def test_groundtruth_interpolation_matches_hand_computation(data_root, tmp_path, toy):
    src = data_root / "tum_fr1_xyz_lists"
    rgb_stamps = _table(src / "rgb.txt", 1)[:3, 0]  # first three real colour timestamps
    root = tmp_path / "seq"
    (root / "img").mkdir(parents=True)
    shutil.copy(src / "groundtruth.txt", root / "groundtruth.txt")
    lines = []
    for i, t in enumerate(rgb_stamps):
        assert cv2.imwrite(str(root / "img" / f"{i}.png"), toy.rgb(i))
        assert cv2.imwrite(str(root / "img" / f"d{i}.png"), np.full((6, 8), 5000, np.uint16))
        lines.append((f"{t:.6f} img/{i}.png", f"{t:.6f} img/d{i}.png"))
    (root / "rgb.txt").write_text("\n".join(a for a, _ in lines) + "\n")
    (root / "depth.txt").write_text("\n".join(b for _, b in lines) + "\n")
    ds = TUMDataset(root, camera=Camera(10, 10, 3.5, 2.5, 8, 6, 5000.0))
    gt = _table(src / "groundtruth.txt", 8)  # [G, 8]
    for i, t in enumerate(rgb_stamps):
        k = np.searchsorted(gt[:, 0], t)  # gt[k-1, 0] < t <= gt[k, 0]
        t0, t1 = gt[k - 1, 0], gt[k, 0]
        a = (t - t0) / (t1 - t0)
        assert 0 < a < 1  # a real blend of two samples, not a copy of one
        expected_t = (1 - a) * gt[k - 1, 1:4] + a * gt[k, 1:4]
        R0 = Rotation.from_quat(gt[k - 1, 4:8])
        R1 = Rotation.from_quat(gt[k, 4:8])
        expected_R = (R0 * Rotation.from_rotvec(a * (R0.inv() * R1).as_rotvec())).as_matrix()
        np.testing.assert_allclose(ds.gt_poses[i][:3, 3], expected_t, atol=1e-9)
        np.testing.assert_allclose(ds.gt_poses[i][:3, :3], expected_R, atol=1e-9)
    assert ds[1].T_wc is not None and np.allclose(ds[1].T_wc, ds.gt_poses[1])


# --- TUM on real data -----------------------------------------------------------------------------------

def test_tum_fr3_cabinet_loads(data_root):
    root = data_root / "tum_fr3_cabinet_kf"
    ds = TUMDataset(root)
    assert len(ds) == 58
    assert ds.camera == TUM_CAMERAS[3]
    assert (ds.camera.width, ds.camera.height, ds.camera.depth_scale) == (640, 480, 5000.0)
    rgb_list = _table(root / "rgb.txt", 1)[:, 0]
    np.testing.assert_array_equal(ds.timestamps, rgb_list)
    np.testing.assert_array_equal(ds.depth_timestamps, _table(root / "depth.txt", 1)[:, 0])
    assert ds.n_unmatched == 0 and ds.n_outside_gt == 0
    assert all(rigidity_error(T) is None for T in ds.gt_poses)
    gt = _table(root / "groundtruth.txt", 8)
    np.testing.assert_allclose(ds.gt_poses[:, :3, 3], gt[:, 1:4], atol=1e-9)  # stamps coincide: no blending
    f = ds[10]
    assert isinstance(f, Frame) and f.rgb.shape == (480, 640, 3) and f.depth.shape == (480, 640)
    assert f.rgb.dtype == np.float32 and 0.0 <= f.rgb.min() and f.rgb.max() <= 1.0
    assert f.timestamp == rgb_list[10] and f.name.endswith("0010_rgb_raw.jpg")
    valid = f.depth[f.depth > 0]
    assert valid.size > 0.5 * f.depth.size and 0.3 < np.median(valid) < 5.0


def test_tum_selection_and_resize(data_root):
    root = data_root / "tum_fr3_cabinet_kf"
    full = TUMDataset(root)
    ds = TUMDataset(root, start=5, stop=20, stride=3, resize=(320, 240))
    assert ds.indices.tolist() == [5, 8, 11, 14, 17] and len(ds) == 5
    np.testing.assert_array_equal(ds.timestamps, full.timestamps[5:20:3])
    np.testing.assert_array_equal(ds.gt_poses, full.gt_poses[5:20:3])
    cam = ds.camera
    assert (cam.width, cam.height) == (320, 240)
    assert cam.fx == pytest.approx(535.4 / 2) and cam.fy == pytest.approx(539.2 / 2)
    assert cam.cx == pytest.approx((320.1 + 0.5) / 2 - 0.5) and cam.cy == pytest.approx((247.6 + 0.5) / 2 - 0.5)
    f = ds[-1]
    assert f.index == 4 and f.timestamp == full.timestamps[17]
    assert f.rgb.shape == (240, 320, 3) and f.depth.shape == (240, 320)
    # nearest-neighbour depth resize keeps measured values only (no blends across edges)
    assert np.isin(np.unique(f.depth), np.unique(full[17].depth)).all()


# --- Replica on real data -------------------------------------------------------------------------------

def test_replica_office0_mini_loads(data_root):
    root = data_root / "replica_office0_mini"
    ds = ReplicaDataset(root)
    assert len(ds) == 4
    cam = ds.camera
    assert (cam.width, cam.height, cam.depth_scale) == (1200, 680, 6553.5)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (600.0, 600.0, 599.5, 339.5)
    traj = np.loadtxt(root / "traj.txt", max_rows=4).reshape(4, 4, 4)
    np.testing.assert_array_equal(ds.gt_poses, traj)
    np.testing.assert_allclose(ds.timestamps, np.arange(4) / 30.0)
    f = ds[2]
    assert f.rgb.shape == (680, 1200, 3) and f.depth.shape == (680, 1200)
    np.testing.assert_array_equal(f.T_wc, traj[2])
    valid = f.depth[f.depth > 0]
    assert valid.size > 0.9 * f.depth.size and 0.3 < np.median(valid) < 10.0


def test_detect_kind_on_real_data(data_root):
    assert detect_kind(data_root / "tum_fr3_cabinet_kf") == "tum"
    assert detect_kind(data_root / "replica_office0_mini") == "replica"
    ds = open_dataset("auto", data_root / "replica_office0_mini", stop=2)
    assert isinstance(ds, ReplicaDataset) and len(ds) == 2


# --- TUM on synthetic data ------------------------------------------------------------------------------

def test_tum_synthetic_association_and_gt_span(make_tum, toy):
    rgb = [100.0, 100.1, 100.2, 100.3]
    depth = [100.005, 100.19, 100.33]  # rgb 100.1 has no partner within 0.03 s; 100.33 is on the boundary
    root = make_tum(rgb_stamps=rgb, depth_stamps=depth)
    gt = root / "groundtruth.txt"
    gt.write_text("\n".join(gt.read_text().splitlines()[:3]) + "\n")  # gt for 100.0 and 100.1 only
    (root / "rgb.txt").write_text((root / "rgb.txt").read_text() + "99.0 rgb/100.000000.png\n")  # before gt span
    (root / "depth.txt").write_text((root / "depth.txt").read_text() + "99.01 depth/100.005000.png\n")
    ds = TUMDataset(root)
    # 99.0 is outside the gt span; 100.1 unmatched; 100.2 beyond gt end (100.1) by more than 0.03 s
    assert ds.timestamps.tolist() == [100.0] and ds.n_unmatched == 1 and ds.n_outside_gt == 3
    np.testing.assert_allclose(ds.gt_poses[0], toy.pose(0), atol=1e-6)
    (root / "groundtruth.txt").unlink()
    ds_nogt = TUMDataset(root)
    assert ds_nogt.gt_poses is None and ds_nogt[0].T_wc is None
    assert ds_nogt.timestamps.tolist() == [99.0, 100.0, 100.2, 100.3]
    np.testing.assert_allclose(ds_nogt.depth_timestamps, [99.01, 100.005, 100.19, 100.33])
    f = ds_nogt[3]
    np.testing.assert_allclose(f.depth, toy.depth_m(2), atol=1 / 5000)  # depth list entry 2 (100.33)
    np.testing.assert_allclose(f.rgb[..., 2], toy.rgb(3)[..., 0] / 255.0, atol=1e-6)  # BGR -> RGB


def test_tum_reads_camera_yaml_and_explicit_camera_wins(make_tum):
    root = make_tum(name="rgbd_dataset_freiburg1_toy")
    ds = TUMDataset(root)
    assert (ds.camera.fx, ds.camera.fy, ds.camera.width, ds.camera.height) == (10.0, 11.0, 8, 6)
    assert ds.camera_source.endswith("camera.yaml")
    cam = Camera(7.0, 7.0, 3.5, 2.5, 8, 6, depth_scale=2500.0)
    ds = TUMDataset(root, camera=cam)
    assert ds.camera == cam
    np.testing.assert_allclose(ds[0].depth, 2 * TUMDataset(root)[0].depth)
    (root / "camera.yaml").unlink()
    fallback = TUMDataset(root)
    assert fallback.raw_camera == TUM_CAMERAS[1]  # falls back to the folder name
    assert fallback.camera == Undistortion(TUM_CAMERAS[1]).camera  # whose frames come out undistorted


def test_tum_default_camera_from_folder_name():
    assert tum_default_camera("rgbd_dataset_freiburg1_xyz") == TUM_CAMERAS[1]
    assert tum_default_camera("tum_fr2_desk") == TUM_CAMERAS[2]
    assert tum_default_camera("FR3-cabinet") == TUM_CAMERAS[3]
    assert tum_default_camera("fr10_scene") is None
    assert tum_default_camera("fr1_vs_fr3") is None  # ambiguous
    assert tum_default_camera("office") is None
    assert TUM_CAMERAS[1].distortion == (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)


def test_tum_reads_what_writer_wrote(tmp_path, toy):
    cam = Camera(10.0, 10.0, 3.5, 2.5, 8, 6)
    frames = [Frame(i, 5.0 + i / 30, toy.rgb(i)[..., ::-1] / 255.0, toy.depth_m(i).astype(np.float32), toy.pose(i))
              for i in range(3)]
    out = write_tum_sequence(tmp_path / "written", frames, cam, depth_scale=5000.0)
    ds = open_dataset("auto", out)
    assert isinstance(ds, TUMDataset) and len(ds) == 3 and ds.camera.depth_scale == 5000.0
    for f, g in zip(frames, ds):
        assert g.timestamp == pytest.approx(f.timestamp, abs=1e-6)
        np.testing.assert_allclose(g.rgb, f.rgb, atol=1 / 255)
        np.testing.assert_allclose(g.depth, f.depth, atol=1 / 5000)
        np.testing.assert_allclose(g.T_wc, f.T_wc, atol=1e-6)


# --- Replica, ScanNet, folder on synthetic data ---------------------------------------------------------

def test_replica_synthetic_extra_poses_ignored(make_replica, toy):
    ds = ReplicaDataset(make_replica(n=3, n_poses=7), fps=10.0)
    assert len(ds) == 3 and ds.gt_poses.shape == (3, 4, 4)
    np.testing.assert_allclose(ds.gt_poses[2], toy.pose(2), atol=1e-12)
    np.testing.assert_allclose(ds.timestamps, [0.0, 0.1, 0.2])
    np.testing.assert_allclose(ds[1].depth, toy.depth_m(1), atol=1 / 6553.5)


def test_scannet_synthetic(make_scannet, toy):
    root = make_scannet(numbers=(0, 2, 10, 11), invalid=(11,))
    ds = ScanNetDataset(root)
    assert ds.frame_numbers.tolist() == [0, 2, 10] and ds.skipped_invalid_pose == [11]  # numeric, not "10" < "2"
    np.testing.assert_allclose(ds.timestamps, [0.0, 2 / 30, 10 / 30])
    cam = ds.camera
    assert (cam.width, cam.height, cam.fx, cam.cx, cam.depth_scale) == (8, 6, 10.0, 3.5, 1000.0)
    f = ds[2]
    assert f.rgb.shape == (6, 8, 3) and f.name.endswith("10.jpg")  # colour brought to the depth size
    np.testing.assert_allclose(f.depth, toy.depth_m(10), atol=1e-3)
    np.testing.assert_allclose(f.T_wc, toy.pose(10), atol=1e-8)
    assert detect_kind(root) == "scannet"


def test_scannet_colour_intrinsics_scaled_without_depth_intrinsics(make_scannet):
    root = make_scannet()
    (root / "intrinsic" / "intrinsic_depth.txt").unlink()
    cam = ScanNetDataset(root).camera
    expected = Camera(20.0, 20.0, 7.5, 5.5, 16, 12, 1000.0).resized(8, 6)
    assert cam == expected


def test_scannet_without_poses_has_no_gt(make_scannet):
    root = make_scannet()
    shutil.rmtree(root / "pose")
    ds = ScanNetDataset(root)
    assert len(ds) == 3 and ds.gt_poses is None


def test_image_folder_natural_order(make_folder, toy):
    root = make_folder()
    cam = Camera(10.0, 10.0, 3.5, 2.5, 8, 6, depth_scale=1000.0)
    ds = ImageFolderDataset(root, camera=cam, fps=10.0)
    assert [p.stem for p in ds.rgb_files] == ["img1", "img2", "img10"]
    assert ds.gt_poses is None and ds[2].T_wc is None
    np.testing.assert_allclose(ds.timestamps, [0.0, 0.1, 0.2])
    np.testing.assert_allclose(ds[2].depth, toy.depth_m(2), atol=1e-3)
    assert detect_kind(root) == "folder"


def test_image_folder_camera_yaml_fallback(make_folder):
    ds = ImageFolderDataset(make_folder(camera_yaml=True))
    assert ds.camera.depth_scale == 1000.0 and ds.camera.fy == 11.0


# --- registry -------------------------------------------------------------------------------------------

def test_open_dataset_by_kind_and_options(make_tum, make_replica, make_scannet, make_folder):
    roots = {"tum": make_tum(), "replica": make_replica(), "scannet": make_scannet(),
             "folder": make_folder(camera_yaml=True)}
    assert set(roots) == set(DATASET_KINDS)
    for kind, root in roots.items():
        assert detect_kind(root) == kind
        ds = open_dataset(kind, root, start=1, stride=1)
        assert len(ds) == 2 and ds[0].rgb.shape == (6, 8, 3)
        assert type(open_dataset("auto", root)) is type(ds)
    ds = open_dataset("TUM", roots["tum"], max_time_diff=0.01, resize=(4, 3))
    assert ds.camera.width == 4 and ds[0].depth.shape == (3, 4)
    with pytest.raises(ConfigError, match="max_time_diff"):
        open_dataset("tum", roots["tum"], max_time_dif=0.01)
