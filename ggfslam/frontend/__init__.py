"""ggfslam.frontend."""
