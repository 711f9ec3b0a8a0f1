"""The system: wires dataset, tracker and evaluation, runs a sequence and writes the run directory."""
from __future__ import annotations

import logging
import platform
import random
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

from ggfslam import __version__
from ggfslam.atomic import write_text_atomic
from ggfslam.config import Config, config_differences, load_config, save_config
from ggfslam.data.base import RGBDDataset
from ggfslam.data.sources import open_dataset_from_config
from ggfslam.data.trajectory_io import read_tum_trajectory, write_tum_trajectory
from ggfslam.errors import DatasetError, GGFSlamError, RunDirError
from ggfslam.eval.perf import StageTimer, current_rss_mb, peak_rss_mb
from ggfslam.eval.trajectory import trajectory_metrics
from ggfslam.kernel_warmup import compile_kernels, load_kernels
from ggfslam.render.cpu import release_free_memory
from ggfslam.rundir import (
    CONFIG_FILE,
    GAUSSIANS_FILE,
    GRAPH_FILE,
    GROUNDTRUTH_FILE,
    KEYFRAME_FEATURES_DIR,
    KEYFRAME_IMAGES_DIR,
    KEYFRAMES_FILE,
    LOG_FILE,
    MESH_FILE,
    METRICS_FILE,
    PLANARITY_FILE,
    RUN_INFO_FILE,
    TRACKING_LOG_FILE,
    TRAJECTORY_FILE,
    prepare_run_dir,
    read_json,
    require_run_dir,
    write_json,
)
from ggfslam.saved_run import load_mapper

log = logging.getLogger("ggfslam")
RSS_EVERY = 100  # frames between memory samples (metrics.json system.rss_mb_by_frame)


def setup_runtime(config: Config) -> None:
    """Seed every RNG and set the thread budget (explicit budgets avoid oversubscribing 2 cores)."""
    seed = config.runtime.seed
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    if config.runtime.num_threads > 0:
        torch.set_num_threads(config.runtime.num_threads)


def make_tracker(config: Config, dataset: RGBDDataset):
    """The tracker named by ``tracking.method``."""
    if config.tracking.method == "o3d_odometry":
        from ggfslam.frontend.odometry_baseline import OdometryBaselineTracker

        return OdometryBaselineTracker(dataset.camera, config.tracking)
    from ggfslam.backend.backend import Backend
    from ggfslam.frontend.tracker import OrbTracker

    backend = Backend(dataset.camera, config.tracking, config.backend)
    return OrbTracker(dataset.camera, config.tracking, backend, config.runtime.seed)


def _progress(enabled: bool):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
        TextColumn("{task.fields[fps]:.1f} frames/s"), TimeRemainingColumn(),
        disable=not enabled, transient=False,
    )


def _attach_log(run_dir: Path) -> logging.Handler:
    handler = logging.FileHandler(run_dir / LOG_FILE)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    return handler


def make_mapper(config: Config, camera, tracker, run_dir: Path):
    """The Gaussian mapper for a run (None when ``mapping.enabled`` is off), reading poses from the SLAM map."""
    if not config.mapping.enabled:
        return None
    from ggfslam.mapping.mapper import Mapper
    from ggfslam.render.types import RenderSettings

    settings = RenderSettings(backend=config.render.backend)
    slam_map = tracker.map
    return Mapper(config.mapping, camera, settings, lambda: slam_map.poses(), run_dir / KEYFRAME_IMAGES_DIR,
                  config.runtime.seed, ggf=config.ggf)


def attach_gcgr(config: Config, tracker, mapper, camera) -> None:
    """With ``gcgr.enabled``, give the backend the map's GCGR factors (and per-frame refinement where asked)."""
    if not config.gcgr.enabled or mapper is None:
        return
    from ggfslam.backend.gcgr_source import GCGRSource
    from ggfslam.render.api import select_backend

    per_frame = config.gcgr.per_frame == "on" or (
        config.gcgr.per_frame == "auto" and select_backend(config.render.backend) == "gsplat")
    source = GCGRSource(mapper, camera, config.gcgr, per_frame)
    tracker.backend.attach_gcgr(source)
    mapper.view_sink = source  # training renders become GCGR models (gcgr.harvest_every)


def _keyframe_landmarks(tracker, kf_id: int) -> np.ndarray:
    """World positions [L, 3] of the live landmarks a keyframe observes."""
    m = tracker.map
    with m.lock:
        if kf_id not in m.keyframes:  # culled by the backend before the mapper took it (concurrent mode)
            return np.zeros((0, 3))
        ids = m.keyframes[kf_id].landmark_ids
        ids = ids[ids >= 0]
        ids = ids[m.alive[ids]]
        return m.positions[ids].copy()


def _check_resume_config(config: Config, run_dir: Path) -> None:
    diff = config_differences(load_config(run_dir / CONFIG_FILE), config)
    if diff:
        raise RunDirError(f"{run_dir}: --resume with a configuration that differs from the run's {CONFIG_FILE} in "
                          f"{', '.join(diff)}; resume without a config (the saved one is used)")


@dataclass
class _RunState:
    """What a run has built so far: enough to continue it, or to save it when it stops early."""

    n: int  # frames in the sequence
    timer: StageTimer = field(default_factory=StageTimer)
    tracker: object = None
    mapper: object = None
    worker: object = None
    lines: list[str] = field(default_factory=lambda: ["# index timestamp state keyframe matches fitness ms"])
    rss: list = field(default_factory=list)  # (frames done, MiB): memory against length
    skipped: list[dict] = field(default_factory=list)  # bad frames passed over: {"index", "error"}
    dropped: list[int] = field(default_factory=list)  # live input: frames that arrived while the system was busy
    live: dict | None = None  # live input: latency_ms per processed frame, stopped_by, source
    start: int = 0  # first frame this invocation tracks
    frame: int = 0  # the frame being processed
    consistent: int | None = None  # frames [0, consistent) are done and the state is whole (None: mid-update)
    checkpointed: int | None = None  # the frame checkpoint.pt continues at (None: no checkpoint)
    wall: float = 0.0

    def frame_indices(self, n_poses: int) -> np.ndarray:
        """Frame indices [n_poses] of the tracker's poses (every frame but the skipped and dropped ones, in
        order)."""
        bad = {s["index"] for s in self.skipped} | set(self.dropped)
        return np.array([i for i in range(self.n) if i not in bad][:n_poses], dtype=np.int64)

    def checkpoint(self, run_dir: Path, next_frame: int, finished: bool = False) -> None:
        """Write checkpoint.pt for continuing at ``next_frame``."""
        from ggfslam.checkpoint import save_checkpoint

        with self.timer("checkpoint"):
            save_checkpoint(run_dir, next_frame=next_frame, tracker=self.tracker, mapper=self.mapper,
                            pending=None if self.worker is None else self.worker.pending(), lines=self.lines,
                            timer=self.timer, rss=self.rss, skipped=self.skipped, finished=finished)
        self.checkpointed = next_frame


class _StopRequests:
    """Ctrl-C or SIGTERM while frames are tracked: the first stops the run after the current frame, with what it
    has saved and a checkpoint to ``--resume`` from; a second stops it at once, as does one outside the tracking
    loop (finishing, writing outputs). During the final refinement the first one ends the training after the
    current step (``is_set``; the run is then saved as stopped), so the stop never lands inside a compiled kernel,
    which would turn it into a SystemError; another one stops at once. Signals are only caught in the main thread."""

    def __init__(self):
        self.requested: str | None = None
        self.tracking = False  # inside the frame loop, where a stop can wait for the frame's end
        self.refining = False  # inside the final refinement, where a stop can wait for the step's end
        self.halted: str | None = None  # the signal that ended the final refinement
        self._previous: dict = {}

    def __enter__(self) -> _StopRequests:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, _frame) -> None:
        if self.refining and self.halted is None:
            self.halted = signal.Signals(signum).name
            log.warning("%s: ending the final refinement after this step and saving the run (again to stop at once)",
                        self.halted)
            return
        if self.requested is not None or not self.tracking:
            raise KeyboardInterrupt(signal.Signals(signum).name)
        self.requested = signal.Signals(signum).name
        log.warning("%s: stopping after this frame and saving the run (again to stop at once)", self.requested)

    def is_set(self) -> bool:
        """The final refinement was asked to stop."""
        return self.halted is not None

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def run(config: Config, out_dir: str | Path, overwrite: bool = False, progress: bool | None = None,
        resume: bool = False, observer=None, live=None) -> dict:
    """Run the system on the configured sequence, write the run directory and return its metrics.

    With ``resume``, ``out_dir`` must be an unfinished run; it continues from its checkpoint (from the first frame
    when it stopped before writing one). A run that stops early (an error, Ctrl-C, SIGTERM) first saves what it
    has (``_save_stopped_run``). ``observer`` (e.g. ``viewer.live.LiveViewer``) is told ``started(config, dataset,
    run_dir, tracker, mapper)``, ``frame(frame, result)`` after each tracked frame and ``finished(run_dir)``.
    ``live`` is a live source (``sources.base.LiveSource``: a replay, a camera, a watched folder): frames then
    arrive on its clock, those arriving while the system is busy are dropped, and a stop request ends the input,
    after which the run finishes and writes every output (metrics.json ``live``)."""
    setup_runtime(config)
    if live is not None and resume:
        raise RunDirError(f"{out_dir}: a live run cannot be resumed (its input is gone); start a new one")
    source = live
    # a fresh install compiles the mapping kernels on every core while the input opens (kernel_warmup.py)
    compiling = compile_kernels(background=True) if config.mapping.enabled else None
    try:
        # bad input (a dataset, a missing camera) fails before the run folder is touched
        if source is None:
            dataset = open_dataset_from_config(config.dataset)
        else:
            dataset, config = source.open(config, Path(out_dir))
        try:
            run_dir, ckpt = _open_run_dir(config, out_dir, overwrite, resume)
        except BaseException:
            if source is not None:
                source.close()
            raise
    except BaseException:
        if compiling is not None:
            compiling.cancel()
        raise
    handler = _attach_log(run_dir)
    st = _RunState(len(dataset))
    if source is not None:
        st.live = {"latency_ms": [], "stopped_by": None, "source": source.describe()}
    try:
        if compiling is not None:  # after the log is attached, so the run's log.txt records the compile
            compiling.wait()
        with _StopRequests() as stop:
            log.info("run %s on %s", config.name, dataset.describe())
            _restore_or_start(config, dataset, run_dir, ckpt, st)
            if source is not None:
                write_json(run_dir / RUN_INFO_FILE, {**read_json(run_dir / RUN_INFO_FILE), "live": source.describe()})
            if observer is not None:
                observer.started(config, dataset, run_dir, st.tracker, st.mapper)
            if source is not None:
                _warm_up_kernels(config, dataset.camera, st.mapper is not None)
            _track_sequence(config, dataset, run_dir, st, stop, progress, observer, source)
            _finish_sequence(config, st, stop)
            metrics = _write_outputs(config, dataset, run_dir, st)
        info = read_json(run_dir / RUN_INFO_FILE)
        info.update(status="finished", finished=datetime.now(timezone.utc).isoformat(timespec="seconds"))
        write_json(run_dir / RUN_INFO_FILE, info)
        log.info("finished: %s", metrics.get("trajectory", {}))
        if observer is not None:
            try:
                observer.finished(run_dir)
            except Exception as e:  # noqa: BLE001 - the run's outputs are written; a viewer's failure is not the run's
                log.warning("the observer could not show the finished run: %s", e)
        return metrics
    except BaseException as e:
        _save_stopped_run(dataset, run_dir, st, e)
        raise
    finally:
        if source is not None:
            source.close()  # after an error the driver would read the rest of the input for nobody
        if st.worker is not None:
            st.worker.abort()  # no-op after finish(); after an error, no training goes on in the background
        if getattr(st.tracker, "backend", None) is not None:
            st.tracker.backend.close()  # no-op after finish(); after an error, its solver process ends
        log.removeHandler(handler)
        handler.close()


def _open_run_dir(config: Config, out_dir: str | Path, overwrite: bool, resume: bool) -> tuple[Path, dict | None]:
    """The run directory (new, or the unfinished run to resume) and its checkpoint (None: start from frame 0)."""
    from ggfslam.checkpoint import CHECKPOINT_FILE, load_checkpoint

    ckpt = None
    if resume:
        run_dir = require_run_dir(out_dir)
        _check_resume_config(config, run_dir)
        info = read_json(run_dir / RUN_INFO_FILE)
        if info.get("status") == "finished":
            raise RunDirError(f"{run_dir}: the run finished; nothing to resume")
        if info.get("live"):
            raise RunDirError(f"{run_dir}: a live run cannot be resumed (its input is gone); start a new one")
        for leftover in [*run_dir.glob(".*.tmp-*"), *(run_dir / KEYFRAME_IMAGES_DIR).glob(".*.tmp-*"),
                         *(run_dir / KEYFRAME_FEATURES_DIR).glob(".*.tmp-*")]:
            leftover.unlink()  # a write cut short by a kill (ggfslam.atomic): never a file of the run
        if (run_dir / CHECKPOINT_FILE).is_file():
            ckpt = load_checkpoint(run_dir)
    else:
        run_dir = prepare_run_dir(out_dir, overwrite)
        save_config(config, run_dir / CONFIG_FILE)
    return run_dir, ckpt


def _restore_or_start(config: Config, dataset: RGBDDataset, run_dir: Path, ckpt: dict | None, st: _RunState) -> None:
    """Tracker, mapper and worker: new, or as the checkpoint left them; run.json says the run is running."""
    from ggfslam.checkpoint import set_rng_state, unpickle_tracker

    info = read_json(run_dir / RUN_INFO_FILE)  # {} for a new run; a resumed one keeps its record
    for key in ("stopped_at_frame", "error", "saved", "resume_from_frame"):  # written by _save_stopped_run
        info.pop(key, None)
    if not info:
        info = {"ggfslam_version": __version__, "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                "command": sys.argv, "dataset": dataset.describe(), "camera": dataset.camera.to_dict(),
                "python": platform.python_version(), "torch": torch.__version__}
    info["status"] = "running"
    if ckpt is not None:
        info.update(resumed_at_frame=ckpt["next_frame"], resumed=datetime.now(timezone.utc).isoformat(timespec="seconds"))
        st.tracker = unpickle_tracker(ckpt)
        st.lines, st.start = ckpt["lines"], ckpt["next_frame"]
        st.checkpointed = st.start
        st.skipped = list(ckpt.get("skipped", []))
        st.rss = list(ckpt.get("rss", []))
        if ckpt["timer"] is not None:
            st.timer.total.update(ckpt["timer"]["total"])
            st.timer.calls.update(ckpt["timer"]["calls"])
        log.info("resumed at frame %d", st.start)
    else:
        st.tracker = make_tracker(config, dataset)
    slam_map = getattr(st.tracker, "map", None)
    if slam_map is not None:  # keyframes' features on disk, behind a bounded cache (a checkpoint's: found again)
        slam_map.feature_store.attach(run_dir / KEYFRAME_FEATURES_DIR, config.backend.feature_cache)
    write_json(run_dir / RUN_INFO_FILE, info)
    st.mapper = make_mapper(config, dataset.camera, st.tracker, run_dir)
    if st.mapper is not None:
        from ggfslam.mapping.worker import MappingWorker

        if ckpt is not None and ckpt["mapper"] is not None:
            st.mapper.load_state(ckpt["mapper"])
            # keyframes stored after the checkpoint are made again, under the same ids, as the run goes on
            st.mapper.store.retain(ckpt["kf_frames"])
        elif ckpt is None:
            st.mapper.store.retain({})  # images a run stopped before its first checkpoint left behind
        st.worker = MappingWorker(st.mapper, config.mapping.concurrent, config.mapping.threads,
                                  config.mapping.realtime)
        attach_gcgr(config, st.tracker, st.mapper, dataset.camera)
        for kf_id, lms in (ckpt or {}).get("pending", {}).items():
            st.worker.enqueue(kf_id, lms)
    if ckpt is not None:
        set_rng_state(ckpt["rng"])
    st.consistent = st.start


def _warm_up_kernels(config: Config, camera, mapping: bool) -> None:
    """Load the compiled kernels of tracking and, with ``mapping``, of the mapper before a live input starts: loading
    or, on a fresh install, compiling them holds the GIL for seconds (a recording of 4 s at 8 Hz lost 22 of its
    first 23 frames while the first keyframe's seeding loaded the mapper's)."""
    t0 = time.perf_counter()
    load_kernels(config, camera, mapping)
    log.info("kernels loaded in %.1f s, before the input starts", time.perf_counter() - t0)


def _dataset_frames(dataset: RGBDDataset, st: _RunState, stop: _StopRequests):
    """Arrivals of a run read from disk, one after the other from ``st.start`` (no clock, nothing dropped); a stop
    request ends the run before the next frame is read (the frame being tracked is finished first)."""
    from ggfslam.sources.base import Arrival

    for i in range(st.start, st.n):
        st.frame, st.consistent = i, i
        if stop.requested:
            raise KeyboardInterrupt(f"{stop.requested} at frame {i}")
        try:
            with st.timer("load"):
                frame = dataset[i]
        except DatasetError as e:
            yield Arrival(i, 0.0, 0.0, error=e)
            continue
        yield Arrival(i, 0.0, 0.0, frame=frame)


def _track_sequence(config: Config, dataset: RGBDDataset, run_dir: Path, st: _RunState, stop: _StopRequests,
                    progress: bool | None, observer=None, source=None) -> None:
    """Track every frame from ``st.start`` (training the map on the keyframes), skipping bad frames; with a live
    ``source`` (``sources.base.LiveSource``), the frames it delivers, until it ends or a stop is requested
    (which ends the input: the run then finishes as usual)."""
    # a live run cannot be resumed (its input is gone): no checkpoints while frames arrive (each stalls tracking
    # for ~0.6 s on the 7-Scenes kitchen, ~18 frames at 30 Hz); the finished run still writes one
    every = config.mapping.checkpoint_every if source is None else 0
    max_bad = int(config.dataset.max_bad_frames * st.n)
    show = config.runtime.progress if progress is None else progress
    t_start = time.perf_counter()
    stop.tracking = True
    arrivals = _dataset_frames(dataset, st, stop) if source is None else iter(source.start())
    with _progress(show and sys.stderr.isatty()) as bar:
        task = bar.add_task("tracking", total=st.n or None, completed=st.start, fps=0.0)
        for a in arrivals:
            i = a.index
            st.frame, st.consistent = i, i
            if stop.requested and source is not None:
                if not st.live.get("stopped_by"):  # a second one stops at once (_StopRequests)
                    log.warning("%s: the input ends at frame %d; finishing the run", stop.requested, i)
                    st.live["stopped_by"] = stop.requested
                    source.stop()
            if source is not None:
                _note_dropped(dataset, st, source, bar, task)
            if a.error is not None:
                if config.dataset.on_bad_frame == "error":
                    raise a.error
                _skip_frame(dataset, st, i, a.error, max_bad)
                bar.update(task, advance=1)
                continue
            frame = a.frame
            st.consistent = None
            t0 = time.perf_counter()
            with st.timer("tracking"):
                res = st.tracker.track(frame)
            ms = 1000 * (time.perf_counter() - t0)
            if source is not None:
                st.live["latency_ms"].append(1000 * (time.perf_counter() - a.arrived))
            st.lines.append(f"{frame.index} {frame.timestamp:.6f} {res.state.value} {int(res.keyframe)} "
                            f"{res.matches} {res.fitness:.4f} {ms:.1f}")
            if observer is not None:
                observer.frame(frame, res)
            if res.keyframe and st.worker is not None:
                _map_keyframe(st, res.keyframe_id, frame)
                if every and len(st.mapper.store) % every == 0:
                    st.checkpoint(run_dir, i + 1)
            elif res.rests_at >= 0 and st.worker is not None:
                with st.timer("mapping"):  # at rest: this frame's steps go to the view the camera looks at
                    st.worker.rest(res.rests_at, frame.index)
            if (i + 1) % RSS_EVERY == 0 or i + 1 == st.n:
                release_free_memory()  # the sample shows what the run holds, not glibc's cache of freed pages
                st.rss.append((i + 1, round(current_rss_mb(), 1)))
            bar.update(task, advance=1, fps=st.timer.fps("tracking"))
    _final_keyframe(st)
    if source is not None:
        source.close()  # the recording is complete before the outputs read it back
        _note_dropped(dataset, st, source, bar, task)
        st.n = source.stats.received  # a live sequence is as long as what arrived (a sensor's, a stopped replay's)
        if source.error is not None and not st.live["stopped_by"]:
            st.live["stopped_by"] = f"input error: {source.error}"
    stop.tracking = False
    st.frame = st.consistent = st.n
    st.wall += time.perf_counter() - t_start


def _final_keyframe(st: _RunState) -> None:
    """The input's last frame as a keyframe (``tracking.final_keyframe_after``), handed to the mapper like any."""
    kf = st.tracker.promote_last_frame()
    if kf is None:
        rest = getattr(st.tracker, "rests_at", None)
        if rest is not None and st.worker is not None:
            # the frames since the last keyframe were held at a keyframe's view: they still earn their mapping steps
            with st.timer("mapping"):
                st.worker.rest(rest, st.tracker.last_frame.index)
        return
    frame = st.tracker.last_frame
    for j in range(len(st.lines) - 1, 0, -1):  # its tracking.txt row now says keyframe
        f = st.lines[j].split(" ")
        if f[0] == str(frame.index):
            f[3] = "1"
            st.lines[j] = " ".join(f)
            break
    if st.worker is not None:
        _map_keyframe(st, kf.id, frame)


def _map_keyframe(st: _RunState, kf_id: int, frame) -> None:
    """Hand a new keyframe's images and landmarks to the mapping worker."""
    with st.timer("mapping"):  # sequential mode: training; concurrent: storing the images
        st.worker.submit(kf_id, frame.index, frame.rgb, frame.depth, _keyframe_landmarks(st.tracker, kf_id))


def _note_dropped(dataset: RGBDDataset, st: _RunState, source, bar, task) -> None:
    """Rows for the frames the live source dropped since the last call (they get no pose)."""
    for i in source.stats.dropped[len(st.dropped):]:
        st.dropped.append(int(i))
        st.lines.append(f"{i} {float(dataset.timestamps[i]):.6f} dropped 0 0 0.0000 0.0")
        bar.update(task, advance=1)


def _skip_frame(dataset: RGBDDataset, st: _RunState, i: int, e: DatasetError, max_bad: int) -> None:
    """Pass over an unreadable frame: one warning, a ``skipped`` row in tracking.txt; too many end the run."""
    st.skipped.append({"index": i, "error": str(e)})
    log.warning("frame %d skipped: %s", i, e)
    st.lines.append(f"{i} {float(dataset.timestamps[i]):.6f} skipped 0 0 0.0000 0.0")
    if len(st.skipped) > max_bad:
        raise DatasetError(e.path, f"{e.reason}; {len(st.skipped)} of {st.n} frames could not be read, more than "
                                   f"dataset.max_bad_frames = {st.n and max_bad / st.n:.0%} allows "
                                   f"(frames {', '.join(str(s['index']) for s in st.skipped[:10])}"
                                   f"{', ...' if len(st.skipped) > 10 else ''})", e.line)


def _finish_sequence(config: Config, st: _RunState, stop: _StopRequests) -> None:
    """Let the backend and the mapper finish their queues, then the final map refinement."""
    st.consistent = None
    t0 = time.perf_counter()
    with st.timer("finish"):
        st.tracker.finish()  # the backend's queued keyframes: their corrections belong in the trajectory
        if st.worker is not None:
            st.worker.finish()
    # tracking, the backend and the queued keyframes are done: the state is whole again, so a stop during the final
    # refinement (a live run's second Ctrl-C) saves a checkpoint of the whole run
    st.consistent = st.n
    if st.mapper is not None:
        with st.timer("final_refinement"):
            st.mapper.sync_poses()  # the final global BA may have moved keyframes
            stop.refining = True
            try:
                if config.mapping.final_seconds > 0:
                    st.mapper.train(sys.maxsize, stop=_Deadline(config.mapping.final_seconds, also=stop))
                else:
                    st.mapper.train(config.mapping.final_iterations, stop=stop)
            finally:
                stop.refining = False
            if stop.halted:
                raise KeyboardInterrupt(f"{stop.halted} during the final refinement")
            st.mapper.refit_exposures()  # each keyframe's last fit is as old as its last step
    st.wall += time.perf_counter() - t0


class _Deadline:
    """A stop signal (``is_set``) that turns on ``seconds`` after it is made, or with ``also``."""

    def __init__(self, seconds: float, also: _StopRequests | None = None):
        self.end = time.perf_counter() + seconds
        self.also = also

    def is_set(self) -> bool:
        return time.perf_counter() >= self.end or (self.also is not None and self.also.is_set())


def _write_trajectories(run_dir: Path, st: _RunState, note: str = ""):
    """trajectory.txt, keyframes.txt and tracking.txt of the frames done; returns (stamps, poses, lost, frame
    indices) of the trajectory."""
    stamps, poses, lost = st.tracker.trajectory()  # every frame, through its optimized reference keyframe
    tracker = st.tracker
    write_tum_trajectory(run_dir / TRAJECTORY_FILE, stamps, poses,
                         header=f"ggfslam {__version__} {tracker.name}: camera-to-world, all frames{note}")
    kf_traj = tracker.keyframe_trajectory()
    if kf_traj is not None:
        write_tum_trajectory(run_dir / KEYFRAMES_FILE, *kf_traj,
                             header=f"ggfslam {__version__} {tracker.name}: camera-to-world, keyframes{note}")
    write_text_atomic(run_dir / TRACKING_LOG_FILE, "\n".join(st.lines) + "\n")
    return stamps, poses, lost, st.frame_indices(len(stamps))


def _write_outputs(config: Config, dataset: RGBDDataset, run_dir: Path, st: _RunState) -> dict:
    """Every output of a finished run (trajectories, graph, map, mesh, checkpoint) and its metrics."""
    tracker, mapper, timer = st.tracker, st.mapper, st.timer
    stamps_a, poses_a, lost_a, frames = _write_trajectories(run_dir, st)
    if getattr(tracker, "backend", None) is not None:  # the factor graph (the odometry baseline has none)
        from ggfslam.backend.export import write_graph_json

        write_graph_json(run_dir / GRAPH_FILE, tracker.backend.map, dataset.camera, config.tracking,
                         config.backend, tracker.backend.gcgr)
    gt = dataset.gt_poses
    if gt is not None:
        write_tum_trajectory(run_dir / GROUNDTRUTH_FILE, dataset.timestamps, gt,
                             header="ground truth of the frames of this run (the colour camera, camera-to-world)")
    metrics = {
        "sequence": {"dataset": dataset.describe(), "frames": st.n, "width": dataset.camera.width,
                     "height": dataset.camera.height},
        "tracking": {"method": tracker.name, "frames": len(stamps_a), "frames_lost": int(lost_a.sum()),
                     "frames_skipped": len(st.skipped), "skipped": st.skipped, "fps": timer.fps("tracking"),
                     "frames_held_still": int(getattr(tracker, "held_still", 0))},
        "backend": tracker.summary(),
    }
    gcgr = getattr(getattr(tracker, "backend", None), "gcgr", None)
    if gcgr is not None and (unused := gcgr.unused_warning()):
        log.warning(unused)
    if st.live is not None:
        metrics["live"] = _live_metrics(st)
    if gt is not None:
        metrics["trajectory"] = _trajectory_metrics(stamps_a, poses_a, dataset.timestamps, gt, config)
    if mapper is not None:
        with timer("map_outputs"):
            metrics.update(_map_outputs(config, mapper, tracker, dataset, frames, poses_a, run_dir))
        st.checkpoint(run_dir, st.n, finished=True)
    metrics["system"] = {"wall_seconds": st.wall, "peak_rss_mb": peak_rss_mb(), "rss_mb_by_frame": st.rss,
                         "stages": timer.summary()}
    write_json(run_dir / METRICS_FILE, metrics)
    return metrics


def _live_metrics(st: _RunState) -> dict:
    """metrics.json ``live``: what arrived, what was processed and dropped, arrival-to-pose latency."""
    lat = np.asarray(st.live["latency_ms"], np.float64)
    processed = len(lat)
    return {"source": st.live["source"], "frames_received": st.n, "frames_processed": processed,
            "frames_dropped": len(st.dropped), "frames_skipped": len(st.skipped),
            "latency_ms_p50": float(np.percentile(lat, 50)) if processed else None,
            "latency_ms_p95": float(np.percentile(lat, 95)) if processed else None,
            "tracking_fps": st.timer.fps("tracking"), "stopped_by": st.live["stopped_by"]}


def _save_stopped_run(dataset: RGBDDataset, run_dir: Path, st: _RunState, e: BaseException) -> None:
    """A run stopping early keeps what it has: a checkpoint when its state is whole (between frames), the
    trajectory of the frames done, the map as gaussians.ply, and run.json saying where, why and how to go on.
    Each step is tried on its own (a full disk may refuse some); the original error is what the caller sees."""
    interrupted = isinstance(e, KeyboardInterrupt)
    why = f"{type(e).__name__}: {e}".rstrip(": ") if str(e) else type(e).__name__
    saved = []

    def attempt(what: str, fn) -> None:
        try:
            fn()
            saved.append(what)
        except Exception as err:  # salvage must not hide the error that stopped the run (Ctrl-C still stops it)
            log.warning("while stopping: %s not saved (%s: %s)", what, type(err).__name__, err)

    if st.tracker is not None:
        if st.consistent is not None and st.consistent > st.start:
            attempt("checkpoint", lambda: st.checkpoint(run_dir, st.consistent))
        note = f" (partial: the run stopped at frame {st.frame})"
        attempt("trajectory", lambda: _write_trajectories(run_dir, st, note))
        if st.mapper is not None and st.mapper.map.n_anchors > 0:
            from ggfslam.mapping.outputs import write_map_ply

            attempt("map", lambda: write_map_ply(st.mapper, run_dir / GAUSSIANS_FILE))
    resume_from = st.checkpointed or 0
    try:
        info = read_json(run_dir / RUN_INFO_FILE)
        info.update(status="interrupted" if interrupted else "failed", stopped_at_frame=st.frame, error=why,
                    saved=saved, resume_from_frame=resume_from)
        write_json(run_dir / RUN_INFO_FILE, info)
    except Exception as err:
        log.warning("while stopping: run.json not updated (%s: %s)", type(err).__name__, err)
    log.error("run stopped at frame %d (%s); saved: %s; `ggfslam run --resume --out %s` continues from frame %d",
              st.frame, why, ", ".join(saved) or "nothing", run_dir, resume_from)


def _map_outputs(config: Config, mapper, tracker, dataset, frames: np.ndarray, poses: np.ndarray, run_dir: Path
                 ) -> dict:
    """Write gaussians.ply (and gaussians_planarity.ply with the field) and mesh.ply fused from the baked file,
    score the file against the map at the keyframes, render every evaluated frame (``frames`` [M] with their
    poses [M, 4, 4]); returns the mapping/rendering metrics."""
    from ggfslam.eval.rendering import ply_fidelity
    from ggfslam.gaussians.explicit import ExplicitGaussians
    from ggfslam.mapping.outputs import write_map_ply, write_planarity_ply, write_rendered_mesh

    g = mapper.bake_gaussians()  # once for the count and both files (view-dependent decoders read every keyframe)
    out = {"mapping": mapper.stats(g)}
    out["mapping"]["ply_gaussians"] = write_map_ply(mapper, run_dir / GAUSSIANS_FILE, g)
    if mapper.ggf is not None:
        write_planarity_ply(mapper, run_dir / PLANARITY_FILE, g)
    baked = ExplicitGaussians.from_ply(run_dir / GAUSSIANS_FILE)  # what a viewer reads, read back as one does
    out["mapping"]["ply_fidelity"] = ply_fidelity(mapper, baked)
    if config.mapping.mesh:
        kf_poses = [T for _, T in sorted(tracker.map.poses().items())]
        try:
            out["mapping"]["mesh_triangles"] = write_rendered_mesh(baked, kf_poses, mapper.intr,
                                                                   config.mapping.mesh_voxel, run_dir / MESH_FILE)
        except GGFSlamError as e:  # an empty map fuses no surface: the run's other outputs still count
            log.warning("mesh.ply not written: %s", e)
    out["rendering"] = rendering_metrics(config, mapper, dataset, frames, poses)
    return out


def rendering_metrics(config: Config, mapper, dataset, frames: np.ndarray, poses: np.ndarray) -> dict:
    """PSNR/SSIM/depth L1 of the map rendered at the estimated pose of every ``eval_stride``-th frame among
    ``frames`` [M] (the frames with a pose, poses [M, 4, 4]; skipped frames have none)."""
    from ggfslam.eval.image import LPIPS
    from ggfslam.eval.rendering import render_metrics
    from ggfslam.mapping.keyframe_store import scaled_intrinsics

    c = config.mapping
    intr = scaled_intrinsics(dataset.camera, c.eval_width)
    by_frame = np.full((len(dataset), 4, 4), np.nan)  # [N, 4, 4]
    by_frame[frames] = poses
    idx = np.asarray(frames)[np.asarray(frames) % c.eval_stride == 0]
    return render_metrics(mapper, dataset, by_frame, idx, intr, LPIPS(config.eval.lpips_weights))


def _trajectory_metrics(est_stamps, est_poses, gt_stamps, gt_poses, config: Config) -> dict:
    """ATE/RPE of a run; a trajectory that cannot be scored (e.g. never left the origin) says why instead."""
    try:
        return trajectory_metrics(est_stamps, est_poses, gt_stamps, gt_poses, config.eval.max_time_diff,
                                  config.eval.rpe_delta)
    except ValueError as e:
        log.warning("trajectory not scored: %s", e)
        return {"ate_rmse_cm": float("nan"), "error": str(e)}


def frames_of_stamps(frame_stamps: np.ndarray, stamps: np.ndarray, path: Path) -> np.ndarray:
    """Frame index [M] of each trajectory timestamp [M] (TUM files keep 6 decimals)."""
    from ggfslam.data.tum import associate

    pose_idx, frames = associate(stamps, frame_stamps, 1e-5)  # pose_idx comes back sorted
    if len(pose_idx) != len(stamps):
        off = np.setdiff1d(np.arange(len(stamps)), pose_idx)
        raise RunDirError(f"{path}: {len(off)} timestamps match no frame of the sequence (first: "
                          f"{stamps[off[0]]:.6f}); was the run made on another selection of frames?")
    return frames


def evaluate(run_dir: str | Path) -> dict:
    """Recompute a run's trajectory (and rendering) metrics from its files, update ``metrics.json`` and return it."""
    run_dir = require_run_dir(run_dir)
    config = load_config(run_dir / CONFIG_FILE)
    traj = run_dir / TRAJECTORY_FILE
    if not traj.is_file():
        raise RunDirError(f"{run_dir}: {TRAJECTORY_FILE} missing (the run did not finish)")
    est_stamps, est_poses = read_tum_trajectory(traj)
    dataset = None
    if (run_dir / GROUNDTRUTH_FILE).is_file():
        gt_stamps, gt_poses = read_tum_trajectory(run_dir / GROUNDTRUTH_FILE)
    else:
        dataset = open_dataset_from_config(config.dataset)
        if dataset.gt_poses is None:
            raise RunDirError(f"{run_dir}: the sequence has no ground truth, so there is no ATE to compute")
        gt_stamps, gt_poses = dataset.timestamps, dataset.gt_poses
    metrics = read_json(run_dir / METRICS_FILE)
    metrics["trajectory"] = _trajectory_metrics(est_stamps, est_poses, gt_stamps, gt_poses, config)
    if config.mapping.enabled:
        _, mapper, _ = load_mapper(run_dir)
        dataset = dataset or open_dataset_from_config(config.dataset)
        frames = frames_of_stamps(np.asarray(dataset.timestamps), est_stamps, traj)
        metrics["rendering"] = rendering_metrics(config, mapper, dataset, frames, est_poses)
    write_json(run_dir / METRICS_FILE, metrics)
    return metrics
