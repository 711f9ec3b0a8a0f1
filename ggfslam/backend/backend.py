"""The backend: owns the map, runs local bundle adjustment, landmark culling and loop closure per keyframe.

In sequential mode every keyframe is processed before tracking continues (repeatable runs); in concurrent mode a
worker thread takes keyframes from a queue and tracking never waits for it, and with ``backend.solver: process``
the thread hands each bundle adjustment to a child process (GTSAM holds the GIL while it optimizes).
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from ggfslam.backend.fusion import fuse_neighbours
from ggfslam.backend.plane_map import associate_planes
from ggfslam.backend.local_ba import BAStats, local_bundle_adjustment
from ggfslam.backend.slam_map import KeyFrame, SlamMap
from ggfslam.config import BackendConfig, TrackingConfig
from ggfslam.data.types import Camera

log = logging.getLogger("ggfslam.backend")


@dataclass
class BackendStats:
    """Counters and timings of the backend over a run."""

    keyframes: int = 0
    ba_runs: int = 0
    ba_seconds: list[float] = field(default_factory=list)
    landmarks_culled: int = 0
    outliers_removed: int = 0
    fused_observations: int = 0
    fused_landmarks: int = 0
    loops: list[dict] = field(default_factory=list)
    # plain defaults (class attributes), so trackers pickled before these counters existed still resume
    ba_failed: int = 0  # bundle adjustments whose system was indeterminate (the map kept its estimate)
    ba_failure: str = ""  # the first such BA, logged once
    global_ba_runs: int = 0  # global BAs (after loop closures)
    global_ba_seconds: float = 0.0  # their total time
    final_ba_done: bool = False  # the final global BA ran (finish() may be called again)
    final_ba_seconds: float = 0.0
    solved_in_process: int = 0  # bundle adjustments the solver process solved (backend.solver: process)
    solver_fallback: str = ""  # why later ones were solved in the tracking process ("": none were)
    keyframes_culled: int = 0  # keyframes retired from the graph (backend.keyframe_culling)


class Backend:
    """Processes keyframes from the frontend; everyone asks it (its map) for poses and landmarks."""

    def __init__(self, camera: Camera, tcfg: TrackingConfig, bcfg: BackendConfig):
        self.camera, self.tcfg, self.bcfg = camera, tcfg, bcfg
        self.map = SlamMap()
        self.stats = BackendStats()
        self.loop_detector = None
        if bcfg.loop_closure:
            from ggfslam.backend.loop_closure import LoopDetector

            self.loop_detector = LoopDetector(camera, feature_store=self.map.feature_store)
        self.gcgr = None  # a GCGRSource once the map is attached (attach_gcgr)
        self._queue: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._solver = None
        self._plane_depth: dict[int, np.ndarray] = {}  # keyframe id -> depth [H, W] whose planes are not detected yet
        self._start_worker()

    def _start_worker(self) -> None:
        if not self.bcfg.concurrent:
            return
        if self.bcfg.solver == "process":
            from ggfslam.backend.solver_process import SolverProcess

            self._solver = SolverProcess()
        self._queue = queue.Queue()
        self._thread = threading.Thread(target=self._worker, name="ggfslam-backend", daemon=True)
        self._thread.start()

    def __getstate__(self) -> dict:
        """Checkpoints: the queue must be drained first (``drain()``); the worker thread is not pickled."""
        if self._queue is not None and self._queue.unfinished_tasks:
            raise RuntimeError("backend: drain() the keyframe queue before pickling")
        state = self.__dict__.copy()
        state.update(_queue=None, _thread=None, _error=None, _solver=None, gcgr=None)  # the map is saved by the mapper
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.__dict__.setdefault("_plane_depth", {})  # checkpoints written before planes were detected here
        if self.loop_detector is not None and getattr(self.loop_detector, "feature_store", None) is None:
            self.loop_detector.feature_store = self.map.feature_store  # checkpoints from before the feature store
        self._solver = None
        self._start_worker()

    def drain(self) -> None:
        """Wait until every queued keyframe is processed (the worker keeps running)."""
        while self._queue is not None and self._queue.unfinished_tasks and self._thread.is_alive():
            time.sleep(0.005)  # not queue.join(): a worker that failed leaves tasks undone forever
        if self._error is not None:
            raise RuntimeError("backend worker failed") from self._error

    def attach_gcgr(self, source) -> None:
        """Give local bundle adjustment the Gaussian map's GCGR factors (a ``GCGRSource``; None detaches)."""
        self.gcgr = source

    # --- keyframes in ---------------------------------------------------------------------------
    def insert_keyframe(self, kf: KeyFrame, depth: np.ndarray | None = None) -> None:
        """Hand a new keyframe (already in the map) and its depth image [H, W] (m, for GCGR) to the backend."""
        self.stats.keyframes += 1
        if self.gcgr is not None and depth is not None:
            self.gcgr.add_keyframe(kf.id, depth)
        if self.bcfg.planes and depth is not None and "planes" not in kf.meta:
            self._plane_depth[kf.id] = depth  # detected by _process: off the tracking thread in concurrent mode
        if self._queue is not None:
            if self._error is not None:
                raise RuntimeError("backend worker failed") from self._error
            self._queue.put(kf.id)
        else:
            self._process(kf.id)

    def _worker(self) -> None:
        import numba

        # GCGR renders here: one numba thread, so tracking keeps a core (numba's thread budget is per thread)
        numba.set_num_threads(1)
        while True:
            kf_id = self._queue.get()
            try:
                if kf_id is None:
                    return
                self._process(kf_id)
            except BaseException as e:  # surfaced to the tracking thread at the next keyframe / finish
                self._error = e
                log.exception("backend worker failed")
                return
            finally:
                self._queue.task_done()

    def _process(self, kf_id: int) -> None:
        depth = self._plane_depth.pop(kf_id, None)
        if depth is not None and kf_id in self.map.keyframes:
            from ggfslam.frontend.planes import detect_planes

            self.map.keyframes[kf_id].meta["planes"] = detect_planes(depth, self.camera)
        self._cull(kf_id)
        if self.bcfg.fusion:
            neighbours = self.map.local_keyframes(kf_id, self.bcfg.fusion_neighbours, min_shared=1,
                                                  temporal=self.bcfg.temporal_window)
            added, merged = fuse_neighbours(self.map, kf_id, neighbours[1:], self.camera, self.tcfg,
                                            self.bcfg.fusion_radius, self.bcfg.fusion_max_distance)
            self.stats.fused_observations += added
            self.stats.fused_landmarks += merged
        if self.bcfg.planes:
            associate_planes(self.map, kf_id, self.bcfg)
        stats: BAStats | None = local_bundle_adjustment(self.map, kf_id, self.camera, self.tcfg, self.bcfg,
                                                           self.gcgr, solver=self._solver)
        if stats is not None and not self._failed(stats, "local BA", kf_id):
            self.stats.ba_runs += 1
            self.stats.ba_seconds.append(stats.seconds)
            self.stats.outliers_removed += stats.outliers
        if self.loop_detector is not None:
            self._detect_loop(self.map.keyframes[kf_id])
        if self.bcfg.keyframe_culling:
            self._cull_keyframes(kf_id)

    def _cull_keyframes(self, kf_id: int) -> None:
        """Retire the redundant keyframes covisible with ``kf_id`` (``backend.keyframe_culling``) from the map, the
        loop detector and the GCGR source."""
        from ggfslam.backend.keyframe_culling import cull_keyframes

        retired = cull_keyframes(self.map, kf_id, self.bcfg.culling_redundancy, self.bcfg.culling_observers)
        for k in retired:
            if self.loop_detector is not None:
                self.loop_detector.remove_keyframe(k)
            if self.gcgr is not None:
                self.gcgr.remove_keyframe(k)
        self.stats.keyframes_culled += len(retired)

    def _detect_loop(self, kf: KeyFrame) -> None:
        from ggfslam.backend.loop_correction import close_loop

        with self.map.lock:
            covisible = set(self.map.covisibility(kf.id))
            T = kf.T_wc.copy()
        f = kf.features
        planes = [p.coefficients for p in kf.meta.get("planes", [])]
        loop = self.loop_detector.add_keyframe(kf.id, f.uv, f.descriptors, f.points_cam, T, covisible, planes)
        if loop is None:
            return
        t0 = time.perf_counter()
        new = close_loop(self.map, loop, **({"solve": self._solver.pose_graph} if self._solver is not None else {}))
        self.loop_detector.update_poses(new)
        self.stats.loops.append({"query": loop.query_id, "match": loop.match_id, "inliers": loop.inliers,
                                 "seconds": time.perf_counter() - t0})
        log.info("loop closed: keyframe %d -> %d (%d inliers)", loop.query_id, loop.match_id, loop.inliers)
        if self.bcfg.global_ba and self.bcfg.fusion:
            self._global_ba()

    def _global_ba(self, final: bool = False) -> None:
        """Every keyframe and landmark bundle-adjusted together: after a loop closure (``backend.global_ba``), or
        with ``final`` at the end (``backend.final_global_ba``, with the GCGR factors when GCGR is on)."""
        from ggfslam.backend.local_ba import global_bundle_adjustment

        what = "final global BA" if final else "global BA"
        stats = global_bundle_adjustment(self.map, self.camera, self.tcfg, self.bcfg, self.gcgr if final else None,
                                         solver=self._solver)
        if stats is None or self._failed(stats, what, max(self.map.keyframes)):
            return
        if final:
            self.stats.final_ba_seconds = stats.seconds
        else:
            self.stats.global_ba_runs += 1
            self.stats.global_ba_seconds += stats.seconds
        self.stats.outliers_removed += stats.outliers
        if self.loop_detector is not None:
            self.loop_detector.update_poses(self.map.graph_poses())
        log.info("%s: %d keyframes, %d landmarks, %d GCGR factors, error %.0f -> %.0f (%.1f s)", what, stats.keyframes,
                 stats.landmarks, stats.gcgr_factors, stats.error_before, stats.error_after, stats.seconds)

    def _failed(self, stats: BAStats, what: str, kf_id: int) -> bool:
        """Whether the bundle adjustment ``what`` at keyframe ``kf_id`` did not run; such BAs are counted
        (backend.ba_failed) and the first one is logged."""
        if not stats.failed:
            return False
        self.stats.ba_failed += 1
        if not self.stats.ba_failure:
            self.stats.ba_failure = f"keyframe {kf_id}: {stats.failed}"
            log.warning("%s skipped at %s (counted as backend.ba_failed; further ones are not logged)", what,
                        self.stats.ba_failure)
        return True

    def place_candidates(self, descriptors, top_k: int) -> list[int]:
        """Keyframes that look most like a set of ORB descriptors (for relocalization), best first."""
        if self.loop_detector is None:
            return []
        bow = self.loop_detector.vocabulary.transform(descriptors)
        with self.map.lock:
            return [k for k, _ in self.loop_detector.database.query(bow, top_k=top_k) if k in self.map.keyframes]

    def _cull(self, kf_id: int) -> None:
        """Drop landmarks that later keyframes do not confirm (ORB-SLAM's recent map point culling)."""
        m = self.map
        with m.lock:
            ids = m.alive_ids()
            if len(ids) == 0:
                return
            age = kf_id - m.created_by[ids]  # keyframes since creation
            n_obs = np.array([len(m.observations[i]) for i in ids])
            found_ratio = m.n_found[ids] / np.maximum(m.n_visible[ids], 1)
            bad = ((age >= 2) & (found_ratio < 0.25)) | ((age >= 3) & (n_obs < self.bcfg.min_observations))
            for lm in ids[bad]:
                m.remove_landmark(int(lm))
            self.stats.landmarks_culled += int(bad.sum())

    def finish(self) -> None:
        """Wait for queued keyframes to be processed and stop the worker; then, once, the final global BA
        (``backend.final_global_ba``); then stop the solver process."""
        try:
            if self._queue is not None and self._thread is not None and self._thread.is_alive():
                self._queue.put(None)
                self._thread.join()
            if self._error is not None:
                raise RuntimeError("backend worker failed") from self._error
            if self.bcfg.final_global_ba and self.bcfg.fusion and not self.stats.final_ba_done:
                self.stats.final_ba_done = True
                self._global_ba(final=True)
        finally:
            self.close()

    def close(self) -> None:
        """Stop the solver process, if any (``finish`` does; a run that stops early calls it too)."""
        if self._solver is not None:
            self.stats.solved_in_process += self._solver.solved
            self.stats.solver_fallback = self._solver.fallback
            self._solver.close()
            self._solver = None

    def summary(self) -> dict:
        """Backend figures for metrics.json."""
        s = self.stats
        return {
            "keyframes": s.keyframes, "keyframes_culled": s.keyframes_culled, "landmarks": int(self.map.alive.sum()),
            "ba_runs": s.ba_runs,
            "ba_failed": s.ba_failed, **({"ba_first_failure": s.ba_failure} if s.ba_failure else {}),
            "ba_ms_mean": 1000 * float(np.mean(s.ba_seconds)) if s.ba_seconds else 0.0,
            "ba_ms_max": 1000 * float(np.max(s.ba_seconds)) if s.ba_seconds else 0.0,
            "landmarks_culled": s.landmarks_culled, "outliers_removed": s.outliers_removed,
            "fused_observations": s.fused_observations, "fused_landmarks": s.fused_landmarks,
            "loops": len(s.loops), "global_ba_runs": s.global_ba_runs, "final_ba_ms": 1000 * s.final_ba_seconds,
            "global_ba_ms_mean": 1000 * s.global_ba_seconds / max(s.global_ba_runs, 1),
            "feature_reads": self.map.feature_store.reads,  # keyframes' features read back from disk (feature_cache)
            **({"gcgr": self.gcgr.summary()} if self.gcgr is not None else {}),
            **({"solved_in_process": s.solved_in_process} if self.bcfg.concurrent and self.bcfg.solver == "process"
               else {}),
            **({"solver_fallback": s.solver_fallback} if s.solver_fallback else {}),
        }
