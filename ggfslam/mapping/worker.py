"""Mapping beside tracking: keyframes are queued and a worker thread trains; tracking never waits.

The tracking thread stores a keyframe's images (``KeyframeStore.add``, a few ms) and queues its id; the
worker seeds its anchors and trains its budget of steps (``Mapper.keyframe_budget``) focused on it, and between
keyframes keeps training on random keyframes (``mapping.idle_training``). The numba kernels release the
GIL, and the worker gets an explicit numba thread budget (``mapping.threads``) so tracking and mapping
do not oversubscribe the cores (PERF_NOTES: two threads each asking for all cores collapse). Once
tracking has finished, the worker takes every core for the keyframes still queued.

With ``mapping.realtime`` (live input) a newly queued keyframe ends the current keyframe's focused training, the
worker runs at a lower CPU priority than tracking, and once tracking has finished the queued keyframes are only
seeded: the final refinement (in the run's thread) trains them.
"""
from __future__ import annotations

import logging
import queue
import threading

import numpy as np

from ggfslam.mapping.mapper import Mapper

log = logging.getLogger("ggfslam")


class MappingWorker:
    """Feeds keyframes to a ``Mapper``: inline (sequential, repeatable) or in a worker thread."""

    def __init__(self, mapper: Mapper, concurrent: bool, threads: int = 1, realtime: bool = False):
        self.mapper = mapper
        self.realtime = realtime
        self.cfg = mapper.cfg
        self.concurrent = concurrent
        self.threads = threads
        self._queue: queue.Queue = queue.Queue()
        self._pending: dict[int, np.ndarray | None] = {}  # queued, not yet trained (saved in checkpoints)
        self._unstored: dict[int, tuple] = {}  # realtime: (frame index, rgb, depth) the worker stores before seeding
        self._pending_lock = threading.Lock()
        self._stop = threading.Event()
        self._abort = threading.Event()
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None
        if concurrent:
            import torch

            # torch's intra-op pool is process-wide; tracking uses OpenCV/GTSAM/Open3D, not torch, so capping
            # it here gives the mapping thread its budget without starving tracking
            self._torch_threads = torch.get_num_threads()  # restored when tracking is done
            torch.set_num_threads(max(1, threads))
            self._thread = threading.Thread(target=self._run, name="ggfslam-mapping", daemon=True)
            self._thread.start()

    def submit(self, kf_id: int, frame_index: int, rgb: np.ndarray, depth: np.ndarray,
               landmarks: np.ndarray | None = None) -> None:
        """A new keyframe: stored now (in realtime mode by the worker, off the tracking thread: ~40 ms at 640x480),
        seeded and trained now (sequential) or by the worker."""
        self._raise()
        if self.realtime and self.concurrent:
            with self._pending_lock:
                self._unstored[kf_id] = (frame_index, rgb, depth)
        else:
            self.mapper.store.add(kf_id, frame_index, rgb, depth)
        self.enqueue(kf_id, landmarks)

    def enqueue(self, kf_id: int, landmarks: np.ndarray | None = None) -> None:
        """Queue an already stored keyframe for seeding and training."""
        if not self.concurrent:
            self.mapper.seed_keyframe(kf_id, landmarks=landmarks)
            self.mapper.train(self.mapper.keyframe_budget(kf_id), focus=kf_id)
            return
        with self._pending_lock:
            self._pending[kf_id] = landmarks
        self._queue.put(kf_id)

    def rest(self, kf_id: int, frame_index: int) -> None:
        """The camera rests at keyframe ``kf_id``'s view at frame ``frame_index``, which made no keyframe
        (``tracking.keyframe_still_translation``): the frames since the last keyframe (or the last such call) get
        their steps now (``Mapper.rest_steps``), focused on that view, where the camera looks, instead of with the
        next keyframe. Sequential mode only: the concurrent worker trains while frames arrive."""
        if not self.concurrent:
            self.mapper.train(self.mapper.rest_steps(frame_index), focus=kf_id)

    def pending(self) -> dict[int, np.ndarray | None]:
        """Keyframes queued or in training, not yet done (id -> landmarks); their images are stored first (a
        checkpoint re-queues them on resume, from the store)."""
        with self._pending_lock:
            while self._unstored:
                kf_id, images = self._unstored.popitem()
                self.mapper.store.add(kf_id, *images)
            return dict(self._pending)

    def _run(self) -> None:
        import numba

        numba.set_num_threads(max(1, min(self.threads, numba.config.NUMBA_NUM_THREADS)))
        if self.realtime:
            _lower_priority()
        m = self.mapper
        full = False
        try:
            while not self._abort.is_set():
                if self._stop.is_set() and not full:
                    # tracking has finished: the queued keyframes get every core (numba's budget is per thread)
                    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
                    self._restore_torch_threads()
                    full = True
                    log.info("tracking finished: mapping takes %d threads for %d queued keyframes (%d steps so far)",
                             numba.get_num_threads(), self._queue.qsize(), m.iteration)
                if full and self.realtime:
                    self._seed_queued()
                    return
                idle = self.cfg.idle_training and len(m.store) > 0 and not self._stop.is_set()
                try:
                    kf_id = self._queue.get(timeout=0.0 if idle else 0.05)
                except queue.Empty:
                    if self._stop.is_set() and self._queue.empty():
                        return
                    if idle:
                        m.train(5, stop=self._abort)
                    continue
                landmarks = self._take(kf_id)
                m.seed_keyframe(kf_id, landmarks=landmarks)
                m.train(m.keyframe_budget(kf_id), focus=kf_id, stop=_Preempt(self) if self.realtime else self._abort)
                # pending until trained: a checkpoint taken meanwhile re-queues it on resume, where seeding it
                # again is a no-op and its focused steps are run in full
                with self._pending_lock:
                    self._pending.pop(kf_id, None)
        except BaseException as e:  # surfaced to the tracking thread at the next keyframe / finish
            self._error = e
            log.exception("mapping worker failed")

    def _seed_queued(self) -> None:
        """Seed every queued keyframe without training it (realtime mode, once tracking has finished)."""
        while not self._abort.is_set():
            try:
                kf_id = self._queue.get_nowait()
            except queue.Empty:
                return
            self.mapper.seed_keyframe(kf_id, landmarks=self._take(kf_id))
            with self._pending_lock:
                self._pending.pop(kf_id, None)

    def _take(self, kf_id: int) -> np.ndarray | None:
        """A queued keyframe's landmarks, its images stored first when the tracking thread left that to us."""
        with self._pending_lock:  # held while storing: a checkpoint (pending) must not miss the images
            images = self._unstored.pop(kf_id, None)
            if images is not None:
                self.mapper.store.add(kf_id, *images)
            return self._pending.get(kf_id)

    def _restore_torch_threads(self) -> None:
        import torch

        torch.set_num_threads(self._torch_threads)

    def _raise(self) -> None:
        if self._error is not None:
            raise RuntimeError("mapping worker failed") from self._error

    def abort(self) -> None:
        """Stop the worker after its current step, dropping queued keyframes (a failed or interrupted run)."""
        self._abort.set()
        self._join()

    def finish(self) -> None:
        """Process every queued keyframe, then stop the worker."""
        self._join()
        self._raise()

    def _join(self) -> None:
        """Stop the worker once its queue is done (at once if aborted) and give torch its threads back (the
        worker does so itself when it sees the stop, but not when it aborts or fails first)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
            self._restore_torch_threads()


def _lower_priority() -> None:
    """Give this thread (and the threads it starts) nice +10: while frames arrive, tracking wins the cores. Linux
    sets a thread's priority by its id; elsewhere this is a no-op."""
    import os

    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 10)
    except (AttributeError, OSError) as e:
        log.info("mapping thread priority unchanged (%s)", e)


class _Preempt:
    """Stops a keyframe's focused training when the run is aborted, tracking has finished, or another keyframe
    waits (realtime mode)."""

    def __init__(self, worker: MappingWorker):
        self.worker = worker

    def is_set(self) -> bool:
        w = self.worker
        return w._abort.is_set() or w._stop.is_set() or not w._queue.empty()
