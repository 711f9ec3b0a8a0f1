"""What a trained map leaves in the run directory: the baked Gaussians PLY and the TSDF mesh."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ggfslam.gaussians.ply import write_gaussians_ply
from ggfslam.mapping.tsdf import TSDFFusion, write_mesh


def write_map_ply(mapper, path: str | Path) -> int:
    """Bake every decoded child (view-independent) into a standard 3DGS PLY; returns the Gaussian count."""
    g = mapper.export_gaussians()
    write_gaussians_ply(path, g.means, g.quats, g.scales, g.opacities, g.colors)
    return len(g)


def write_planarity_ply(mapper, path: str | Path) -> int:
    """The same Gaussians as ``write_map_ply``, coloured by their anchor's P_2D (red = 2D, blue = 3D)."""
    g = mapper.export_planarity()
    write_gaussians_ply(path, g.means, g.quats, g.scales, g.opacities, g.colors)
    return len(g)


def fuse_rendered_mesh(mapper, poses: list[np.ndarray], intr, voxel: float, depth_max: float = 8.0):
    """TSDF-fuse the map's rendered depth and colour at poses (camera-to-world) into a triangle mesh."""
    tsdf = TSDFFusion(intr, voxel_size=voxel, depth_max=depth_max)
    for T in poses:
        out = mapper.render(T, intr)
        depth = np.where(out.alpha.numpy() > 0.5, out.depth.numpy(), 0.0).astype(np.float32)
        tsdf.integrate(depth, out.color.numpy(), T)
    return tsdf.extract_mesh()


def write_rendered_mesh(mapper, poses: list[np.ndarray], intr, voxel: float, path: str | Path) -> int:
    """``fuse_rendered_mesh`` written to ``path`` (binary PLY); returns the triangle count."""
    mesh = fuse_rendered_mesh(mapper, poses, intr, voxel)
    write_mesh(path, mesh)
    return len(mesh.triangles)
