"""GTSAM custom factors for ggfslam (RGB-D observation and GCGR factors), each with checked Jacobians."""
