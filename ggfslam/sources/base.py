"""What every live source shares: arrivals in a newest-wins queue filled by a driver thread, delivery statistics,
and, for sources without a dataset folder behind them (a camera), the sequence the run reads and records.

A source is used by ``slam.run(live=source)`` in this order: ``open(config, out_dir)`` (the sequence the run
reads, and the config to save with it; a sensor starts here, so a missing device fails before the run folder
is touched), ``start()``, iteration over arrivals until the input ends (``stop()`` ends it early), ``close()``
(idempotent, on every exit: the device is released and the recording completed), ``describe()`` for
metrics.json.

Times are ``time.perf_counter()`` seconds.
"""
from __future__ import annotations

import logging
import queue
import threading
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ggfslam.data.types import Camera, Frame
from ggfslam.data.undistort import undistortion_of
from ggfslam.errors import DatasetError, GGFSlamError

log = logging.getLogger("ggfslam")
RECORDING_DIR = "input"  # a sensor run's recorded frames, inside its run folder (TUM layout)


class SourceError(GGFSlamError):
    """A live source cannot start (no device, no library, unreadable recording)."""


@dataclass
class Arrival:
    """One delivered frame (or the error reading it) and when it arrived."""

    index: int  # frame index in the sequence (order of arrival)
    arrived: float  # perf_counter seconds
    due: float  # when it should have arrived (a replay's timestamps; a sensor's arrival)
    frame: Frame | None = None
    error: DatasetError | None = None


@dataclass
class DeliveryStats:
    """What a live source delivered: frames received, dropped and how late."""

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


class LiveSource:
    """A driver thread (``_drive``, in subclasses) puts arrivals into a ``LatestFrames`` queue; iterating takes them.

    ``stop`` ends the input: the driver stops delivering, arrivals already queued still come out. A sensor source
    sets ``sequence`` (a ``LiveSequence``) in ``open``; each frame the run takes is then recorded into it."""

    def __init__(self, capacity: int = 2):
        self.error: Exception | None = None  # what ended the input, when the driver failed
        self.queue = LatestFrames(capacity)
        self.stats = DeliveryStats(dropped=self.queue.dropped)  # the queue's own list: current while it runs
        self.sequence: LiveSequence | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def describe(self) -> str:
        """One line naming the source, for metrics.json and logs."""
        raise NotImplementedError

    def open(self, config, out_dir: Path):
        """(the sequence the run reads, the config to save with the run)."""
        raise NotImplementedError

    def _drive(self) -> None:
        """Deliver arrivals until the input ends or ``self._stop`` is set (runs in the driver thread)."""
        raise NotImplementedError

    def start(self) -> LiveSource:
        """Start the driver thread."""
        self._thread = threading.Thread(target=self._drive_then_close, name=f"ggfslam-{type(self).__name__}",
                                        daemon=True)
        self._thread.start()
        return self

    def _drive_then_close(self) -> None:
        try:
            self._drive()
        except Exception as e:  # noqa: BLE001 - a driver failure ends the input; the run finishes with what it has
            log.error("live input ended by an error: %s", e)
            self.error = e
        finally:
            self.queue.close()

    def stop(self) -> None:
        """End the input: no further frames are delivered; those waiting in the queue still come out."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        self._release()

    def close(self) -> None:
        """Stop, and complete the recording (what the run took of the queue is written; the rest is not)."""
        self.stop()
        if self.sequence is not None:
            self.sequence.close()

    def _release(self) -> None:
        """Free the device (sensor sources)."""

    def _deliver(self, index: int, arrived: float, due: float, frame: Frame | None,
                 error: DatasetError | None = None) -> None:
        self.stats.received += 1
        self.stats.late_ms.append(1000 * (arrived - due))
        self.queue.put(Arrival(index, arrived, due, frame, error))

    def __iter__(self):
        while (a := self.queue.get()) is not None:
            if self.sequence is not None and a.frame is not None:
                self.sequence.record(a.frame)  # as the sensor gave it
                a = replace(a, frame=self.sequence.undistort(a.frame))
            yield a


class LiveSequence:
    """The sequence of a sensor run as the run reads it: the camera, every received frame's timestamp, and the
    frames the run took, recorded in TUM layout in ``folder`` by a writer thread (so ``ggfslam eval``, ``render``
    and ``view`` read the run later, and it can be run again offline). Frames dropped live are not recorded.
    The recording keeps the sensor's images and camera (``raw_camera``, with its distortion); the run reads them
    undistorted (``camera``, ``undistort``; data/undistort.py), as a dataset reading the recording does."""

    gt_poses = None

    def __init__(self, camera: Camera, name: str, folder: Path | None, depth_scale: float = 1000.0):
        self.raw_camera, self.name, self.folder, self.depth_scale = camera, name, folder, depth_scale
        self._undistortion = undistortion_of(camera)
        self.camera = camera if self._undistortion is None else self._undistortion.camera
        self._stamps: list[float] = []
        self._files: dict[int, tuple[Path, Path]] = {}
        self._writer = None
        self._todo: queue.Queue = queue.Queue()
        self._thread: threading.Thread | None = None
        self._closed = False
        self.write_error: Exception | None = None

    def add_stamp(self, timestamp: float, files: tuple[Path, Path] | None = None) -> int:
        """A frame arrived (with its colour and depth files, when it comes from files): its index in the sequence."""
        self._stamps.append(timestamp)
        if files is not None:
            self._files[len(self._stamps) - 1] = files
        return len(self._stamps) - 1

    @property
    def timestamps(self) -> np.ndarray:
        """Timestamps [N] of the frames received so far."""
        return np.asarray(self._stamps, np.float64)

    def __len__(self) -> int:
        return len(self._stamps)

    def describe(self) -> str:
        """One line naming the sequence."""
        cam = self.camera
        return f"{self.name} ({len(self)} frames, {cam.width}x{cam.height})"

    def undistort(self, frame: Frame) -> Frame:
        """The frame as the run reads it: undistorted when the sensor's camera has distortion."""
        u = self._undistortion
        return frame if u is None else replace(frame, rgb=u.rgb(frame.rgb), depth=u.depth(frame.depth))

    def record(self, frame: Frame) -> None:
        """Queue a frame the run takes for writing (no-op without a folder)."""
        if self.folder is None or self._closed:
            return
        if self._thread is None:
            from ggfslam.data.writer import TumSequenceWriter

            self._writer = TumSequenceWriter(self.folder, self.raw_camera, self.depth_scale)
            self._thread = threading.Thread(target=self._write, name="ggfslam-recorder", daemon=True)
            self._thread.start()
        self._todo.put(frame)

    def _write(self) -> None:
        while (frame := self._todo.get()) is not None:
            try:
                self._files[frame.index] = self._writer.add(frame)
            except Exception as e:  # noqa: BLE001 - a full disk loses the recording, not the run
                if self.write_error is None:
                    log.error("recording %s stopped: %s", self.folder, e)
                self.write_error = e

    def close(self) -> None:
        """Write what is queued, then the lists and camera.yaml; later frames are not recorded."""
        self._closed = True
        if self._thread is None:
            return
        self._todo.put(None)
        self._thread.join()
        self._thread = None
        if self.write_error is None:
            self._writer.close()

    def __getitem__(self, i: int) -> Frame:
        from ggfslam.data.imageio import read_depth, read_rgb

        if i not in self._files:
            raise DatasetError(self.folder or self.name, f"frame {i} was not recorded (it was dropped while live)")
        rgb, depth = self._files[i]
        return self.undistort(Frame(i, self._stamps[i], read_rgb(rgb), read_depth(depth, self.depth_scale)))
