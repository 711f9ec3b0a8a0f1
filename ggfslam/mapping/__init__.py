"""ggfslam.mapping."""
