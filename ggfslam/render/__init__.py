"""ggfslam.render."""
