"""Frames, cameras, dataset readers and synthetic sequences."""
from ggfslam.data.base import RGBDDataset
from ggfslam.data.registry import DATASET_KINDS, detect_kind, open_dataset
from ggfslam.data.types import Camera, Frame

__all__ = ["Camera", "Frame", "RGBDDataset", "DATASET_KINDS", "detect_kind", "open_dataset"]
