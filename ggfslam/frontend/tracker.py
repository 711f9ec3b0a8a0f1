"""The feature frontend: ORB tracking against the local map, keyframe selection, relocalization.

Per frame: predict the pose with a constant-velocity model, match the previous frame's map points by
projection (else the reference keyframe's by descriptor + PnP RANSAC), refine the pose (motion-only, robust),
then search the local map (landmarks of covisible keyframes) and refine again. When tracking fails the frame
is LOST and the next frames try to relocalize against the keyframes. Every frame's pose is stored relative
to its reference keyframe, so backend corrections (BA, loop closure) move the whole trajectory.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ggfslam.backend.backend import Backend
from ggfslam.backend.fusion import project_landmarks
from ggfslam.backend.slam_map import KeyFrame
from ggfslam.config import TrackingConfig
from ggfslam.data.types import Camera, Frame
from ggfslam.frontend.dense_odometry import DenseOdometry
from ggfslam.frontend.features import Features, OrbExtractor
from ggfslam.frontend.matching import match_projected, match_ratio
from ggfslam.frontend.pose_refine import refine_pose
from ggfslam.frontend.sharpness import sharpness
from ggfslam.frontend.types import TrackingState, TrackResult
from ggfslam.geometry.pnp import pnp_ransac
from ggfslam.geometry.se3 import invert, rotation_angle


@dataclass
class FrameRecord:
    """What the final trajectory needs of a frame: its reference keyframe and pose relative to it."""

    index: int
    timestamp: float
    ref_kf: int
    T_ref_cur: np.ndarray  # [4, 4]
    state: TrackingState


class OrbTracker:
    """ORB frontend feeding a GTSAM backend (see module docstring)."""

    name = "orb"

    def __init__(self, camera: Camera, cfg: TrackingConfig, backend: Backend, seed: int = 0):
        self.camera, self.cfg, self.backend = camera, cfg, backend
        self.map = backend.map
        self.extractor = OrbExtractor(camera, cfg, seed)  # the seed draws the keypoint jitter only (off by default)
        self.level_scale = cfg.scale_factor ** np.arange(cfg.n_levels)  # [L]
        self.state = TrackingState.NOT_INITIALIZED
        self.records: list[FrameRecord] = []
        self.velocity: np.ndarray | None = None  # inv(T_wc_prev) @ T_wc_last
        self.last_T: np.ndarray | None = None
        # a new keyframe's pose relative to itself as tracked, before bundle adjustment moved it (its record holds
        # the identity): the next frame's motion model starts from the tracked pose
        self.tracked_rel: tuple[int, np.ndarray] | None = None
        self.last_features: Features | None = None
        self.last_lm: np.ndarray | None = None  # [N] landmark per keypoint of the last frame (-1 none)
        self.ref_kf: int = -1
        self.last_kf_frame = -1
        self.next_kf_id = 0
        self.dense = DenseOdometry(camera, cfg) if cfg.dense_fallback else None
        self.last_frame: Frame | None = None
        self.recent_sharpness: list[float] = []  # of the last 2 * keyframe_max_frames frames, this one last
        self.held_still = 0  # frames whose keyframe due by time was not made: the camera was at a known view
        self.rests_at: int | None = None  # the keyframe whose view the input's last frame had (promote_last_frame)
        self.rested_frame = -1  # the last frame promote_last_frame found at rest (a resumed run asks again)

    def __setstate__(self, state: dict) -> None:  # checkpoints written before an attribute existed still resume
        state.setdefault("recent_sharpness", [])
        state.setdefault("held_still", 0)
        state.setdefault("rests_at", None)
        state.setdefault("rested_frame", -1)
        self.__dict__.update(state)

    # --- geometry helpers ---------------------------------------------------------------------------
    def _sigma(self, octave: np.ndarray) -> np.ndarray:
        return self.cfg.pixel_sigma * self.level_scale[octave]

    def _refine(self, T: np.ndarray, F: Features, lm: np.ndarray, kp: np.ndarray):
        """Refine pose T from matches (landmark ids lm [K], keypoint indices kp [K]); returns (T, inlier mask)."""
        with self.map.lock:
            X = self.map.positions[lm].copy()
        res = refine_pose(T, X, F.uv[kp], F.depth[kp], self._sigma(F.octave[kp]), self.camera,
                          self.cfg.virtual_baseline)
        return res.T_wc, res.inliers

    def _project(self, T_wc: np.ndarray, lm: np.ndarray):
        """Pixels [K, 2], predicted levels [K] and in-view mask [K] of landmarks seen from T_wc."""
        with self.map.lock:
            uv, _, level, inside = project_landmarks(self.map, lm, T_wc, self.camera, self.cfg.scale_factor,
                                                     self.cfg.n_levels)
        return uv, level, inside

    def _search(self, T: np.ndarray, F: Features, lm: np.ndarray, radius: float, taken: np.ndarray | None = None):
        """Match landmarks lm to keypoints by projection from T; returns (landmark ids, keypoint indices, in view)."""
        uv, level, inside = self._project(T, lm)
        lm_in = lm[inside]
        with self.map.lock:
            desc = self.map.descriptors[lm_in]
        pairs = match_projected(uv[inside], desc, level[inside], F.uv, F.descriptors, F.octave, radius,
                                self.level_scale, self.cfg.match_max_distance, self.cfg.match_ratio, taken)
        return lm_in[pairs[:, 0]], pairs[:, 1], lm_in

    # --- tracking stages ----------------------------------------------------------------------------
    def _track_motion_model(self, F: Features):
        pred = self.last_T @ self.velocity
        lm_all = self.last_lm[self.last_lm >= 0]
        with self.map.lock:
            lm_all = lm_all[self.map.alive[lm_all]]
        lm, kp, _ = self._search(pred, F, lm_all, self.cfg.match_radius)
        if len(lm) < 2 * self.cfg.min_matches:  # fast motion or a jerk: widen the window
            lm, kp, _ = self._search(pred, F, lm_all, 2.5 * self.cfg.match_radius)
        if len(lm) < self.cfg.min_matches:
            return None
        T, inl = self._refine(pred, F, lm, kp)
        if inl.sum() < self.cfg.min_matches:
            return None
        return T, lm[inl], kp[inl]

    def _pnp(self, F: Features, kf: KeyFrame):
        """Pose of the frame from descriptor matches to the landmarks of keyframe ``kf`` (PnP RANSAC + refine)."""
        has = np.nonzero(kf.landmark_ids >= 0)[0]
        if len(has) < self.cfg.min_matches or len(F) < self.cfg.min_matches:
            return None
        pairs = match_ratio(F.descriptors, kf.features.descriptors[has], self.cfg.match_max_distance, 0.8)
        if len(pairs) < self.cfg.min_matches:
            return None
        kp = pairs[:, 0]
        lm = kf.landmark_ids[has[pairs[:, 1]]]
        with self.map.lock:
            ok_lm = self.map.alive[lm]
            kp, lm = kp[ok_lm], lm[ok_lm]
            X = self.map.positions[lm].copy()
        if len(lm) < self.cfg.min_matches:
            return None
        found = pnp_ransac(X, F.uv[kp], self.camera.K, iterations=200, reprojection_px=4.0)
        if found is None or len(found[1]) < self.cfg.min_matches:
            return None
        T0, inl = found
        T, good = self._refine(T0, F, lm[inl], kp[inl])
        if good.sum() < self.cfg.min_matches:
            return None
        return T, lm[inl][good], kp[inl][good]

    def _pnp_last_frame(self, F: Features) -> np.ndarray | None:
        """Pose [4, 4] from descriptor matches to the previous frame's keypoints with depth (PnP RANSAC), or None.

        With wide baselines in low texture, few map points survive to be matched, while the previous frame's
        own depth-backed keypoints are many: a pose from them lets the local-map search start near the truth."""
        last = self.last_features
        if last is None or self.last_T is None or len(F) < 6:
            return None
        has = np.nonzero(last.has_depth)[0]
        pairs = match_ratio(F.descriptors, last.descriptors[has], self.cfg.match_max_distance, self.cfg.match_ratio)
        need = max(6, self.cfg.min_matches // 2)
        if len(pairs) < need:
            return None
        X = last.points_cam[has[pairs[:, 1]]] @ self.last_T[:3, :3].T + self.last_T[:3, 3]  # [K, 3] world
        found = pnp_ransac(X, F.uv[pairs[:, 0]], self.camera.K, iterations=500, reprojection_px=3.0)
        if found is None or len(found[1]) < need:
            return None
        return found[0]

    def _track_local_map(self, F: Features, T: np.ndarray, lm: np.ndarray, kp: np.ndarray):
        """Add matches from the local map (landmarks of keyframes covisible with the current matches), refine."""
        with self.map.lock:
            counts = self.map.observer_counts(lm)
            local = [k for k, _ in counts.most_common(self.cfg.local_map_keyframes)]
            if self.ref_kf >= 0 and self.ref_kf not in local:
                local.append(self.ref_kf)
            if local:
                for k, _ in self.map.covisibility(local[0]).most_common(self.cfg.local_map_keyframes // 2):
                    if k not in local:
                        local.append(k)
            cand = self.map.landmarks_of(local)
        cand = cand[~np.isin(cand, lm)]  # keeps landmarks_of's order: oldest first
        taken = np.zeros(len(F), dtype=bool)
        taken[kp] = True
        lm2, kp2, seen = self._search(T, F, cand, self.cfg.match_radius, taken)
        with self.map.lock:
            self.map.n_visible[seen] += 1
            self.map.n_visible[lm] += 1
        lm_all, kp_all = np.concatenate([lm, lm2]), np.concatenate([kp, kp2])
        T, inl = self._refine(T, F, lm_all, kp_all)
        lm_all, kp_all = lm_all[inl], kp_all[inl]
        with self.map.lock:
            self.map.n_found[lm_all] += 1
        if self.ref_kf >= 0 and local:
            self._set_reference(local[0] if counts else self.ref_kf)  # the keyframe sharing most points with it
        return T, lm_all, kp_all

    def _relocalize(self, F: Features):
        n = self.cfg.relocalization_candidates
        candidates = self.backend.place_candidates(F.descriptors, n) if len(F) else []
        # the newest keyframes too: right after a blackout the camera is usually still near them
        for k in sorted(self.map.keyframes)[::-1][:n]:
            if k not in candidates:
                candidates.append(k)
        for k in candidates:
            kf = self.map.keyframes.get(k)  # the backend may have culled it since
            res = None if kf is None else self._pnp(F, kf)
            if res is not None:
                self._set_reference(k)
                return res
        return None

    def _set_reference(self, kf_id: int) -> None:
        """Make keyframe ``kf_id`` (or, culled meanwhile, the one it rides on) the reference keyframe, which the
        backend does not cull while it is one."""
        with self.map.lock:
            self.ref_kf = self.map.living(kf_id)
            self.map.tracking_ref = self.ref_kf

    # --- keyframes ------------------------------------------------------------------------------------
    def _dense_step(self, frame: Frame, guess: np.ndarray | None = None) -> np.ndarray | None:
        """Pose of the frame by dense RGB-D odometry from the previous frame, or None if it fails.

        Dense alignment converges only near the answer: it starts from a (weak) feature estimate ``guess``
        [4, 4] when there is one, else from no motion."""
        if self.last_frame is None:
            return None
        init = np.eye(4) if guess is None else invert(self.last_T) @ guess
        ok, T_prev_cur, fitness = self.dense.relative(self.dense.rgbd(frame), self.dense.rgbd(self.last_frame), init)
        if not ok or fitness < 0.3:  # below this overlap the alignment is not trusted
            return None
        return self.last_T @ T_prev_cur

    def _new_keyframe(self, frame: Frame, F: Features, T: np.ndarray, lm: np.ndarray, kp: np.ndarray,
                      link: tuple[int, np.ndarray] | None = None) -> KeyFrame:
        kf = KeyFrame(self.next_kf_id, frame.index, frame.timestamp, T.copy(), F, np.full(len(F), -1, np.int64))
        if link is not None:
            kf.meta["odometry_link"] = link  # (keyframe id, T_that_this)
        self.next_kf_id += 1
        self.map.add_keyframe(kf)
        with self.map.lock:
            for l, k in zip(lm, kp):
                self.map.add_observation(int(l), kf, int(k))
            fresh = np.nonzero((kf.landmark_ids < 0) & F.has_depth)[0]
            if len(fresh) > self.cfg.max_new_landmarks:
                # the closest points first (RGB-D ORB-SLAM): their depth is the most precise
                fresh = fresh[np.argsort(F.depth[fresh], kind="stable")[: self.cfg.max_new_landmarks]]
            if len(fresh):
                Xw = F.points_cam[fresh] @ T[:3, :3].T + T[:3, 3]
                self.map.add_landmarks(Xw, F.descriptors[fresh], kf, fresh)
        self._set_reference(kf.id)
        self.last_kf_frame = frame.index
        self.backend.insert_keyframe(kf, frame.depth)
        return kf

    def _due_by_time(self, frame: Frame) -> bool:
        """``keyframe_max_frames`` have passed and, with ``keyframe_sharpness_ratio``, this frame is not blurred
        against the recent frames (or has waited ``keyframe_max_frames`` more already)."""
        since = frame.index - self.last_kf_frame
        if since < self.cfg.keyframe_max_frames:
            return False
        r = self.cfg.keyframe_sharpness_ratio
        if r <= 0 or since >= 2 * self.cfg.keyframe_max_frames or not self.recent_sharpness:
            return True
        return self.recent_sharpness[-1] >= r * float(np.median(self.recent_sharpness))

    def known_view(self, T: np.ndarray) -> int | None:
        """The nearest keyframe within ``keyframe_still_translation`` and ``keyframe_still_rotation_deg`` of
        camera-to-world T [4, 4] (the camera is at a view the map has), else None (also for a checkpoint's settings
        from before these)."""
        d_max = getattr(self.cfg, "keyframe_still_translation", 0.0)
        if d_max <= 0:
            return None
        every = self.map.poses()  # culled keyframes too: the mapper keeps their views
        ids = np.array(list(every), np.int64)  # [K]
        poses = np.stack(list(every.values()))  # [K, 4, 4]
        dist = np.linalg.norm(poses[:, :3, 3] - T[:3, 3], axis=1)  # [K]
        # the relative rotation's angle from its trace: cos = (tr(R_kf^T R) - 1) / 2
        cos = (np.einsum("kij,ij->k", poses[:, :3, :3], T[:3, :3]) - 1.0) / 2.0  # [K]
        near = (dist <= d_max) & (cos >= np.cos(np.radians(self.cfg.keyframe_still_rotation_deg)))
        return int(ids[near][np.argmin(dist[near])]) if near.any() else None

    def _need_keyframe(self, frame: Frame, T: np.ndarray, n_tracked: int) -> tuple[bool, int]:
        """(whether the frame becomes a keyframe, the keyframe whose view it rests at where a keyframe due only by
        time was held back for that, else -1)."""
        rest = None
        if self._due_by_time(frame):
            rest = self.known_view(T)
            if rest is None:
                return True, -1
        if self._needed_by_tracking(T, n_tracked):
            return True, -1
        if rest is None:
            return False, -1
        self.held_still += 1
        return False, rest

    def _needed_by_tracking(self, T: np.ndarray, n_tracked: int) -> bool:
        """Too few of the reference keyframe's points tracked, or moved or turned too far from it."""
        ref = self.map.keyframes[self.ref_kf]
        with self.map.lock:
            ref_lm = ref.landmark_ids[ref.landmark_ids >= 0]
            ref_lm = ref_lm[self.map.alive[ref_lm]]
            # only points other keyframes confirmed count (ORB-SLAM's nMinObs); fresh ones are not yet trusted
            min_obs = 3 if len(self.map.keyframes) > 2 else 2
            ref_tracked = sum(1 for l in ref_lm if len(self.map.observations[l]) >= min_obs)
        if n_tracked < self.cfg.keyframe_tracked_ratio * ref_tracked:
            return True
        rel = invert(ref.T_wc) @ T
        angle = np.degrees(rotation_angle(rel[:3, :3]))
        return bool(np.linalg.norm(rel[:3, 3]) > self.cfg.keyframe_translation or angle > self.cfg.keyframe_rotation_deg)

    # --- main entry -----------------------------------------------------------------------------------
    def track(self, frame: Frame) -> TrackResult:
        """Track one frame; returns its pose estimate now (the final one comes from ``trajectory()``)."""
        F = self.extractor.extract(frame.rgb, frame.depth, frame.index)
        if self.state == TrackingState.NOT_INITIALIZED:
            return self._initialize(frame, F)
        if self.cfg.keyframe_sharpness_ratio > 0:
            self.recent_sharpness = [*self.recent_sharpness, sharpness(frame.rgb)][-2 * self.cfg.keyframe_max_frames:]
        # bundle adjustment or a loop closure may have moved the reference keyframe since the last frame
        ref, rel = getattr(self, "tracked_rel", None) or (self.records[-1].ref_kf, self.records[-1].T_ref_cur)
        self.tracked_rel = None
        self.last_T = self.map.pose(ref) @ rel
        res = None
        dense_T, res = None, None
        empty = np.zeros(0, np.int64)
        if self.state in (TrackingState.OK, TrackingState.RELOCALIZED):
            guess = self._track_motion_model(F)
            if guess is None:
                guess = self._pnp(F, self.map.keyframes[self.ref_kf])
            if guess is None:
                T_last = self._pnp_last_frame(F)
                guess = None if T_last is None else (T_last, empty, empty)
            if self.dense is not None and (guess is None or len(guess[1]) < self.cfg.dense_guess_below):
                dense_T = self._dense_step(frame, None if guess is None else guess[0])  # few feature matches: a dense estimate may place the frame better
            tries = [self._track_local_map(F, *guess)] if guess is not None else []
            if dense_T is not None:
                tries.append(self._track_local_map(F, dense_T, empty, empty))
            if tries:
                res = max(tries, key=lambda t: len(t[1]))
            state = TrackingState.OK
        else:
            found = self._relocalize(F)
            res = None if found is None else self._track_local_map(F, *found)
            state = TrackingState.RELOCALIZED
        if res is not None:
            T, lm, kp = res
            if len(lm) < self.cfg.min_matches:
                res = None
        if res is None and dense_T is not None:
            # too little texture for features: keep the dense estimate and anchor a keyframe on it
            T, lm, kp = dense_T, empty, empty
            res = (T, lm, kp)
        if res is None:
            self.state = TrackingState.LOST
            T_ref = self.map.keyframes[self.ref_kf].T_wc
            # while lost, report the last pose (the frame is counted as lost in the metrics)
            self.records.append(FrameRecord(frame.index, frame.timestamp, self.ref_kf,
                                            invert(T_ref) @ self.last_T, TrackingState.LOST))
            self.velocity = np.eye(4)
            return TrackResult(self.last_T.copy(), False, 0.0, TrackingState.LOST)
        gcgr = self.backend.gcgr
        if gcgr is not None and gcgr.per_frame and state == TrackingState.OK:
            T = gcgr.refine_frame(T, frame.depth)  # per-frame GCGR: the map pulls the tracked pose
        self.state = state
        self.velocity = invert(self.last_T) @ T if state == TrackingState.OK else np.eye(4)
        weak = len(lm) < self.cfg.min_matches  # only a dense estimate placed this frame
        is_kf, rests_at = False, -1  # rests_at: a keyframe due by time held back at that keyframe's view
        if state == TrackingState.OK:
            is_kf, rests_at = (True, -1) if weak else self._need_keyframe(frame, T, len(lm))
        lm_per_kp = np.full(len(F), -1, np.int64)
        lm_per_kp[kp] = lm
        kf_id = -1
        if is_kf:
            # a keyframe placed by dense odometry shares too few points to be held by BA: tie it to its reference
            link = (self.ref_kf, invert(self.map.keyframes[self.ref_kf].T_wc) @ T) if weak else None
            kf = self._new_keyframe(frame, F, T, lm, kp, link)
            lm_per_kp = kf.landmark_ids.copy()
            kf_id = kf.id
        self.last_T, self.last_features, self.last_lm, self.last_frame = T, F, lm_per_kp, frame
        # a keyframe's frame is the keyframe: its final pose is the optimized one, including what bundle adjustment
        # has already changed at insertion (a record relative to that pose would undo it)
        T_ref = self.map.keyframes[self.ref_kf].T_wc
        T_ref_cur = invert(T_ref) @ T
        if is_kf:
            self.tracked_rel = (self.ref_kf, T_ref_cur)
            T_ref_cur = np.eye(4)
        self.records.append(FrameRecord(frame.index, frame.timestamp, self.ref_kf, T_ref_cur, state))
        return TrackResult(T.copy(), True, len(lm) / max(len(F), 1), state, is_kf, len(lm), kf_id, rests_at)

    def _initialize(self, frame: Frame, F: Features) -> TrackResult:
        """First frame with enough depth-backed keypoints becomes keyframe 0 at the world origin."""
        if F.has_depth.sum() < 2 * self.cfg.min_matches:
            self.records.append(FrameRecord(frame.index, frame.timestamp, -1, np.eye(4),
                                            TrackingState.NOT_INITIALIZED))
            return TrackResult(np.eye(4), False, 0.0, TrackingState.NOT_INITIALIZED)
        T = np.eye(4)
        kf = self._new_keyframe(frame, F, T, np.zeros(0, np.int64), np.zeros(0, np.int64))
        self.state = TrackingState.OK
        self.velocity = np.eye(4)
        self.last_T, self.last_features, self.last_lm, self.last_frame = T, F, kf.landmark_ids.copy(), frame
        self.records.append(FrameRecord(frame.index, frame.timestamp, kf.id, np.eye(4), TrackingState.OK))
        return TrackResult(T, True, 1.0, TrackingState.OK, True, 0, kf.id)

    def promote_last_frame(self) -> KeyFrame | None:
        """At the end of the input: make the last frame a keyframe when it was tracked, is not one, and at least
        ``final_keyframe_after`` frames followed the last keyframe (so the map learns what the camera saw since), but
        not when the camera came to rest at a keyframe's view (``rests_at`` then names that keyframe, on the first call
        for that frame only); returns the new keyframe, else None."""
        self.rests_at = None
        n = getattr(self.cfg, "final_keyframe_after", 0)  # a checkpoint's tracker from before the setting: as it was
        if n <= 0 or not self.records or self.last_frame is None:
            return None
        r = self.records[-1]
        if (r.state != TrackingState.OK or r.index != self.last_frame.index or r.index - self.last_kf_frame < n
                or r.index == self.rested_frame):
            return None
        T = self.map.pose(r.ref_kf) @ r.T_ref_cur  # [4, 4] as the backend holds it now
        self.rests_at = self.known_view(T)
        if self.rests_at is not None:  # the camera came to rest at a keyframe's view: nothing new to map
            self.rested_frame = r.index  # answered once: its frames' steps are not handed out twice
            return None
        kp = np.nonzero(self.last_lm >= 0)[0]
        with self.map.lock:
            kp = kp[self.map.alive[self.last_lm[kp]]]  # bundle adjustment may have culled points since
        lm = self.last_lm[kp]
        link = None
        if len(lm) < self.cfg.min_matches:  # placed by dense odometry: tied to its reference as in ``track``
            link = (r.ref_kf, r.T_ref_cur.copy())
        kf = self._new_keyframe(self.last_frame, self.last_features, T, lm, kp, link)
        self.records[-1] = FrameRecord(r.index, r.timestamp, kf.id, np.eye(4), r.state)
        self.last_lm = kf.landmark_ids.copy()
        return kf

    def trajectory(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Final timestamps [N], camera-to-world poses [N, 4, 4] of every frame, and lost flags [N].

        Frames before initialization get the first keyframe's pose.
        """
        poses = self.map.poses()
        stamps, out, lost = [], [], []
        first = poses[min(poses)] if poses else np.eye(4)
        for r in self.records:
            T = first if r.ref_kf < 0 else poses[r.ref_kf] @ r.T_ref_cur
            stamps.append(r.timestamp)
            out.append(T)
            lost.append(r.state in (TrackingState.LOST, TrackingState.NOT_INITIALIZED))
        return np.array(stamps), np.stack(out), np.array(lost)

    def finish(self) -> None:
        """Let the backend process every queued keyframe."""
        self.backend.finish()

    def summary(self) -> dict:
        """Backend figures (keyframes, landmarks, BA timing, loops) for metrics.json."""
        return self.backend.summary()

    def keyframe_trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Timestamps [K] and camera-to-world poses [K, 4, 4] of the keyframes."""
        with self.map.lock:
            poses = self.map.poses()
            stamps = {k: kf.timestamp for k, kf in [*self.map.keyframes.items(), *self.map.retired.items()]}
        ids = sorted(poses)
        return np.array([stamps[k] for k in ids]), np.stack([poses[k] for k in ids])
