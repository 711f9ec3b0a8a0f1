"""GCGR in the SLAM system: each keyframe's GCGR factors (``factors/gcgr.py``) built from the Gaussian map.

Local bundle adjustment asks ``window_factors`` (a BA in this process) or ``window_models`` (whose first-order
models go to the solver process) for the keyframes it optimizes. The source keeps each new
keyframe's sensor depth at the factors' resolution (``gcgr.width``, by default the training resolution; older
keyframes fall back to the mapper's keyframe store) and caches one ``GCGRModel`` per keyframe, from two sources:
- the mapper's training renders (the source is the mapper's ``view_sink``): every ``gcgr.harvest_every`` steps on a
  keyframe, the render the step made anyway becomes the keyframe's model, at no render cost. The first
  ``harvest_every`` steps after a keyframe's first step are skipped: its newly seeded anchors only echo its own
  depth then;
- its own renders, at most ``gcgr.renders_per_ba`` per local BA (by default none where training renders serve: the
  new keyframe's map then only echoes the depth it has just seeded; the newest keyframe first, then keyframes whose
  model is missing or older than ``gcgr.max_age`` steps). In sequential mode BA runs inside tracking, so these are
  what GCGR costs the tracking rate.
A model re-renders by itself when the optimizer linearizes it past the relinearization threshold
(``gcgr.relinearize: render``), or is left out of BAs from there until training hands over a fresh view (``drop``).
``refine_frame`` is the per-frame GCGR pose refinement of tracked frames.
The refined keyframe poses reach the mapper and the frontend through the SLAM map, like every BA result.
"""
from __future__ import annotations

import threading
import time
from collections import OrderedDict

import gtsam
import numpy as np
import torch
from gtsam.symbol_shorthand import X

from factors.gcgr import KINDS, MIN_PIXELS, GCGRModel, MapView, SensorView
from factors.gcgr_linear import labelled_factors
from ggfslam.backend.local_ba import IndeterminateSystem, optimize_lm
from ggfslam.config import GCGRConfig
from ggfslam.errors import ConfigError
from ggfslam.mapping.keyframe_store import resize_depth, scaled_intrinsics

CACHE = 48  # keyframes whose sensor views and models are kept (a few BA windows)


class GCGRSource:
    """GCGR factors and per-frame refinement from a ``Mapper`` (see the module docstring)."""

    def __init__(self, mapper, camera, cfg: GCGRConfig, per_frame: bool = False):
        self.mapper, self.cfg, self.per_frame = mapper, cfg, per_frame
        self.intr = mapper.intr if cfg.width == 0 else scaled_intrinsics(camera, cfg.width)
        # training renders serve only at the training resolution
        self.harvest = cfg.harvest_every > 0 and self.intr == mapper.intr and not cfg.exclude_own_anchors
        if not self.harvest and self.renders_per_ba == 0 and not per_frame:
            raise ConfigError("gcgr.renders_per_ba is 0 and the training renders cannot serve (gcgr.harvest_every is 0, "
                              "gcgr.width differs from mapping.train_width, or gcgr.exclude_own_anchors is true): GCGR "
                              "would have no view of the map")
        self._first_step: dict[int, int] = {}  # keyframe -> map iteration of its first training step
        self._retired: set[int] = set()  # keyframes culled from the graph: no BA asks for their factors again
        self._sensors: OrderedDict[int, SensorView] = OrderedDict()
        self._models: OrderedDict[int, tuple[GCGRModel, int]] = OrderedDict()  # id -> (model, map iteration)
        self._lock = threading.Lock()  # tracking adds keyframes while the backend thread builds factors
        self.models_built = 0
        self.models_harvested = 0
        self.factors_added = 0
        self.pixels_total = 0
        self.renders = 0
        self.render_seconds = 0.0
        self.frames_refined = 0
        self.refine_failed = 0  # per-frame refinements whose system was indeterminate (pose kept)
        self.refine_seconds = 0.0
        self.models_stale = 0  # models left out of a BA: past the relinearization threshold (relinearize: drop)
        self.ba_relinearized = 0  # BAs solved in the solver process that rendered moved keyframes and solved again

    @property
    def renders_per_ba(self) -> int:
        """Renders one local BA may make: ``gcgr.renders_per_ba``, by default none where training renders serve."""
        r = self.cfg.renders_per_ba
        return r if r is not None else int(not self.harvest)

    # --- inputs --------------------------------------------------------------------------------------
    def add_keyframe(self, kf_id: int, depth: np.ndarray) -> None:
        """Keep a new keyframe's sensor depth [H, W] (m) at the factors' resolution."""
        view = SensorView.from_depth(resize_depth(depth, self.intr), self.intr)
        with self._lock:
            self._sensors[kf_id] = view
            while len(self._sensors) > CACHE:
                self._sensors.popitem(last=False)

    def remove_keyframe(self, kf_id: int) -> None:
        """Forget a keyframe culled from the graph (its sensor view, its model; its training renders are refused)."""
        with self._lock:
            self._retired.add(kf_id)
            self._sensors.pop(kf_id, None)
            self._models.pop(kf_id, None)
            self._first_step.pop(kf_id, None)

    def sensor(self, kf_id: int) -> SensorView | None:
        """The keyframe's sensor view: kept since insertion, else from the mapper's store, else None."""
        with self._lock:
            if kf_id in self._sensors:
                return self._sensors[kf_id]
        if kf_id not in self.mapper.store:
            return None
        return SensorView.from_depth(resize_depth(self.mapper.store.get(kf_id).depth, self.intr), self.intr)

    def ready(self) -> bool:
        """Whether the map has been trained at all (an empty map says nothing about poses)."""
        return self.mapper.map.n_anchors > 0 and self.mapper.iteration > 0

    def render(self, T_wc: np.ndarray, kf_id: int | None = None) -> MapView:
        """The map rendered at T_wc [4, 4] at the factors' resolution for keyframe ``kf_id`` (without the anchors
        it seeded when ``gcgr.exclude_own_anchors``)."""
        t0 = time.perf_counter()
        without = kf_id if self.cfg.exclude_own_anchors else None
        view = MapView.from_render(self.mapper.render(T_wc, self.intr, without_kf=without))
        self.renders += 1
        self.render_seconds += time.perf_counter() - t0
        return view

    # --- factors -------------------------------------------------------------------------------------
    def cached_models(self) -> dict[int, tuple[GCGRModel, int]]:
        """Keyframe -> (model, map iteration of its render) of every cached model: the factors local BA uses."""
        with self._lock:
            return dict(self._models)

    def _cached(self, kf_id: int) -> tuple[GCGRModel, int] | None:
        """The keyframe's cached (model, map iteration of its render), or None."""
        with self._lock:
            return self._models.get(kf_id)

    def build(self, kf_id: int, T_wc: np.ndarray, view: MapView | None = None, iteration: int | None = None
               ) -> GCGRModel | None:
        """A new model of the keyframe from ``view`` (made at T_wc [4, 4] before map step ``iteration``), or from a
        render at T_wc; it replaces the cached one. None without sensor depth."""
        sensor = self.sensor(kf_id)
        if sensor is None:
            return None
        it = self.mapper.iteration if iteration is None else iteration
        m = GCGRModel(kf_id, lambda T: self.render(T, kf_id), sensor, T_wc, self.cfg, view=view,
                      relinearize=self.cfg.relinearize == "render")
        self.models_built += 1
        with self._lock:
            self._models[kf_id] = (m, it)
            self._models.move_to_end(kf_id)
            while len(self._models) > CACHE:
                self._models.popitem(last=False)
        return m

    # --- the mapper's view sink ---------------------------------------------------------------------
    def wants(self, kf_id: int, iteration: int) -> bool:
        """Whether the mapper's training step ``iteration`` on ``kf_id`` should hand its render over."""
        if not self.harvest:
            return False
        with self._lock:
            if kf_id in self._retired:
                return False
            first = self._first_step.setdefault(kf_id, iteration)
            cached = self._models.get(kf_id)
        if iteration - first < self.cfg.harvest_every:
            return False
        return cached is None or iteration - cached[1] >= self.cfg.harvest_every

    @torch.no_grad()
    def offer(self, kf_id: int, T_wc: np.ndarray, iteration: int, out) -> None:
        """A training render of ``kf_id`` at T_wc [4, 4] (``RenderOutput``) becomes the keyframe's model."""
        if self.build(kf_id, T_wc, MapView.from_render(out), iteration) is not None:
            self.models_harvested += 1

    def model(self, kf_id: int, T_wc: np.ndarray) -> GCGRModel | None:
        """The keyframe's GCGR model at pose T_wc: the cached one while its render is younger than
        ``gcgr.max_age`` map steps, else a new render; None without a map or sensor depth."""
        if not self.ready():
            return None
        cached = self._cached(kf_id)
        if cached is not None and self.mapper.iteration - cached[1] < self.cfg.max_age:
            return cached[0]
        return self.build(kf_id, T_wc)

    def window_models(self, poses: dict[int, np.ndarray]) -> list[GCGRModel]:
        """The GCGR models of the keyframes in ``poses`` (id -> T_wc [4, 4]) for one local BA, each with factors.

        At most ``gcgr.renders_per_ba`` new renders for keyframes without a model (the newest first) or whose
        model is older than ``gcgr.max_age`` steps (stalest first); the others use their cached model (however
        old) or get none this time. With ``gcgr.relinearize: drop``, models whose keyframe has moved past the
        relinearization threshold since their render are left out."""
        if not self.ready():
            return []
        it = self.mapper.iteration
        cached = {k: self._cached(k) for k in poses}
        age = {k: None if c is None else it - c[1] for k, c in cached.items()}
        newest = max(poses, default=None)
        order = sorted(poses, key=lambda k: (k != newest, age[k] is not None, -(age[k] or 0)))
        budget = self.renders_per_ba
        out = []
        for k in order:
            wanted = age[k] is None or age[k] >= self.cfg.max_age
            m = self.build(k, poses[k]) if wanted and budget > 0 else None
            budget -= m is not None
            if m is None and cached[k] is not None:
                m = cached[k][0]
            if m is None or len(m) < MIN_PIXELS:
                continue
            if not m.relinearizes and m.moved_past(poses[k]):  # gcgr.relinearize: drop
                self.models_stale += 1
                continue
            out.append(m)
            self.factors_added += len(KINDS)
            self.pixels_total += len(m)
        return out

    def window_factors(self, poses: dict[int, np.ndarray]) -> list[tuple[int, str, gtsam.CustomFactor]]:
        """(keyframe, kind, factor) of the GCGR factors of ``window_models(poses)``, for a BA in this process."""
        return labelled_factors(self.window_models(poses))

    def refine_frame(self, T_wc: np.ndarray, depth: np.ndarray, iterations: int = 5) -> np.ndarray:
        """Per-frame GCGR: the tracked pose T_wc [4, 4] refined against the map under a prior on it."""
        if not self.ready():
            return T_wc
        t0 = time.perf_counter()
        sensor = SensorView.from_depth(resize_depth(depth, self.intr), self.intr)
        m = GCGRModel(0, self.render, sensor, T_wc, self.cfg)
        fs = m.factors()
        if not fs:
            return T_wc
        s_rot, s_trans = self.cfg.per_frame_sigmas
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(T_wc), gtsam.noiseModel.Diagonal.Sigmas(
            np.array([s_rot] * 3 + [s_trans] * 3))))
        for f in fs.values():
            graph.add(f)
        values = gtsam.Values()
        values.insert(X(0), gtsam.Pose3(T_wc))
        try:
            result = optimize_lm(graph, values, iterations)
        except IndeterminateSystem:  # keep the tracked pose (counted in refine_failed)
            self.refine_failed += 1
            return T_wc
        T = result.atPose3(X(0)).matrix()
        self.frames_refined += 1
        self.refine_seconds += time.perf_counter() - t0
        return T

    def unused_warning(self) -> str | None:
        """Why GCGR did nothing in a run, when it made no factor and refined no frame (None when it did something)."""
        if self.factors_added or self.frames_refined:
            return None
        return (f"gcgr.enabled, but GCGR made no factor in any bundle adjustment: {self.models_built} keyframe models, "
                f"none in time for a BA (the mapper trained {self.mapper.iteration} steps over "
                f"{len(self.mapper.store)} keyframes; a keyframe's training render becomes its model only after "
                f"gcgr.harvest_every = {self.cfg.harvest_every} steps on it). Lower gcgr.harvest_every or set "
                f"gcgr.renders_per_ba >= 1 to give BAs models, or leave gcgr off")

    def summary(self) -> dict:
        """GCGR figures for metrics.json (``backend.gcgr``)."""
        return {"models": self.models_built, "models_from_training": self.models_harvested, "factors": self.factors_added,
                "pixels_mean": self.pixels_total / max(self.factors_added // 2, 1),
                "renders": self.renders, "render_ms_mean": 1000 * self.render_seconds / max(self.renders, 1),
                "models_stale": self.models_stale, "ba_relinearized": self.ba_relinearized,
                "frames_refined": self.frames_refined, "refine_failed": self.refine_failed,
                "refine_ms_mean": 1000 * self.refine_seconds / max(self.frames_refined, 1)}
