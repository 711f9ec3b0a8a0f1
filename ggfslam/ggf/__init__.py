"""ggfslam.ggf."""
