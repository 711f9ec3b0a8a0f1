"""ggfslam.gaussians."""
