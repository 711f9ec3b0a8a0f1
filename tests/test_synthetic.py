"""The synthetic sequence generator: geometry consistency, texture quality for ORB, trajectories, noise, files."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from ggfslam.data.imageio import read_depth, read_rgb
from ggfslam.data.replica import read_cam_params, read_matrix_trajectory
from ggfslam.data.synthetic import (
    TRAJECTORY_KINDS,
    SyntheticSequence,
    _scene_caster,
    kinect_depth_noise,
    make_scene,
    render_frame,
    render_mesh_sequence,
    render_replica_sequence,
    synthetic_camera,
    trajectory,
    write_synthetic_sequence,
)
from ggfslam.data.trajectory_io import read_tum_trajectory
from ggfslam.errors import DatasetError, RunDirError
from ggfslam.geometry.depth import backproject, normals_from_depth, project, transform_points
from ggfslam.geometry.se3 import invert


@pytest.fixture(scope="module")
def scene():
    return make_scene(seed=0)


@pytest.fixture(scope="module")
def small_seq(scene):
    """20 noise-free orbit frames at 320x240, rendered once."""
    seq = SyntheticSequence(n_frames=20, width=320, height=240, trajectory="orbit", seed=0, scene=scene)
    return seq, list(seq)


def _rel_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(Ra.T @ Rb).magnitude()))


# --- scene -------------------------------------------------------------------------------------------
def test_scene_labels_and_colours(scene):
    n_tri = len(scene.mesh.triangles)
    assert scene.triangle_labels.shape == (n_tri,)
    assert set(np.unique(scene.triangle_labels)) == set(range(len(scene.object_names)))
    assert scene.planar_object.shape == (len(scene.object_names),)
    planar = dict(zip(scene.object_names, scene.planar_object))
    assert planar["floor"] and planar["table"] and planar["cabinet"]
    assert not planar["sphere_floor"] and not planar["pillar"] and not planar["sphere_on_table"]
    assert scene.triangle_planar.any() and (~scene.triangle_planar).any()
    assert scene.mesh.has_vertex_colors() and scene.mesh.has_vertex_normals()
    # shade is a pure function of its inputs
    pts = np.random.default_rng(0).uniform([-3, -2.5, 0], [3, 2.5, 3], size=(100, 3))
    tri = np.arange(100) * (n_tri // 100)
    nrm = np.tile([0.0, 0.0, 1.0], (100, 1))
    a = scene.shade(pts, tri, nrm)
    assert a.shape == (100, 3) and a.dtype == np.float32 and a.min() >= 0 and a.max() <= 1
    np.testing.assert_array_equal(a, scene.shade(pts, tri, nrm))


def test_textureless_wall_is_flat():
    sc = make_scene(seed=0, textureless_wall=True)
    cam = synthetic_camera(160, 120)
    img = render_frame(sc, cam, trajectory("line", 10, seed=0)[5])
    wall = img["object_ids"] == sc.object_names.index("wall_yneg")
    assert wall.mean() > 0.5
    assert np.ptp(img["rgb"][wall], axis=0).max() < 1e-5


# --- rendering consistency ---------------------------------------------------------------------------
def _warp_errors(fi, fj, cam) -> tuple[np.ndarray, float]:
    """|z| differences of frame i's points seen in frame j (z-buffer consistent ones) and their fraction."""
    P = backproject(fi.depth, cam.fx, cam.fy, cam.cx, cam.cy)[fi.depth > 0]  # [M, 3]
    Pj = transform_points(invert(fj.T_wc) @ fi.T_wc, P)
    uv, z = project(Pj, cam.fx, cam.fy, cam.cx, cam.cy)
    inside = ((z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1.001)
              & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height - 1.001))
    uv, z = uv[inside], z[inside]
    u0, v0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    a, b = uv[:, 0] - u0, uv[:, 1] - v0
    corners = np.stack([fj.depth[v0, u0], fj.depth[v0, u0 + 1], fj.depth[v0 + 1, u0], fj.depth[v0 + 1, u0 + 1]], 1)
    smooth = (corners.min(1) > 0) & (corners.max(1) - corners.min(1) < 0.02 * corners.max(1))
    inv = 1.0 / np.maximum(corners, 1e-9)  # inverse depth is linear in the image on a plane
    inv_j = (1 - a) * (1 - b) * inv[:, 0] + a * (1 - b) * inv[:, 1] + (1 - a) * b * inv[:, 2] + a * b * inv[:, 3]
    diff = np.abs(1.0 / inv_j - z)
    visible = smooth & (diff < 0.05)  # the rest is occluded in frame j
    return diff[visible], float(visible.mean())


@pytest.mark.parametrize("i,j", [(0, 1), (0, 10), (5, 19)])
def test_depth_warping_is_consistent(small_seq, i, j):
    seq, frames = small_seq
    diff, frac = _warp_errors(frames[i], frames[j], seq.camera)
    assert frac > 0.8
    assert np.median(diff) < 1e-3


def test_rendered_normals_match_depth_normals(small_seq):
    seq, frames = small_seq
    cam = seq.camera
    f = frames[3]
    nd = normals_from_depth(f.depth, cam.fx, cam.fy, cam.cx, cam.cy)
    nr = f.meta["normals"]
    obj = f.meta["object_ids"]
    # planar objects, away from object borders
    same = np.ones_like(obj, dtype=bool)
    for dy in (-2, 0, 2):
        for dx in (-2, 0, 2):
            same &= np.roll(obj, (dy, dx), axis=(0, 1)) == obj
    planar = seq.scene.planar_object[np.maximum(obj, 0)] & (obj >= 0) & same & (np.linalg.norm(nd, axis=-1) > 0)
    planar[:2], planar[-2:], planar[:, :2], planar[:, -2:] = False, False, False, False
    assert planar.mean() > 0.5
    cos = np.clip(np.sum(nd[planar] * nr[planar], axis=-1), -1, 1)
    ang = np.degrees(np.arccos(cos))
    assert np.median(ang) < 1.0
    assert np.percentile(ang, 90) < 5.0
    # rendered normals are unit and face the camera
    P = backproject(f.depth, cam.fx, cam.fy, cam.cx, cam.cy)
    valid = f.depth > 0
    np.testing.assert_allclose(np.linalg.norm(nr[valid], axis=-1), 1.0, atol=1e-4)
    assert np.all(np.sum(nr[valid] * P[valid], axis=-1) <= 1e-6)


def test_determinism_and_seed(scene):
    cam = synthetic_camera(160, 120)
    T = trajectory("orbit", 5, seed=0)[2]
    a = render_frame(scene, cam, T)
    b = render_frame(make_scene(seed=0), cam, T)
    for k in ("rgb", "depth", "normals", "tri_ids", "object_ids"):
        np.testing.assert_array_equal(a[k], b[k])
    c = render_frame(make_scene(seed=1), cam, T)
    np.testing.assert_array_equal(a["depth"], c["depth"])  # the seed changes texture, not geometry
    assert np.mean(np.abs(a["rgb"] - c["rgb"])) > 0.05
    np.testing.assert_array_equal(trajectory("loop", 30, seed=3), trajectory("loop", 30, seed=3))
    assert not np.allclose(trajectory("loop", 30, seed=3), trajectory("loop", 30, seed=4))


def test_orb_features_are_plentiful_spread_and_matchable(scene):
    cam = synthetic_camera(640, 480)
    poses = trajectory("orbit", 40, seed=0)
    orb = cv2.ORB_create(1000)
    grey = [cv2.cvtColor(np.round(render_frame(scene, cam, poses[k])["rgb"] * 255).astype(np.uint8),
                         cv2.COLOR_RGB2GRAY) for k in (20, 21)]
    (k1, d1), (k2, d2) = (orb.detectAndCompute(g, None) for g in grey)
    assert len(k1) > 300 and len(k2) > 300
    pts = np.array([kp.pt for kp in k1])  # [K, 2]
    cells = {(int(x // 160), int(y // 120)) for x, y in pts}
    assert len(cells) / 16 > 0.6
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(d1, d2, k=2)
    good = [m for m, n in (p for p in pairs if len(p) == 2) if m.distance < 0.75 * n.distance]
    assert len(good) > 100


# --- trajectories ------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", TRAJECTORY_KINDS)
def test_trajectory_is_smooth_inside_and_clear(scene, kind):
    n = 120
    P = trajectory(kind, n, seed=1)
    assert P.shape == (n, 4, 4)
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", P[:, :3, :3], P[:, :3, :3]), np.tile(np.eye(3), (n, 1, 1)),
                               atol=1e-9)
    steps = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
    assert steps.max() < 0.015 and steps.min() > 0.005
    rot = [_rel_angle_deg(P[k, :3, :3], P[k + 1, :3, :3]) for k in range(n - 1)]
    assert max(rot) < 1.0
    eye = P[:, :3, 3]
    assert np.all(eye > scene.room_min + 0.5) and np.all(eye < scene.room_max - 0.5)
    clearance = _scene_caster(scene).scene.compute_distance(o3d.core.Tensor(eye.astype(np.float32))).numpy()
    assert clearance.min() > 0.4
    cam = synthetic_camera(80, 60)
    for T in P[::10]:
        d = render_frame(scene, cam, T)["depth"]
        assert d.min() > 0.3  # every pixel hits the closed room, nothing is too close


def test_loop_returns_to_its_start():
    for n in (20, 300):
        P = trajectory("loop", n, seed=0)
        assert np.linalg.norm(P[-1, :3, 3] - P[0, :3, 3]) < 0.1
        assert _rel_angle_deg(P[-1, :3, :3], P[0, :3, :3]) < 5.0
    far = np.linalg.norm(P[:, :3, 3] - P[0, :3, 3], axis=1)
    assert far.max() > 1.0  # a real excursion before coming back
    view = [_rel_angle_deg(P[0, :3, :3], T[:3, :3]) for T in P]
    assert max(view) > 45.0  # the middle of the loop looks elsewhere


def test_trajectory_rejects_unknown_kind():
    with pytest.raises(ValueError, match="unknown trajectory"):
        trajectory("spiral", 10)


# --- noise -------------------------------------------------------------------------------------------
def test_depth_noise_model(scene):
    cam = synthetic_camera(320, 240)
    img = render_frame(scene, cam, trajectory("orbit", 5, seed=0)[0])
    gt = img["depth"]
    noisy = kinect_depth_noise(gt, np.random.default_rng(5), img["normals"], cam)
    np.testing.assert_array_equal(noisy, kinect_depth_noise(gt, np.random.default_rng(5), img["normals"], cam))
    assert not np.array_equal(noisy, kinect_depth_noise(gt, np.random.default_rng(6), img["normals"], cam))
    both = (gt > 0) & (noisy > 0)
    std = []
    for lo, hi in ((0.8, 1.6), (2.0, 2.8), (3.4, 4.4)):
        m = both & (gt >= lo) & (gt < hi)
        assert m.sum() > 200
        std.append(np.std(noisy[m] - gt[m]))
    assert std[0] < std[1] < std[2]
    assert std[0] < 0.01 and std[2] > 0.01
    assert noisy.max() <= 4.5 and (gt > 4.5).any()  # nothing beyond the range
    holes = (gt > 0) & (gt < 4.5) & (noisy == 0)
    assert 0.001 < holes.mean() < 0.2
    # holes concentrate at depth discontinuities
    edge = np.zeros_like(gt, dtype=bool)
    edge[:, 1:] |= np.abs(np.diff(gt, axis=1)) > 0.1
    edge[1:, :] |= np.abs(np.diff(gt, axis=0)) > 0.1
    assert holes[edge].mean() > 5 * holes[~edge].mean()


def test_noisy_sequence_keeps_clean_depth_and_is_reproducible(scene):
    a = SyntheticSequence(n_frames=3, width=96, height=72, seed=2, depth_noise=True, scene=scene)[1]
    b = SyntheticSequence(n_frames=3, width=96, height=72, seed=2, depth_noise=True, scene=scene)[1]
    np.testing.assert_array_equal(a.depth, b.depth)
    assert "depth_gt" in a.meta and not np.array_equal(a.depth, a.meta["depth_gt"])


# --- files -------------------------------------------------------------------------------------------
def _tree_bytes(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_write_synthetic_sequence(tmp_path):
    n, w, h = 6, 96, 72
    out = write_synthetic_sequence(tmp_path / "a", n_frames=n, width=w, height=h, trajectory="loop", seed=4,
                                   depth_noise=True)
    again = write_synthetic_sequence(tmp_path / "b", n_frames=n, width=w, height=h, trajectory="loop", seed=4,
                                     depth_noise=True)
    files = _tree_bytes(out)
    assert files == _tree_bytes(again)  # same bytes for the same seed
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "camera.yaml", "mesh.ply", "scene.json",
                 "mesh_labels.npy"):
        assert name in files
    rgb_lines = [ln.split() for ln in (out / "rgb.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(rgb_lines) == n
    img = cv2.imread(str(out / rgb_lines[2][1]), cv2.IMREAD_UNCHANGED)
    assert img.shape == (h, w, 3) and img.dtype == np.uint8
    depth_lines = [ln.split() for ln in (out / "depth.txt").read_text().splitlines() if not ln.startswith("#")]
    raw = cv2.imread(str(out / depth_lines[2][1]), cv2.IMREAD_UNCHANGED)
    assert raw.shape == (h, w) and raw.dtype == np.uint16
    seq = SyntheticSequence(n_frames=n, width=w, height=h, trajectory="loop", seed=4, depth_noise=True)
    f2 = seq[2]
    np.testing.assert_allclose(raw / 5000.0, f2.depth, atol=1.1e-4)
    np.testing.assert_allclose(read_rgb(out / rgb_lines[2][1]), f2.rgb, atol=0.5 / 255 + 1e-6)
    stamps, poses = read_tum_trajectory(out / "groundtruth.txt")
    np.testing.assert_allclose(stamps, np.arange(n) / 30.0, atol=1e-6)
    np.testing.assert_allclose(poses, seq.poses, atol=1e-6)
    meta = json.loads((out / "scene.json").read_text())
    assert meta["seed"] == 4 and meta["trajectory"] == "loop" and meta["depth_noise"] is True
    assert [o["name"] for o in meta["objects"]] == seq.scene.object_names
    mesh = o3d.io.read_triangle_mesh(str(out / "mesh.ply"))
    assert mesh.has_vertex_colors() and len(mesh.triangles) == len(seq.scene.triangle_labels)
    np.testing.assert_array_equal(np.load(out / "mesh_labels.npy"), seq.scene.triangle_labels)
    with pytest.raises(RunDirError):
        write_synthetic_sequence(out, n_frames=2, width=w, height=h)
    # round trip through the TUM reader, when it is there
    tum = pytest.importorskip("ggfslam.data.tum")
    ds = tum.TUMDataset(out)
    assert len(ds) == n
    cam = ds.camera
    assert (cam.width, cam.height) == (w, h) and cam.fx == pytest.approx(seq.camera.fx)
    fr = ds[2]
    np.testing.assert_allclose(fr.depth, f2.depth, atol=1.1e-4)
    np.testing.assert_allclose(fr.T_wc, seq.poses[2], atol=1e-5)
    # the noise-free depth comes back too (what the metrics score against), resized like the depth
    np.testing.assert_allclose(fr.meta["depth_gt"], f2.meta["depth_gt"], atol=1.1e-4)
    assert np.abs(fr.depth - fr.meta["depth_gt"])[fr.depth > 0].max() > 5e-3  # and it is not the noisy depth
    small = tum.TUMDataset(out, resize=(w // 2, h // 2))[2]
    np.testing.assert_array_equal(small.meta["depth_gt"], cv2.resize(fr.meta["depth_gt"], (w // 2, h // 2),
                                                                      interpolation=cv2.INTER_NEAREST))
    clean = write_synthetic_sequence(tmp_path / "clean", n_frames=2, width=w, height=h)
    assert not (clean / "depth_gt").exists() and "depth_gt" not in tum.TUMDataset(clean)[1].meta


def test_render_mesh_sequence_reproduces_the_scene_depth(tmp_path, scene):
    src = write_synthetic_sequence(tmp_path / "src", n_frames=2, width=64, height=48, seed=0)
    cam = synthetic_camera(96, 72)
    poses = trajectory("line", 4, seed=0)
    out = render_mesh_sequence(src / "mesh.ply", poses, cam, tmp_path / "mesh_seq", timestamps=np.arange(4) * 0.5)
    assert (out / "mesh.ply").read_bytes() == (src / "mesh.ply").read_bytes()
    stamps, gt = read_tum_trajectory(out / "groundtruth.txt")
    np.testing.assert_allclose(stamps, np.arange(4) * 0.5)
    depth_lines = [ln.split() for ln in (out / "depth.txt").read_text().splitlines() if not ln.startswith("#")]
    ref = render_frame(scene, cam, poses[1])
    d = read_depth(out / depth_lines[1][1], 5000.0)
    np.testing.assert_allclose(d, ref["depth"], atol=2e-4)
    # vertex colours are the scene's shaded albedo sampled at the vertices: same colours, less detail
    rgb_lines = [ln.split() for ln in (out / "rgb.txt").read_text().splitlines() if not ln.startswith("#")]
    rgb = read_rgb(out / rgb_lines[1][1])
    assert np.median(np.abs(rgb - ref["rgb"])) < 0.25


def test_render_mesh_sequence_errors(tmp_path):
    cam = synthetic_camera(32, 24)
    with pytest.raises(DatasetError, match="not found"):
        render_mesh_sequence(tmp_path / "none.ply", np.eye(4)[None], cam, tmp_path / "o")
    plain = o3d.geometry.TriangleMesh.create_box()
    o3d.io.write_triangle_mesh(str(tmp_path / "plain.ply"), plain)
    with pytest.raises(DatasetError, match="vertex colours"):
        render_mesh_sequence(tmp_path / "plain.ply", np.eye(4)[None], cam, tmp_path / "o")
    with pytest.raises(ValueError, match="shape"):
        render_mesh_sequence(tmp_path / "plain.ply", np.eye(4), cam, tmp_path / "o")


# --- Replica -----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def replica_root():
    from ggfslam.data.paths import default_data_root

    root = default_data_root() / "replica_office0_mini"
    if not (root / "office0_mesh.ply").is_file():
        pytest.skip(f"Replica office0 mini not found at {root} (set GGFSLAM_DATA)")
    return root


def test_replica_poses_are_opencv_camera_to_world(replica_root):
    """Rendering office0's mesh at traj.txt pose 0 reproduces the dataset's own depth image 0."""
    from ggfslam.data.synthetic import MeshRaycaster

    cam = read_cam_params(replica_root / "cam_params.json")
    poses = read_matrix_trajectory(replica_root / "traj.txt")
    assert len(poses) == 2000
    caster = MeshRaycaster(o3d.io.read_triangle_mesh(str(replica_root / "office0_mesh.ply")))
    ref = read_depth(replica_root / "results" / "depth000000.png", 6553.5)

    def median_err(T):
        d = caster.cast(cam, T)["depth"]
        both = (d > 0) & (ref > 0)
        assert both.mean() > 0.5
        return float(np.median(np.abs(d[both] - ref[both])))

    assert median_err(poses[0]) < 0.03  # the mesh is decimated: a few mm to cm
    gl = poses[0].copy()
    gl[:3, 1:3] *= -1  # the OpenGL reading (y up, z backward) must be clearly wrong
    assert median_err(gl) > 0.2


def test_render_replica_sequence(tmp_path, replica_root):
    out = render_replica_sequence(replica_root, tmp_path / "rep", n_frames=3, width=120, height=68, stride=2)
    stamps, poses = read_tum_trajectory(out / "groundtruth.txt")
    np.testing.assert_allclose(poses, read_matrix_trajectory(replica_root / "traj.txt")[[0, 2, 4]], atol=1e-6)
    np.testing.assert_allclose(stamps, np.array([0, 2, 4]) / 30.0, atol=1e-6)
    depth_lines = [ln.split() for ln in (out / "depth.txt").read_text().splitlines() if not ln.startswith("#")]
    d = read_depth(out / depth_lines[0][1], 5000.0)
    assert d.shape == (68, 120) and (d > 0).mean() > 0.9
    # the real depth, subsampled (pixel centres of the 10x smaller image fall between real pixels: use area)
    ref = read_depth(replica_root / "results" / "depth000000.png", 6553.5)
    ref_small = cv2.resize(ref, (120, 68), interpolation=cv2.INTER_AREA)
    both = (d > 0) & (ref_small > 0)
    assert np.median(np.abs(d[both] - ref_small[both])) < 0.05
    assert (out / "mesh.ply").is_file()
