"""ggfslam.eval."""
