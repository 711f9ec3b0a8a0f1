"""Mesh extraction by TSDF fusion of RGB-D frames into Open3D's tensor VoxelBlockGrid.

We use ``open3d.t.geometry.VoxelBlockGrid`` rather than the legacy ``ScalableTSDFVolume``, which produced empty
meshes in this project. Two Open3D details matter: the grid wants the world-to-camera extrinsic (the inverse of our
``T_wc``), and ``extract_triangle_mesh`` keeps only voxels whose weight is strictly greater than its threshold
(default 3.0, i.e. seen in at least 4 frames), so we pass the threshold explicitly.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import open3d.core as o3c

from ggfslam.atomic import atomic_path
from ggfslam.errors import GGFSlamError, RunDirError


class EmptyMeshError(GGFSlamError):
    """TSDF fusion produced no surface (no valid depth, or poses/intrinsics that do not match the images)."""


class TSDFFusion:
    """Fuses depth + colour frames with camera-to-world poses into a TSDF and extracts a coloured triangle mesh."""

    def __init__(self, camera, voxel_size: float = 0.01, trunc_voxels: float = 4.0, depth_max: float = 5.0,
                 block_count: int = 50000):
        """Empty grid for ``camera`` (fx, fy, cx, cy, width, height); truncation = trunc_voxels * voxel_size."""
        if not voxel_size > 0 or not trunc_voxels > 0 or not depth_max > 0:
            raise ValueError(
                f"voxel_size, trunc_voxels and depth_max must be > 0 (got {voxel_size}, {trunc_voxels}, {depth_max})")
        self.camera = camera
        self.voxel_size = float(voxel_size)
        self.trunc_voxels = float(trunc_voxels)
        self.depth_max = float(depth_max)
        self.width, self.height = int(camera.width), int(camera.height)
        self._device = o3c.Device("CPU:0")
        K = np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])  # [3, 3]
        self._intrinsic = o3c.Tensor(K, o3c.float64, self._device)
        self._vbg = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"),
            attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
            attr_channels=((1), (1), (3)),
            voxel_size=self.voxel_size,
            block_resolution=8,
            block_count=int(block_count),
            device=self._device,
        )
        self._n_integrated = 0

    @property
    def n_integrated(self) -> int:
        """Number of frames that contributed to the grid (frames without valid depth are skipped)."""
        return self._n_integrated

    def integrate(self, depth: np.ndarray, color: np.ndarray, T_wc: np.ndarray) -> None:
        """Fuse one frame: depth [H,W] metres (0 = invalid), color [H,W,3] in [0,1], camera-to-world T_wc [4,4]."""
        depth = np.asarray(depth, dtype=np.float32)  # [H, W]
        color = np.asarray(color, dtype=np.float32)  # [H, W, 3]
        T_wc = np.asarray(T_wc, dtype=np.float64)  # [4, 4]
        if depth.shape != (self.height, self.width):
            raise ValueError(f"depth: expected shape [{self.height}, {self.width}], got {list(depth.shape)}")
        if color.shape != (self.height, self.width, 3):
            raise ValueError(f"color: expected shape [{self.height}, {self.width}, 3], got {list(color.shape)}")
        if T_wc.shape != (4, 4) or not np.all(np.isfinite(T_wc)):
            raise ValueError(f"T_wc: expected a finite [4, 4] pose, got shape {list(T_wc.shape)}")
        # NaN/inf depth would poison whole voxel blocks; treat it like the sensor's 0 = no measurement
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
        if not np.any((depth > 0) & (depth <= self.depth_max)):
            return
        color = np.ascontiguousarray(np.clip(np.nan_to_num(color), 0.0, 1.0))

        extrinsic = o3c.Tensor(np.linalg.inv(T_wc), o3c.float64, self._device)  # [4, 4] world-to-camera
        depth_img = o3d.t.geometry.Image(o3c.Tensor(depth, device=self._device))
        color_img = o3d.t.geometry.Image(o3c.Tensor(color, device=self._device))
        blocks = self._vbg.compute_unique_block_coordinates(
            depth_img, self._intrinsic, extrinsic, 1.0, self.depth_max, self.trunc_voxels)
        if blocks.shape[0] == 0:
            return
        self._vbg.integrate(blocks, depth_img, color_img, self._intrinsic, self._intrinsic, extrinsic,
                            1.0, self.depth_max, self.trunc_voxels)
        self._n_integrated += 1

    def extract_mesh(self, min_observations: int = 1) -> o3d.geometry.TriangleMesh:
        """Legacy triangle mesh with vertex colours of the zero crossing seen in >= min_observations frames."""
        if self._n_integrated == 0:
            # Open3D raises a cryptic hash-map error on a grid without blocks
            return o3d.geometry.TriangleMesh()
        # each frame adds weight 1 and Open3D keeps weight > threshold, hence the half
        mesh = self._vbg.extract_triangle_mesh(weight_threshold=float(min_observations) - 0.5)
        return mesh.to_legacy()


def write_mesh(path, mesh: o3d.geometry.TriangleMesh) -> None:
    """Write ``mesh`` as a binary PLY with vertex colours, atomically; EmptyMeshError if it has no triangles."""
    path = Path(path)
    if len(mesh.triangles) == 0:
        raise EmptyMeshError(
            f"{path}: TSDF fusion produced no surface (0 triangles); check the depth images (metres, 0 = invalid, "
            "within depth_max), the camera intrinsics and that poses are camera-to-world")
    with atomic_path(path) as tmp:
        ok = o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False, compressed=False,
                                        write_vertex_normals=mesh.has_vertex_normals(),
                                        write_vertex_colors=True, write_triangle_uvs=False)
        if not ok or not tmp.is_file():
            raise RunDirError(f"{path}: Open3D could not write the mesh (does the folder exist and is it writable?)")
