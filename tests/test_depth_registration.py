"""Depth registration (depth from a second camera warped into the colour camera): values against the analytic
depth of known surfaces, occlusion, and the dataset path that applies it (dataset.depth_registration)."""
from __future__ import annotations

import numpy as np
import pytest

from ggfslam.config import config_from_dict
from ggfslam.data.depth_calibration import colour_edge_distance, near_discontinuities
from ggfslam.data.sources import open_dataset_from_config
from ggfslam.data.types import Camera, Frame
from ggfslam.data.writer import write_tum_sequence
from ggfslam.errors import ConfigError
from ggfslam.geometry.depth import register_depth
from ggfslam.geometry.se3 import pose_from_tum

KD = (585.0, 585.0, 320.0, 240.0)  # the depth camera (7-Scenes' nominal Kinect v1 intrinsics)
KC = (528.0, 528.0, 320.8, 238.4)  # the colour camera beside it
W, H = 640, 480


def _rays(k, w, h):
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    return np.stack([(u - k[2]) / k[0], (v - k[3]) / k[1], np.ones_like(u)], axis=-1)  # [h, w, 3]


def _plane_depth(k, n, d, w=W, h=H):
    """Depth [h, w] of the plane n . X = d seen by a pinhole camera k at the origin."""
    return d / (_rays(k, w, h) @ n)


def _T(t, q=(0.0, 0.0, 0.0, 1.0)):
    return pose_from_tum(np.array([*t, *q], np.float64))


def test_identity_registration_returns_the_depth_unchanged():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 4.0, (H, W)).astype(np.float32)
    depth[rng.random((H, W)) < 0.1] = 0
    np.testing.assert_array_equal(register_depth(depth, KD, KD, np.eye(4), W, H), depth)


@pytest.mark.parametrize("t, q", [((-0.025, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
                                  ((0.03, -0.01, 0.005), (0.01, -0.02, 0.005, 0.99972))])
def test_tilted_plane_matches_its_analytic_depth_in_the_colour_camera(t, q):
    q = tuple(np.array(q) / np.linalg.norm(q))
    n_d = np.array([0.3, -0.2, 1.0])
    n_d /= np.linalg.norm(n_d)
    d_d = 2.0
    depth = _plane_depth(KD, n_d, d_d).astype(np.float32)
    T = _T(t, q)  # depth camera -> colour camera
    out = register_depth(depth, KD, KC, T, W, H)
    # the same plane in the colour camera: n_c = R n_d, d_c = d_d + n_c . t
    n_c = T[:3, :3] @ n_d
    expected = _plane_depth(KC, n_c, d_d + n_c @ T[:3, 3])
    covered = out > 0
    assert covered.mean() > 0.75  # the colour camera sees wider than the depth camera: a margin stays empty
    # corners take the centre's depth, so the footprint's depth is off by the slope over half a pixel at most
    np.testing.assert_allclose(out[covered], expected[covered], atol=2e-3)
    # no holes inside the covered region (each colour pixel centre is inside some depth pixel's footprint)
    rows = np.nonzero(covered.any(axis=1))[0]
    for r in rows[5:-5:40]:
        cols = np.nonzero(covered[r])[0]
        assert covered[r, cols[0]:cols[-1] + 1].all()


def test_upsampling_registration_leaves_no_holes():
    depth = np.full((H // 2, W // 2), 1.5, np.float32)  # a coarser depth camera than the colour one
    kd = (KD[0] / 2, KD[1] / 2, (KD[2] + 0.5) / 2 - 0.5, (KD[3] + 0.5) / 2 - 0.5)
    out = register_depth(depth, kd, KC, _T((-0.02, 0.0, 0.0)), W, H)
    inner = out[40:-40, 50:-50]  # inside the depth camera's narrower view
    assert (inner == pytest.approx(1.5, abs=1e-6)) and inner.min() > 0


def test_nearest_surface_wins_and_the_baseline_opens_a_shadow():
    # a far wall at 3 m with a near box at 1 m in the middle of the depth image
    depth = np.full((H, W), 3.0, np.float32)
    depth[200:280, 280:360] = 1.0
    T = _T((-0.05, 0.0, 0.0))  # a wide baseline for a clear shadow
    out = register_depth(depth, KD, KD, T, W, H)
    # the box's centre pixel (320, 240) at 1 m moves by f * tx / z = -29.25 px; the wall by -9.75 px
    assert out[240, 320 - 29] == pytest.approx(1.0)
    assert out[240, 240] == pytest.approx(3.0) and out[240, 360] == pytest.approx(3.0)  # the wall on either side
    # pixels of the wall the depth camera could not see behind the box (box's right edge moves 19.5 px further
    # left than the wall behind it): 0, not interpolated
    row = out[240]
    right_edge = 360 - 0.5 - 29.25  # box edge in the colour image
    wall_edge = 360 - 0.5 - 9.75  # where the wall behind that edge lands
    gap = row[int(np.ceil(right_edge)) + 1:int(np.floor(wall_edge))]
    assert len(gap) >= 15 and (gap == 0).all()


def _written_sequence(tmp_path, camera, n=2):
    depth = _plane_depth(KD, np.array([0.0, 0.0, 1.0]), 2.0).astype(np.float32)
    depth[100:150, 100:150] = 1.2
    rgb = np.full((H, W, 3), 0.5, np.float32)
    frames = [Frame(i, 1.0 + i / 30, rgb, depth, np.eye(4)) for i in range(n)]
    return write_tum_sequence(tmp_path / "seq", frames, camera, depth_scale=1000.0), depth


def test_dataset_applies_the_configured_registration(tmp_path):
    root, depth = _written_sequence(tmp_path, Camera(*KC, W, H, 1000.0))
    cfg = config_from_dict({"dataset": {"kind": "tum", "path": str(root), "depth_registration": {
        "fx": KD[0], "fy": KD[1], "cx": KD[2], "cy": KD[3], "translation": [-0.025, 0.0, 0.0]}}}).dataset
    ds = open_dataset_from_config(cfg)
    assert ds.camera.fx == KC[0]  # the dataset's intrinsics are the colour camera's
    expected = register_depth(np.round(depth * 1000) / 1000, KD, KC, _T((-0.025, 0.0, 0.0)), W, H)
    np.testing.assert_allclose(ds[1].depth, expected, atol=1e-6)
    # resized frames are registered at the stored size first, then resized like any depth
    cfg.resize = (320, 240)
    small = open_dataset_from_config(cfg)[0].depth
    assert small.shape == (240, 320) and small[120, 160] == pytest.approx(2.0, abs=1e-3)


@pytest.mark.parametrize("ground_truth", ["depth", "color"])
def test_ground_truth_of_the_depth_camera_is_moved_to_the_colour_camera(tmp_path, ground_truth):
    root, _ = _written_sequence(tmp_path, Camera(*KC, W, H, 1000.0), n=3)
    T_wd = [_T((0.1 * i, -0.2, 0.05 * i), (0.0, np.sin(0.1 * i), 0.0, np.cos(0.1 * i))) for i in range(3)]
    lines = [f"{1.0 + i / 30:.6f} " + " ".join(f"{v:.9f}" for v in _tum(T)) for i, T in enumerate(T_wd)]
    (root / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n")
    reg = {"fx": KD[0], "fy": KD[1], "cx": KD[2], "cy": KD[3], "translation": [-0.025, 0.01, 0.0],
           "rotation": [0.0, 0.0, float(np.sin(0.01)), float(np.cos(0.01))], "ground_truth": ground_truth}
    cfg = config_from_dict({"dataset": {"kind": "tum", "path": str(root), "depth_registration": reg}}).dataset
    ds = open_dataset_from_config(cfg)
    T_cd = cfg.depth_registration.T_color_depth()
    p_d = np.array([0.3, -0.2, 2.0, 1.0])  # a point in the depth camera of frame 2
    for i in range(3):
        T_wc = ds.gt_poses[i]
        np.testing.assert_allclose(ds[i].T_wc, T_wc, atol=1e-12)
        if ground_truth == "color":
            np.testing.assert_allclose(T_wc, T_wd[i], atol=1e-8)
        else:  # the colour camera's pose puts the point where the depth camera's does
            np.testing.assert_allclose(T_wc @ (T_cd @ p_d), T_wd[i] @ p_d, atol=1e-8)
            assert np.linalg.norm(T_wc[:3, 3] - T_wd[i][:3, 3]) == pytest.approx(np.hypot(0.025, 0.01), abs=1e-6)


def _tum(T):
    from ggfslam.geometry.se3 import pose_to_tum

    return pose_to_tum(T)


def test_registration_config_errors_name_the_field(tmp_path):
    base = {"kind": "tum", "path": str(tmp_path)}
    with pytest.raises(ConfigError, match="unit quaternion"):
        config_from_dict({"dataset": {**base, "depth_registration": {"fx": 1, "fy": 1, "cx": 0, "cy": 0,
                                                                     "rotation": [0, 0, 0, 2]}}})
    with pytest.raises(ConfigError, match="focal lengths must be > 0"):
        config_from_dict({"dataset": {**base, "depth_registration": {"fx": 0, "fy": 1, "cx": 0, "cy": 0}}})
    with pytest.raises(ConfigError, match="depth_registration"):
        config_from_dict({"dataset": {**base, "depth_registration": {"fx": 1, "fy": 1, "cx": 0, "cy": 0,
                                                                     "baseline": 0.02}}})
    root, _ = _written_sequence(tmp_path, Camera(*KC, W, H, 1000.0, (0.1, 0.0, 0.0, 0.0)), n=1)
    cfg = config_from_dict({"dataset": {"kind": "tum", "path": str(root), "depth_registration": {
        "fx": KD[0], "fy": KD[1], "cx": KD[2], "cy": KD[3]}}}).dataset
    ds = open_dataset_from_config(cfg)  # a distorted colour camera: depth goes into its undistorted image
    assert ds.camera.distortion == () and ds[0].depth.shape == (H, W)


def _edge_chamfer(rgb: np.ndarray, depth: np.ndarray) -> float:
    """Median distance (px, capped at 10) from each depth discontinuity (near side) to the nearest colour edge."""
    return float(np.median(np.minimum(colour_edge_distance(rgb)[near_discontinuities(depth)], 10.0)))


def test_7scenes_registered_config_brings_depth_edges_onto_colour_edges(data_root, monkeypatch):
    """The shipped 7-Scenes registration on real Kinect frames: depth discontinuities land on colour edges."""
    from pathlib import Path

    from ggfslam.config import load_config

    monkeypatch.setenv("GGFSLAM_DATA", str(data_root))
    configs = Path(__file__).resolve().parents[1] / "configs" / "7scenes"
    raw = open_dataset_from_config(load_config(configs / "redkitchen_500.yaml").dataset)
    reg = open_dataset_from_config(load_config(configs / "redkitchen_500_registered.yaml").dataset)
    before = [_edge_chamfer(raw[i].rgb, raw[i].depth) for i in (0, 150, 300, 450)]
    after = [_edge_chamfer(reg[i].rgb, reg[i].depth) for i in (0, 150, 300, 450)]
    assert np.median(after) < 0.6 * np.median(before), (before, after)


def _raw_sequence(tmp_path):
    """The procedural room's depth moved into a made-up depth camera (focal 1/0.9 of the colour camera's, principal
    point off by (3, -2) px, 2.5 cm to its side), written as an unregistered TUM folder whose camera.yaml is the
    depth camera's: (folder, frames, colour camera, depth intrinsics)."""
    from ggfslam.geometry.se3 import invert

    syn = open_dataset_from_config(config_from_dict({"dataset": {"kind": "synthetic", "synthetic": {
        "n_frames": 60, "seed": 3}}}).dataset)
    c = syn.camera
    kc = (c.fx, c.fy, c.cx, c.cy)
    kd = (c.fx / 0.9, c.fy / 0.9, c.cx + 3.0, c.cy - 2.0)
    frames = []
    for i in range(0, 60, 6):
        f = syn[i]
        raw = register_depth(f.depth, kc, kd, invert(_T((-0.025, 0.0, 0.0))), c.width, c.height)  # depth camera's
        frames.append(Frame(len(frames), f.timestamp, f.rgb, raw, f.T_wc))
    root = write_tum_sequence(tmp_path / "raw", frames, Camera(*kd, c.width, c.height, 5000.0), 5000.0)
    return root, frames, c, kd


def test_fit_recovers_a_known_registration(tmp_path):
    """The fit finds the colour camera and puts depth edges back onto colour edges as well as the true
    registration does."""
    from ggfslam.data.depth_calibration import (
        edge_distance,
        edge_frame,
        fit_depth_registration,
    )
    from ggfslam.data.registry import open_dataset

    root, frames, c, kd = _raw_sequence(tmp_path)
    fit = fit_depth_registration(open_dataset("tum", root), n_frames=10)
    truth = edge_distance([edge_frame(f.rgb, f.depth, kd) for f in frames], c.fx, c.fy, c.cx, c.cy,
                          (-0.025, 0.0, 0.0))
    assert fit.fx == pytest.approx(c.fx, rel=0.01)
    assert fit.cx == pytest.approx(c.cx, abs=1.5) and fit.cy == pytest.approx(c.cy, abs=1.5)
    assert fit.translation[0] == pytest.approx(-0.025, abs=0.003) and abs(fit.translation[1]) < 0.003
    assert fit.distance_after_px <= truth + 0.1 < fit.distance_before_px - 1.0, (fit, truth)


def test_calibrate_depth_prints_a_config_that_registers_the_sequence(tmp_path):
    import yaml
    from typer.testing import CliRunner

    from ggfslam.cli import app

    root, frames, c, kd = _raw_sequence(tmp_path)
    cfg_path = tmp_path / "raw.yaml"
    cfg_path.write_text(f"dataset: {{kind: tum, path: {root}}}\n")
    res = CliRunner().invoke(app, ["calibrate-depth", str(cfg_path), "--frames", "10"])
    assert res.exit_code == 0, res.output
    pasted = yaml.safe_load(res.output)["dataset"]  # the comment line is YAML too
    assert pasted["camera"]["fx"] == pytest.approx(c.fx, rel=0.01) and pasted["camera"]["depth_scale"] == 5000.0
    ds = open_dataset_from_config(config_from_dict({"dataset": {"kind": "tum", "path": str(root), **pasted}}).dataset)
    assert ds.camera.fx == pasted["camera"]["fx"]
    # the registered depth agrees with the colour camera's own depth where both exist (edges aside)
    reg, true = ds[3].depth, _synthetic_depth(3)
    both = (reg > 0) & (true > 0)
    assert both.mean() > 0.7 and np.median(np.abs(reg[both] - true[both])) < 0.01
    # a registered config is refused: the fit needs the raw depth
    cfg_path.write_text(yaml.safe_dump({"dataset": {"kind": "tum", "path": str(root), **pasted}}))
    res = CliRunner().invoke(app, ["calibrate-depth", str(cfg_path)])
    assert res.exit_code == 2 and "already set" in res.output
    # so is a camera with lens distortion: the fit moves pinhole cameras
    cfg_path.write_text(yaml.safe_dump({"dataset": {"kind": "tum", "path": str(root), "camera": {
        **pasted["camera"], "distortion": [0.1, 0.0, 0.0, 0.0]}}}))
    res = CliRunner().invoke(app, ["calibrate-depth", str(cfg_path)])
    assert res.exit_code == 2 and "lens distortion" in res.output


def _synthetic_depth(k: int) -> np.ndarray:
    syn = open_dataset_from_config(config_from_dict({"dataset": {"kind": "synthetic", "synthetic": {
        "n_frames": 60, "seed": 3}}}).dataset)
    return syn[6 * k].depth
