"""ggfslam.render: differentiable Gaussian rasterization (CPU numba kernels, plain-torch reference, gsplat).

Public API::

    from ggfslam.render import rasterize, RenderSettings, RenderOutput, select_backend
    out = rasterize(means, quats, scales, opacities, colors, camera, T_cw, pose_xi=xi, extras=p2d[:, None])

See ``api.rasterize`` for arguments and ``types`` for conventions (quaternions wxyz, linear scales,
activated opacities, world-to-camera ``T_cw``, right perturbation ``T_wc = T_wc0 Exp(xi)``).
"""
from ggfslam.render.api import rasterize, select_backend
from ggfslam.render.normals import normals_from_depth
from ggfslam.render.pose import perturbed_T_cw, se3_exp
from ggfslam.render.types import Intrinsics, RenderOutput, RenderSettings

__all__ = [
    "Intrinsics",
    "RenderOutput",
    "RenderSettings",
    "normals_from_depth",
    "perturbed_T_cw",
    "rasterize",
    "se3_exp",
    "select_backend",
]
