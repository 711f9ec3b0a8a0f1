"""A dataset replayed on time: a driver thread delivers each frame at its timestamp (divided by ``rate``) into a
``LatestFrames`` queue of one or two; a frame that arrives while the queue is full pushes out the oldest one, which
is dropped and counted, as a sensor driver drops frames a busy system does not take.

A frame is read before it is due (the driver prefetches one), so reading costs no delivery time; a frame that
cannot be read is delivered as its ``DatasetError``.

A sensor's driver hands over decoded frames, but reading a dataset's files costs CPU (7-Scenes kitchen at 30 Hz:
PNG decoding and depth registration take ~24 ms of each 33 ms): on two cores that would compete with the system
and understate what a live run does. So by default the replay decodes every frame before its clock starts, when
they fit in ``PRELOAD_BUDGET_BYTES`` (500 frames at 640x480: 2.5 GB), and reads them as they fall due otherwise.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ggfslam.data.base import RGBDDataset
from ggfslam.data.types import Frame
from ggfslam.errors import DatasetError
from ggfslam.sources.base import Arrival, LatestFrames, LiveSource, log

__all__ = ["Arrival", "LatestFrames", "ReplaySource", "PRELOAD_BUDGET_BYTES"]
PRELOAD_BUDGET_BYTES = 4 << 30  # decoded frames a replay holds in memory at most (rgb and depth float32)


class ReplaySource(LiveSource):
    """Frames of ``dataset`` delivered at ``rate`` times their timestamps' pace; iterate to take them."""

    def __init__(self, dataset: RGBDDataset, rate: float = 1.0, capacity: int = 2, preload: bool | None = None):
        if not rate > 0:
            raise ValueError(f"--rate must be positive, got {rate}")
        super().__init__(capacity)
        cam = dataset.camera
        if preload is None:  # rgb [H, W, 3] and depth [H, W], float32
            preload = len(dataset) * cam.width * cam.height * 16 <= PRELOAD_BUDGET_BYTES
        self.dataset, self.rate, self.preload = dataset, rate, preload
        self._frames: list | None = None  # preloaded (frame, error) pairs

    def describe(self) -> str:
        """One line naming the source, for metrics.json and logs."""
        return (f"replay of {self.dataset.describe()} at {self.rate:g}x, queue of {self.queue.capacity}, "
                f"{'decoded beforehand' if self.preload else 'read as due'}")

    def open(self, config, out_dir: Path):
        """The dataset replayed, and the config as it is."""
        return self.dataset, config

    def start(self) -> ReplaySource:
        """Start delivering (frame 0 now, the others at their timestamps' offsets); with ``preload``, every frame is
        decoded first."""
        if self.preload and self._frames is None:
            log.info("decoding %d frames before the replay starts", len(self.dataset))
            self._frames = [self._read(i) for i in range(len(self.dataset))]
        return super().start()

    def _read(self, i: int) -> tuple[Frame | None, DatasetError | None]:
        try:
            return self.dataset[i], None
        except DatasetError as e:
            return None, e

    def _drive(self) -> None:
        stamps = np.asarray(self.dataset.timestamps, np.float64)  # [N]
        t0 = time.perf_counter()
        for i in range(len(stamps)):
            due = t0 + (stamps[i] - stamps[0]) / self.rate
            frame, error = self._read(i) if self._frames is None else self._frames[i]
            if self._frames is not None:
                self._frames[i] = None  # delivered: the run holds it from here
            if self._stop.wait(max(0.0, due - time.perf_counter())):
                return
            self._deliver(i, time.perf_counter(), due, frame, error)
