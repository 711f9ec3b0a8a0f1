"""A folder that another program fills (a ROS bag exporter, a capture tool), watched for new frames.

The layout is the ``folder`` dataset's: ``rgb/<name>.<png|jpg|...>`` with ``depth/<name>.png`` (16-bit), intrinsics
and depth scale from ``camera.yaml`` in the folder or the config's ``dataset.camera``. A frame is delivered once
both of its files exist and their sizes have not changed for one poll (a writer that is not atomic is not read
half-way), in natural name order, at the time it appears; frames already there when the watch starts are delivered
at once. Frames must appear in name order: a frame whose name sorts before one already delivered is passed over
with a warning. Timestamps are ``index / fps``, as the ``folder`` reader gives them, so after the run the folder
reads back as the same sequence (``ggfslam eval``, ``render``, ``run``).

The input ends with a stop request (Ctrl-C) or, with ``idle_timeout``, after that many seconds without a new frame.
"""
from __future__ import annotations

import time
from pathlib import Path

from ggfslam.data.base import check_frame_shapes
from ggfslam.data.folder import COLOUR_SUFFIXES, folder_camera
from ggfslam.data.imageio import read_depth, read_rgb
from ggfslam.data.paths import natural_key
from ggfslam.data.types import Frame
from ggfslam.errors import DatasetError
from ggfslam.sources.base import LiveSequence, LiveSource, SourceError, log


class FolderSource(LiveSource):
    """Frames appearing in ``path`` (``rgb/`` and ``depth/``), checked every ``poll`` seconds."""

    def __init__(self, path: str | Path, fps: float = 30.0, idle_timeout: float = 0.0, poll: float = 0.05,
                 capacity: int = 2):
        super().__init__(capacity)
        self.path, self.fps, self.idle_timeout, self.poll = Path(path), fps, idle_timeout, poll
        if not fps > 0:
            raise SourceError(f"--fps must be positive, got {fps}")
        self._sizes: dict[str, tuple[int, int]] = {}  # stem -> file sizes at the last poll (not yet delivered)
        self._seen: set[str] = set()
        self._last: tuple | None = None  # natural key of the last delivered name

    def describe(self) -> str:
        """One line naming the source, for metrics.json and logs."""
        idle = f", ends after {self.idle_timeout:g} s without a frame" if self.idle_timeout > 0 else ""
        return f"folder {self.path} watched every {self.poll:g} s, queue of {self.queue.capacity}{idle}"

    def open(self, config, out_dir: Path):
        """The folder's camera; the run's dataset becomes the folder (read as kind ``folder`` afterwards)."""
        from ggfslam.config import DatasetConfig
        from ggfslam.data.sources import camera_from_config

        if not self.path.is_dir():
            raise SourceError(f"{self.path}: folder to watch not found (create it, or start the program that "
                              "fills it first)")
        camera = self.camera = folder_camera(self.path, camera_from_config(config.dataset))
        for sub in ("rgb", "depth"):
            (self.path / sub).mkdir(exist_ok=True)  # the producer may not have made them yet
        self.sequence = LiveSequence(camera, f"folder {self.path}", folder=None, depth_scale=camera.depth_scale)
        d = config.dataset
        dataset = DatasetConfig(kind="folder", path=str(self.path), camera=d.camera, on_bad_frame=d.on_bad_frame,
                                max_bad_frames=d.max_bad_frames)
        return self.sequence, config.model_copy(update={"dataset": dataset})

    def _ready(self) -> list[tuple[str, Path, Path]]:
        """Frames whose two files exist and kept their sizes since the last poll, in natural name order."""
        colour, depth = {}, {}
        for p in (self.path / "rgb").iterdir():
            if p.suffix.lower() in COLOUR_SUFFIXES and not p.name.startswith(".") and p.stem not in self._seen:
                colour[p.stem] = p
        for p in (self.path / "depth").iterdir():
            if p.suffix.lower() == ".png" and not p.name.startswith(".") and p.stem in colour:
                depth[p.stem] = p
        ready = []
        for stem in sorted(depth, key=natural_key):
            try:
                sizes = (colour[stem].stat().st_size, depth[stem].stat().st_size)
            except FileNotFoundError:  # renamed or removed between the listing and now
                continue
            if self._sizes.get(stem) == sizes and all(sizes):
                ready.append((stem, colour[stem], depth[stem]))
            else:
                self._sizes[stem] = sizes
        return ready

    def _drive(self) -> None:
        quiet_since = time.perf_counter()
        while not self._stop.wait(self.poll):
            ready = self._ready()
            now = time.perf_counter()
            if not ready and self.idle_timeout > 0 and now - quiet_since >= self.idle_timeout:
                log.info("no new frame in %s for %g s: the input ends", self.path, self.idle_timeout)
                return
            for stem, rgb_path, depth_path in ready:
                self._seen.add(stem)
                self._sizes.pop(stem, None)
                key = natural_key(stem)
                if self._last is not None and key < self._last:
                    log.warning("%s appeared after a frame that sorts after it: passed over (frames must appear in "
                                "name order)", rgb_path)
                    continue
                self._last = key
                quiet_since = now
                i = len(self.sequence)
                self.sequence.add_stamp(i / self.fps, (rgb_path, depth_path))
                try:
                    rgb, depth = read_rgb(rgb_path), read_depth(depth_path, self.camera.depth_scale)
                    check_frame_shapes(str(rgb_path), rgb, depth, self.camera, str(depth_path))
                    frame, error = Frame(i, i / self.fps, rgb, depth, name=str(rgb_path)), None
                except DatasetError as e:
                    frame, error = None, e
                self._deliver(i, time.perf_counter(), now, frame, error)

