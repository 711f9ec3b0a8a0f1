"""TSDF mesh extraction: analytic plane views fuse into a coloured mesh at the right place; empty fusion errors."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from ggfslam.errors import GGFSlamError
from ggfslam.mapping.tsdf import TSDFFusion, write_mesh

CAMERA = SimpleNamespace(fx=120.0, fy=120.0, cx=79.5, cy=59.5, width=160, height=120)
PLANE_Z = 1.5  # world plane z = 1.5 m
COLOR = (0.8, 0.4, 0.2)
VOXEL = 0.01


def plane_depth(T_wc: np.ndarray) -> np.ndarray:
    """Depth [H, W] (metres) of the world plane z = PLANE_Z seen from camera-to-world pose T_wc."""
    u, v = np.meshgrid(np.arange(CAMERA.width), np.arange(CAMERA.height))
    rays = np.stack([(u - CAMERA.cx) / CAMERA.fx, (v - CAMERA.cy) / CAMERA.fy, np.ones(u.shape)], -1)  # [H, W, 3]
    dz = rays @ T_wc[:3, :3].T[:, 2]  # [H, W] world z component of each ray (camera z = 1)
    return ((PLANE_Z - T_wc[2, 3]) / dz).astype(np.float32)


def pose(tx: float = 0.0, tz: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("y", yaw_deg, degrees=True).as_matrix()
    T[:3, 3] = [tx, 0.0, tz]
    return T


@pytest.fixture(scope="module")
def mesh() -> o3d.geometry.TriangleMesh:
    # the yawed, pushed-back third view fails unless T_wc is inverted into Open3D's world-to-camera extrinsic
    poses = [pose(), pose(tx=0.1), pose(tx=-0.05, tz=-0.3, yaw_deg=8.0)]
    fusion = TSDFFusion(CAMERA, voxel_size=VOXEL)
    color = np.empty((CAMERA.height, CAMERA.width, 3), np.float32)
    color[:] = COLOR
    for T in poses:
        fusion.integrate(plane_depth(T), color, T)
    assert fusion.n_integrated == 3
    return fusion.extract_mesh()


def test_plane_mesh(mesh):
    assert len(mesh.triangles) > 1000
    v = np.asarray(mesh.vertices)  # [V, 3]
    assert np.abs(v[:, 2] - PLANE_Z).max() < VOXEL
    # the fused area spans the union of the views: at least the first view's footprint in x
    half_width = PLANE_Z * (CAMERA.width / 2) / CAMERA.fx
    assert v[:, 0].min() < -0.9 * half_width and v[:, 0].max() > 0.9 * half_width + 0.1
    np.testing.assert_allclose(np.asarray(mesh.vertex_colors), np.tile(COLOR, (len(v), 1)), atol=1e-3)


def test_min_observations_keeps_only_overlap(mesh):
    fusion = TSDFFusion(CAMERA, voxel_size=VOXEL)
    color = np.full((CAMERA.height, CAMERA.width, 3), 0.5, np.float32)
    for T in (pose(), pose(tx=0.3)):
        fusion.integrate(plane_depth(T), color, T)
    all_x = np.asarray(fusion.extract_mesh().vertices)[:, 0]
    both_x = np.asarray(fusion.extract_mesh(min_observations=2).vertices)[:, 0]
    assert len(both_x) > 0
    assert all_x.max() - all_x.min() > both_x.max() - both_x.min() + 0.25
    assert len(fusion.extract_mesh(min_observations=3).triangles) == 0


def test_write_mesh_round_trip(tmp_path, mesh):
    path = tmp_path / "mesh.ply"
    write_mesh(path, mesh)
    assert path.read_bytes()[:40].startswith(b"ply\nformat binary_little_endian")
    back = o3d.io.read_triangle_mesh(str(path))
    assert len(back.vertices) == len(mesh.vertices)
    assert len(back.triangles) == len(mesh.triangles)
    assert back.has_vertex_colors()
    assert [p.name for p in tmp_path.iterdir()] == ["mesh.ply"]


def test_empty_fusion_is_a_clear_error(tmp_path):
    fusion = TSDFFusion(CAMERA)
    # no valid depth at all, and a plane beyond depth_max, both contribute nothing
    fusion.integrate(np.zeros((CAMERA.height, CAMERA.width), np.float32),
                     np.zeros((CAMERA.height, CAMERA.width, 3), np.float32), np.eye(4))
    fusion.integrate(np.full((CAMERA.height, CAMERA.width), 9.0, np.float32),
                     np.zeros((CAMERA.height, CAMERA.width, 3), np.float32), np.eye(4))
    assert fusion.n_integrated == 0
    empty = fusion.extract_mesh()
    assert len(empty.triangles) == 0
    path = tmp_path / "mesh.ply"
    with pytest.raises(GGFSlamError, match="no surface") as info:
        write_mesh(path, empty)
    assert str(path) in str(info.value)
    assert not path.exists()


def test_shape_validation():
    fusion = TSDFFusion(CAMERA)
    with pytest.raises(ValueError, match="depth"):
        fusion.integrate(np.ones((10, 10), np.float32), np.zeros((CAMERA.height, CAMERA.width, 3)), np.eye(4))
    with pytest.raises(ValueError, match="color"):
        fusion.integrate(np.ones((CAMERA.height, CAMERA.width), np.float32), np.zeros((5, 5, 3)), np.eye(4))
