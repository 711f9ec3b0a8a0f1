"""ggfslam: RGB-D Gaussian-Splatting SLAM with a Geometric-Gaussian Field (GGF-SLAM), CPU-first."""
__version__ = "0.1.0"

from ggfslam.numba_setup import configure as _configure_numba

_configure_numba()
