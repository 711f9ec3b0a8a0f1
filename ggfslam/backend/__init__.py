"""ggfslam.backend."""
