"""ggfslam.data."""
