"""What a trained map leaves in the run directory: the baked Gaussians PLY and the TSDF mesh fused from it."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from ggfslam.gaussians.decoders import DecodedGaussians
from ggfslam.gaussians.explicit import ExplicitGaussians
from ggfslam.gaussians.ply import write_gaussians_ply
from ggfslam.mapping.tsdf import TSDFFusion, write_mesh
from ggfslam.render.types import Intrinsics, RenderOutput


def write_map_ply(mapper, path: str | Path, baked: DecodedGaussians | None = None) -> int:
    """The map baked (``baked``, or ``Mapper.bake_gaussians()`` now) into a standard 3DGS PLY; returns the Gaussian
    count."""
    g = mapper.bake_gaussians() if baked is None else baked
    write_gaussians_ply(path, g.means, g.quats, g.scales, g.opacities, g.colors, g.sh_rest)
    return len(g)


def write_planarity_ply(mapper, path: str | Path, baked: DecodedGaussians | None = None) -> int:
    """The same Gaussians as ``write_map_ply`` (``baked``, or a new bake), coloured by their anchor's P_2D
    (red = 2D, blue = 3D)."""
    g = mapper.export_planarity(baked)
    write_gaussians_ply(path, g.means, g.quats, g.scales, g.opacities, g.colors)
    return len(g)


def fuse_rendered_mesh(render: Callable[[np.ndarray], RenderOutput], poses: list[np.ndarray], intr: Intrinsics,
                       voxel: float, depth_max: float = 8.0):
    """TSDF-fuse rendered depth and colour (``render(T_wc)`` at ``intr``) at poses (camera-to-world) into a mesh."""
    tsdf = TSDFFusion(intr, voxel_size=voxel, depth_max=depth_max)
    for T in poses:
        out = render(T)
        depth = np.where(out.alpha.numpy() > 0.5, out.depth.numpy(), 0.0).astype(np.float32)
        tsdf.integrate(depth, out.color.clamp(0, 1).numpy(), T)
    return tsdf.extract_mesh()


def write_rendered_mesh(baked: ExplicitGaussians, poses: list[np.ndarray], intr: Intrinsics, voxel: float,
                        path: str | Path) -> int:
    """The baked Gaussians (the PLY's) rendered at poses and TSDF-fused into a binary PLY mesh at ``path``; returns
    the triangle count."""
    mesh = fuse_rendered_mesh(lambda T: baked.render(T, intr), poses, intr, voxel)
    write_mesh(path, mesh)
    return len(mesh.triangles)
