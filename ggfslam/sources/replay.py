"""A dataset replayed on time: a driver thread delivers each frame at its timestamp (divided by ``rate``) into a
``LatestFrames`` queue of one or two; a frame that arrives while the queue is full pushes out the oldest one, which
is dropped and counted, as a sensor driver drops frames a busy system does not take.

Times are ``time.perf_counter()`` seconds. A frame is read from disk before it is due (the driver prefetches
one), so reading costs no delivery time; a frame that cannot be read is delivered as its ``DatasetError``.

A sensor's driver hands over decoded frames, but reading a dataset's files costs CPU (7-Scenes kitchen at 30 Hz:
PNG decoding and depth registration take ~24 ms of each 33 ms): on two cores that would compete with the system
and understate what a live run does. So by default the replay decodes every frame before its clock starts, when
they fit in ``PRELOAD_BUDGET_BYTES`` (500 frames at 640x480: 2.5 GB), and reads them as they fall due otherwise.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ggfslam.data.base import RGBDDataset
from ggfslam.data.types import Frame
from ggfslam.errors import DatasetError

log = logging.getLogger("ggfslam")
PRELOAD_BUDGET_BYTES = 4 << 30  # decoded frames a replay holds in memory at most (rgb and depth float32)


@dataclass
class Arrival:
    """One delivered frame (or the error reading it) and when it arrived."""

    index: int  # frame index in the dataset
    arrived: float  # perf_counter seconds
    due: float  # when the timestamps said it should arrive
    frame: Frame | None = None
    error: DatasetError | None = None


@dataclass
class DeliveryStats:
    received: int = 0  # frames the driver delivered
    dropped: list[int] = field(default_factory=list)  # indices pushed out of the queue unseen
    late_ms: list[float] = field(default_factory=list)  # delivery minus due time, per frame


class LatestFrames:
    """A queue of at most ``capacity`` arrivals where the newest wins: putting into a full queue drops the oldest."""

    def __init__(self, capacity: int = 2):
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self._items: deque[Arrival] = deque()
        self.capacity = capacity
        self._cond = threading.Condition()
        self._closed = False
        self.dropped: list[int] = []

    def put(self, item: Arrival) -> None:
        """Add the newest arrival; the oldest goes if the queue is full."""
        with self._cond:
            if len(self._items) >= self.capacity:
                self.dropped.append(self._items.popleft().index)
            self._items.append(item)
            self._cond.notify()

    def close(self) -> None:
        """No more arrivals: ``get`` returns None once the queue is empty."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def get(self, timeout: float | None = None) -> Arrival | None:
        """The oldest waiting arrival; None when closed and empty (or after ``timeout`` seconds without one)."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._items or self._closed, timeout):
                return None
            return self._items.popleft() if self._items else None


class ReplaySource:
    """Frames of ``dataset`` delivered at ``rate`` times their timestamps' pace; iterate to take them."""

    def __init__(self, dataset: RGBDDataset, rate: float = 1.0, capacity: int = 2, preload: bool | None = None):
        if not rate > 0:
            raise ValueError(f"--rate must be positive, got {rate}")
        cam = dataset.camera
        if preload is None:  # rgb [H, W, 3] and depth [H, W], float32
            preload = len(dataset) * cam.width * cam.height * 16 <= PRELOAD_BUDGET_BYTES
        self.dataset, self.rate, self.preload = dataset, rate, preload
        self._frames: list | None = None  # preloaded (frame, error) pairs
        self.queue = LatestFrames(capacity)
        self.stats = DeliveryStats(dropped=self.queue.dropped)  # the queue's own list: current while it runs
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def describe(self) -> str:
        """One line naming the source, for metrics.json and logs."""
        return (f"replay of {self.dataset.describe()} at {self.rate:g}x, queue of {self.queue.capacity}, "
                f"{'decoded beforehand' if self.preload else 'read as due'}")

    def start(self) -> ReplaySource:
        """Start delivering (frame 0 now, the others at their timestamps' offsets); with ``preload``, every frame is
        decoded first."""
        if self.preload and self._frames is None:
            log.info("decoding %d frames before the replay starts", len(self.dataset))
            self._frames = [self._read(i) for i in range(len(self.dataset))]
        self._thread = threading.Thread(target=self._drive, name="ggfslam-replay", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """End the input: no further frames are delivered; those waiting in the queue still come out."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def __iter__(self):
        while (a := self.queue.get()) is not None:
            yield a

    def _read(self, i: int) -> tuple[Frame | None, DatasetError | None]:
        try:
            return self.dataset[i], None
        except DatasetError as e:
            return None, e

    def _drive(self) -> None:
        stamps = np.asarray(self.dataset.timestamps, np.float64)  # [N]
        t0 = time.perf_counter()
        try:
            for i in range(len(stamps)):
                due = t0 + (stamps[i] - stamps[0]) / self.rate
                frame, error = self._read(i) if self._frames is None else self._frames[i]
                if self._frames is not None:
                    self._frames[i] = None  # delivered: the run holds it from here
                if self._stop.wait(max(0.0, due - time.perf_counter())):
                    break
                now = time.perf_counter()
                self.stats.received += 1
                self.stats.late_ms.append(1000 * (now - due))
                self.queue.put(Arrival(i, now, due, frame, error))
        finally:
            self.queue.close()
