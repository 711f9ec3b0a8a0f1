"""``ggfslam run --view``: the viewer following a running system.

The viewer's server lives in a process of its own: drawing, serialising and sending to the browser, aligning the
ground truth and lifting the graph cost the run nothing but the snapshots it hands over (in one thread of the
viewer's own, the run's threads only keep a thumbnail per keyframe). A first version drew from a thread of the
run's process and took 20% off tracking (frames/s) on the demo, through the interpreter lock
(``benchmarks/bench_viewer.py``).

The run calls ``started``, ``frame`` (after each tracked frame) and ``finished``. Every ``pose_period`` seconds
the snapshot thread sends the trajectory and the keyframe poses (bundle adjustment and loop closure move them);
every ``map_period`` seconds, or less often when baking takes long (at most ``map_share`` of one core), it bakes
the Gaussian map (the same bake as gaussians.ply) and sends it with the factor graph. When the run has written its
folder, the viewer shows that folder as ``ggfslam view`` would, frame slider included.
"""
from __future__ import annotations

import logging
import multiprocessing
import threading
import time
from pathlib import Path

import numpy as np

from ggfslam.errors import ViewerError

log = logging.getLogger("ggfslam.viewer")


class LiveViewer:
    """A viser server in its own process, fed by a running ``slam.run`` (pass it as ``observer``). The process is
    spawned, so a script that creates one needs the usual ``if __name__ == "__main__":`` guard."""

    def __init__(self, host: str, port: int, pose_period: float = 1.0, map_period: float = 5.0,
                 map_share: float = 0.1):
        from ggfslam.viewer.app import check_port

        check_port(host, port)
        self.pose_period, self.map_period, self.map_share = pose_period, map_period, map_share
        ctx = multiprocessing.get_context("spawn")  # no copy of the run's threads, locks or torch state
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(host, port, child), name="ggfslam-viewer", daemon=True)
        self._proc.start()
        child.close()
        if not self._conn.poll(120):
            self._proc.kill()
            raise ViewerError("the viewer's process did not start within 120 s")
        try:
            kind, value = self._conn.recv()
        except EOFError:
            raise ViewerError("the viewer's process ended at start (its error is above); from a script, create "
                              "the LiveViewer under `if __name__ == \"__main__\":`, as for any spawned "
                              "process") from None
        if kind == "error":
            raise ViewerError(value)
        self.port = int(value)
        self._send_lock = threading.Lock()
        self._thumbs: dict[int, np.ndarray] = {}  # keyframe id -> thumbnail not yet sent
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.updates = {"poses": 0, "maps": 0, "map_seconds": 0.0, "pose_seconds": 0.0}

    def _send(self, *msg) -> None:
        with self._send_lock:
            self._conn.send(msg)

    # -- called by the run ---------------------------------------------------------------------------------------
    def started(self, config, dataset, run_dir: Path, tracker, mapper) -> None:
        """The run has its tracker and mapper: start following them."""
        self.config, self.dataset, self.run_dir = config, dataset, Path(run_dir)
        self.tracker, self.mapper = tracker, mapper
        cam = dataset.camera
        gt = dataset.gt_poses
        self._send("start", f"ggfslam (live): {config.name}", str(self.run_dir),
                   float(2 * np.arctan(cam.height / (2 * cam.fy))), cam.width / cam.height,
                   None if gt is None else np.asarray(dataset.timestamps, np.float64), gt,
                   config.eval.max_time_diff)
        self._thread = threading.Thread(target=self._follow, name="ggfslam-viewer-snapshots", daemon=True)
        self._thread.start()

    def frame(self, frame, result) -> None:
        """A frame was tracked; a keyframe leaves its thumbnail (a resize: well under a millisecond)."""
        if result.keyframe:
            from ggfslam.viewer.layers import thumbnail

            self._thumbs[int(result.keyframe_id)] = thumbnail(frame.rgb)

    def finished(self, run_dir: Path) -> None:
        """The run wrote its folder: stop following and show the folder itself."""
        self._halt()
        self._send("finished", str(run_dir))

    def status(self) -> dict:
        """What the page shows now (layers, problems, frustums, the slider's range), from the viewer's process."""
        with self._send_lock:
            self._conn.send(("status",))
            return self._conn.recv()

    def close(self) -> None:
        """Stop following and shut the viewer's process down."""
        self._halt()
        if self._proc.is_alive():
            try:
                self._send("stop")
            except (OSError, ValueError):
                pass
            self._proc.join(10)
            if self._proc.is_alive():
                self._proc.kill()
        self._conn.close()

    def _halt(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    # -- the snapshot thread -------------------------------------------------------------------------------------
    def _follow(self) -> None:
        next_map = time.perf_counter() + min(self.map_period, 2.0)
        while not self._stop.wait(self.pose_period):
            try:
                t0 = time.perf_counter()
                self._send_poses()
                self.updates["poses"] += 1
                self.updates["pose_seconds"] += time.perf_counter() - t0
                if time.perf_counter() >= next_map:
                    t0 = time.perf_counter()
                    self._send_map()
                    took = time.perf_counter() - t0
                    self.updates["maps"] += 1
                    self.updates["map_seconds"] += took
                    next_map = time.perf_counter() + max(self.map_period, took / self.map_share)
            except (KeyError, IndexError, RuntimeError) as e:
                # the run changed under us (a keyframe culled mid-read); the next tick reads it again
                log.debug("viewer snapshot skipped: %s", e)
            except (OSError, EOFError) as e:  # the viewer's process is gone: the run goes on without it
                log.warning("the viewer stopped: %s", e)
                return

    def _send_poses(self) -> None:
        stamps, poses, _ = self.tracker.trajectory()
        if not len(poses):
            return
        kf_ids, kf_poses = np.zeros(0, np.int64), np.zeros((0, 4, 4))
        if hasattr(self.tracker, "map"):  # the odometry baseline has no keyframes
            kp = self.tracker.map.poses()
            kf_ids = np.array(sorted(kp), np.int64)
            kf_poses = np.stack([kp[i] for i in kf_ids]) if len(kf_ids) else kf_poses
        thumbs = {k: self._thumbs.pop(k) for k in list(self._thumbs) if k in set(kf_ids.tolist())}
        self._send("poses", stamps, poses, kf_ids, kf_poses, thumbs)

    def _send_map(self) -> None:
        if self.mapper is not None and self.mapper.map.n_anchors:
            g = self.mapper.bake_gaussians()
            planar = self.mapper.export_planarity(g).colors.numpy() if self.mapper.ggf is not None else None
            self._send("map", g.means.numpy(), g.quats.numpy(), g.scales.numpy(), g.colors.clamp(0, 1).numpy(),
                       g.opacities.numpy(), planar)
        backend = getattr(self.tracker, "backend", None)
        if backend is not None:
            from ggfslam.backend.export import graph_to_dict

            self._send("graph", graph_to_dict(backend.map, self.dataset.camera, self.config.tracking,
                                              self.config.backend, backend.gcgr))


def _serve(host: str, port: int, conn) -> None:
    """The viewer's process: a viser server drawing what the run sends, until told to stop."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the run's: it stops us through close()
    try:
        from ggfslam.viewer.app import start_server

        server = start_server(host, port)
    except Exception as e:  # noqa: BLE001 - reported to the run as one line
        conn.send(("error", str(e)))
        return
    conn.send(("ready", server.get_port()))
    follower = _Follower(server)
    try:
        while True:
            msg = conn.recv()
            if msg[0] == "stop":
                break
            if msg[0] == "status":
                conn.send(follower.status())
                continue
            try:
                getattr(follower, "on_" + msg[0])(*msg[1:])
            except Exception as e:  # noqa: BLE001 - one bad snapshot must not end the viewer
                log.warning("viewer: %s update failed: %s", msg[0], e)
    except (EOFError, OSError):
        pass  # the run's process is gone
    finally:
        server.stop()


class _Follower:
    """The scene in the viewer's process, updated from the run's snapshots."""

    def __init__(self, server):
        self.server, self.scene = server, None
        self._thumbs: dict[int, np.ndarray] = {}
        self._first = True

    def on_start(self, title, run_dir, fov, aspect, gt_stamps, gt, max_diff) -> None:
        from ggfslam.viewer.layers import RunLayers
        from ggfslam.viewer.scene import RunScene

        self.scene = RunScene(self.server, RunLayers(Path(run_dir)), None, title=title)
        self.fov, self.aspect, self.gt_stamps, self.gt, self.max_diff = fov, aspect, gt_stamps, gt, max_diff

    def on_poses(self, stamps, poses, kf_ids, kf_poses, thumbs) -> None:
        from ggfslam.viewer.layers import Keyframes, LayerError, align_trajectories

        L = self.scene.layers
        self._thumbs.update(thumbs)
        try:
            L.trajectories = align_trajectories(stamps, poses, self.gt_stamps, self.gt, self.max_diff)
        except LayerError:  # fewer than three frames: no alignment yet
            L.trajectories = align_trajectories(stamps, poses, None, None, 0.0)
        if len(kf_ids):
            L.keyframes = Keyframes(kf_ids, np.full(len(kf_ids), -1), kf_poses, self.fov, self.aspect,
                                    [self._thumbs.get(int(i)) for i in kf_ids])
        if self._first:
            self.scene.set_view()
            self._first = False
        self.scene.draw_trajectories(L.trajectories)
        if L.keyframes is not None:
            self.scene.draw_keyframes(L.keyframes)
        self.scene.write_summary()

    def on_map(self, means, quats, scales, colors, opacities, planar) -> None:
        from ggfslam.viewer.layers import Splats, covariances

        L = self.scene.layers
        L.splats = Splats(means, covariances(quats, scales), colors, opacities.reshape(-1, 1),
                          None if planar is None else np.clip(planar, 0, 1), len(means))
        self.scene.draw_splats(L.splats)
        self.scene.write_summary()

    def on_graph(self, data: dict) -> None:
        from ggfslam.viewer.layers import build_graph

        self.scene.layers.graph = build_graph(self.scene.layers.run_dir, data)
        self.scene.draw_graph(self.scene.layers.graph)
        self.scene.write_summary()

    def on_finished(self, run_dir: str) -> None:
        from ggfslam.viewer.frames import FrameViews
        from ggfslam.viewer.layers import load_run_layers

        layers = load_run_layers(run_dir)
        t = layers.trajectories
        self.scene.layers = layers
        self.scene.frames = FrameViews(layers.run_dir, t.stamps, t.est) if t is not None else None
        self.scene.draw_all()

    def status(self) -> dict:
        if self.scene is None:
            return {}
        L, sc = self.scene.layers, self.scene
        return {"run_dir": str(L.run_dir), "problems": dict(L.problems),
                "layers": [n for n in ("splats", "mesh", "trajectories", "keyframes", "graph")
                           if getattr(L, n) is not None],
                "frustums": sorted(sc._frustums), "frustums_visible": all(h.visible for h in sc._frustums.values()),
                "keyframes": [] if L.keyframes is None else [int(i) for i in L.keyframes.ids],
                "slider_max": None if sc.slider is None else int(sc.slider.max),
                "frames": None if L.trajectories is None else len(L.trajectories.est)}
