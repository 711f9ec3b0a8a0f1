"""Geometric-Gaussian Field (paper §4.2, METHOD.md §3, §4, §6): planar probability per anchor, AMR, AOF."""
from ggfslam.ggf.geometric_field import GeometricGaussianField, planarity_colors

__all__ = ["GeometricGaussianField", "planarity_colors"]
