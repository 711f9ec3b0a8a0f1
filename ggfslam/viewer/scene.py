"""The viewer's scene in a viser server: one node per layer, one checkbox per layer, a frame slider, and a click
picker that names the factor-graph element under the cursor with its kind and error.

Every ``draw_*`` method replaces its nodes (viser replaces a node added again under the same name), so the live
viewer calls them again as the run goes on; a node's visibility follows its checkbox.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from ggfslam.viewer.layers import Edges, Graph, Keyframes, Mesh, RunLayers, Splats, Trajectories

BACKGROUND = (255, 255, 255)  # viser's canvas
EDGE_COLORS = {"covisibility": (60, 120, 220), "odometry_link": (40, 170, 90), "loop": (230, 40, 40)}
PICK_RADIANS = 0.03  # how far off the click ray an element may lie and still be picked


def error_colors(values: np.ndarray, vmax: float | None = None) -> np.ndarray:
    """uint8 colours [N, 3] of values [N] on the turbo colour map, 0 .. vmax (default: the 95th percentile);
    nan grey."""
    from matplotlib import colormaps

    v = np.asarray(values, np.float64)
    ok = np.isfinite(v)
    if vmax is None:
        vmax = float(np.percentile(v[ok], 95)) if ok.any() else 1.0
    t = np.clip(np.where(ok, v, 0) / max(vmax, 1e-12), 0, 1)
    rgb = (colormaps["turbo"](t)[:, :3] * 255).astype(np.uint8)
    rgb[~ok] = 150
    return rgb


def rotation_wxyz(R: np.ndarray) -> np.ndarray:
    """Quaternion (w, x, y, z) of a rotation matrix [3, 3]."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def polyline_segments(points: np.ndarray) -> np.ndarray:
    """Segments [N-1, 2, 3] joining consecutive points [N, 3]."""
    return np.stack([points[:-1], points[1:]], axis=1)


@dataclass
class Pickable:
    """Elements of one layer a click can pick: each is a set of 3D points (a landmark, samples along an edge)."""

    layer: str
    points: np.ndarray  # [M, 3]
    owner: np.ndarray  # [M] element index of each point
    describe: object  # callable(element index) -> markdown line


def pick(pickables: list[Pickable], origin: np.ndarray, direction: np.ndarray,
         radians: float = PICK_RADIANS) -> tuple[Pickable, int] | None:
    """The element whose point lies closest (in angle) to the click ray, within ``radians``; None if none."""
    d = direction / np.linalg.norm(direction)
    best = None
    for p in pickables:
        if not len(p.points):
            continue
        v = p.points - origin  # [M, 3]
        along = v @ d  # [M]
        off = np.linalg.norm(v - along[:, None] * d, axis=1)  # [M]
        ang = np.where(along > 1e-6, np.arctan2(off, np.maximum(along, 1e-6)), np.inf)
        i = int(np.argmin(ang))
        if ang[i] <= radians and (best is None or ang[i] < best[0]):
            best = (ang[i], p, int(p.owner[i]))
    return None if best is None else (best[1], best[2])


class RunScene:
    """A run's layers drawn in ``server`` (a ``viser.ViserServer``), with the GUI that switches them."""

    def __init__(self, server, layers: RunLayers, frames=None, title: str = "ggfslam"):
        self.server, self.layers, self.frames = server, layers, frames
        self._lock = threading.RLock()
        self.pickables: dict[str, Pickable] = {}
        gui = server.gui
        self.info = gui.add_markdown(f"**{title}**")
        with gui.add_folder("Layers"):
            self.show = {name: gui.add_checkbox(name, initial_value=on) for name, on in (
                ("Gaussian map", True), ("colour by P_2D", False), ("mesh", False), ("trajectory", True),
                ("ground truth", True), ("keyframes", True), ("landmarks", False), ("covisibility", False),
                ("odometry links", True), ("loops", True), ("planes", False), ("GCGR factors", True))}
        for name, box in self.show.items():
            box.on_update(lambda _e, n=name: self._toggled(n))
        self.selection = gui.add_markdown("Click a landmark, an edge, a plane or a GCGR factor to see its error.")
        self.problems = gui.add_markdown("")
        self.slider = None
        self._frame_images = None
        self._nodes: dict[str, list] = {}  # checkbox name -> its scene handles
        self._frustums: dict[int, object] = {}  # keyframe id -> its frustum handle
        self.initial_pose: np.ndarray | None = None  # [4, 4] T_wc of the view a new browser starts from
        server.scene.on_click()(self._clicked)

    # -- drawing -----------------------------------------------------------------------------------------------
    def draw_all(self) -> None:
        """Every layer the run has, the slider, the summary and the problems."""
        L = self.layers
        self.set_view()
        if L.splats is not None:
            self.draw_splats(L.splats)
        if L.mesh is not None:
            self.draw_mesh(L.mesh)
        if L.trajectories is not None:
            self.draw_trajectories(L.trajectories)
        if L.keyframes is not None:
            self.draw_keyframes(L.keyframes)
        if L.graph is not None:
            self.draw_graph(L.graph)
        if self.frames is not None and L.trajectories is not None and self.slider is None:
            self.add_frame_slider(len(L.trajectories.est))
        self.write_summary()

    def _set(self, layer: str, handles: list) -> None:
        with self._lock:
            self._nodes[layer] = handles
            for h in handles:
                h.visible = self._visible(layer)

    def _visible(self, layer: str) -> bool:
        return bool(self.show[layer].value)

    def _toggled(self, layer: str) -> None:
        if layer == "colour by P_2D":
            if self.layers.splats is not None:
                self.draw_splats(self.layers.splats)
            return
        with self._lock:
            for h in self._nodes.get(layer, []):
                h.visible = self._visible(layer)

    def set_view(self) -> None:
        """Up = the first keyframe's up (-y of its OpenCV camera); the initial view = that keyframe's viewpoint,
        stepped back so its own frustum and image sit in the middle of the view instead of filling it."""
        L = self.layers
        poses = L.keyframes.poses if L.keyframes is not None and len(L.keyframes.poses) else (
            L.trajectories.est if L.trajectories is not None else None)
        if poses is None:
            return
        T = poses[0].copy()
        T[:3, 3] -= 4 * self.frustum_scale * T[:3, 2]
        self.initial_pose = T
        self.server.scene.set_up_direction(tuple(-T[:3, 1]))
        cam = self.server.initial_camera
        cam.position = tuple(T[:3, 3])
        ahead = float(np.clip((L.centre() - T[:3, 3]) @ T[:3, 2], 0.5, 5.0))
        cam.look_at = tuple(T[:3, 3] + ahead * T[:3, 2])
        cam.up = tuple(-T[:3, 1])
        if L.keyframes is not None:
            cam.fov = float(L.keyframes.fov_y)

    @property
    def frustum_scale(self) -> float:
        """Size of the camera frustums: 5% of the trajectory's extent."""
        t = self.layers.trajectories
        extent = float(np.ptp(t.est[:, :3, 3], axis=0).max()) if t is not None and len(t.est) else 1.0
        return float(np.clip(0.05 * max(extent, 0.5), 0.03, 0.5))

    def draw_splats(self, s: Splats) -> None:
        """Show the map's Gaussians (coloured by P_2D when that layer is on)."""
        planar = self._visible("colour by P_2D") and s.planar_colors is not None
        h = self.server.scene.add_gaussian_splats(
            "/map/gaussians", centers=s.means, covariances=s.covariances,
            rgbs=s.planar_colors if planar else s.colors, opacities=s.opacities)
        self._set("Gaussian map", [h])

    def draw_mesh(self, m: Mesh) -> None:
        """Show the mesh (per-vertex colours through trimesh)."""
        if m.colors is not None:
            # viser's simple mesh has one colour; per-vertex colours go through trimesh
            import trimesh

            tm = trimesh.Trimesh(m.vertices, m.faces, vertex_colors=(m.colors * 255).astype(np.uint8), process=False)
            h = self.server.scene.add_mesh_trimesh("/map/mesh", tm)
        else:
            h = self.server.scene.add_mesh_simple("/map/mesh", m.vertices, m.faces, color=(180, 180, 180))
        self._set("mesh", [h])

    def draw_trajectories(self, t: Trajectories) -> None:
        """Show the estimated and ground-truth trajectories."""
        sc = self.server.scene
        seg = polyline_segments(t.est[:, :3, 3])  # [N-1, 2, 3]
        if len(seg):
            if t.gt is not None:
                col = error_colors(t.error_m)  # [N, 3]
                colors = np.stack([col[:-1], col[1:]], axis=1)
            else:
                colors = np.broadcast_to(np.array([255, 140, 0], np.uint8), seg.shape).copy()
            self._set("trajectory", [sc.add_line_segments("/trajectory/estimate", seg, colors, thickness=3,
                                                           thickness_units="screen")])
        if t.gt is not None and len(t.gt) > 1:
            gseg = polyline_segments(t.gt[:, :3, 3])
            self._set("ground truth", [sc.add_line_segments("/trajectory/ground_truth", gseg, (40, 40, 40),
                                                            thickness=2, thickness_units="screen")])

    def draw_keyframes(self, k: Keyframes) -> None:
        """Frustums with their images: new keyframes are added, known ones only moved (their image is sent once)."""
        scale = self.frustum_scale
        with self._lock:
            for i, (kf, T) in enumerate(zip(k.ids, k.poses)):
                wxyz, pos = rotation_wxyz(T[:3, :3]), T[:3, 3]
                h = self._frustums.get(int(kf))
                if h is not None:
                    h.wxyz, h.position = wxyz, pos
                    continue
                img = k.images[i] if i < len(k.images) else None
                self._frustums[int(kf)] = self.server.scene.add_camera_frustum(
                    f"/keyframes/kf_{int(kf):06d}", fov=k.fov_y, aspect=k.aspect, scale=scale, image=img,
                    color=(230, 120, 20), thickness=2, thickness_units="screen", format="jpeg", wxyz=wxyz,
                    position=pos)
            for kf in set(self._frustums) - {int(i) for i in k.ids}:  # culled keyframes
                self._frustums.pop(kf).remove()
            self._set("keyframes", list(self._frustums.values()))

    def draw_graph(self, g: Graph) -> None:
        """Show the factor graph (keyframes, landmarks, factors) and make its elements pickable."""
        sc = self.server.scene
        with self._lock:
            self.pickables.clear()
        size = 0.4 * self.frustum_scale
        if len(g.landmarks):
            h = sc.add_point_cloud("/graph/landmarks", g.landmarks.astype(np.float32), error_colors(g.landmark_chi2),
                                   point_size=0.2 * size, point_shape="circle")
            self._set("landmarks", [h])
            self._pickable("landmarks", g.landmarks, np.arange(len(g.landmarks)), lambda i: (
                f"**landmark l{g.landmark_ids[i]}**: {g.landmark_obs[i]} observations, error "
                f"{g.landmark_error[i]:.3f} (GTSAM, Huber), mean chi2 {g.landmark_chi2[i]:.2f}"))
        for e in g.edges:
            self._draw_edges(g, e)
        self._draw_planes(g)
        self._draw_gcgr(g, size)

    def _pickable(self, layer: str, points: np.ndarray, owner: np.ndarray, describe) -> None:
        with self._lock:
            self.pickables[layer] = Pickable(layer, np.asarray(points, np.float64), owner, describe)

    def _draw_edges(self, g: Graph, e: Edges) -> None:
        layer = {"covisibility": "covisibility", "odometry_link": "odometry links", "loop": "loops"}[e.kind]
        ok = np.array([int(a) in g.kf_position and int(b) in g.kf_position for a, b in zip(e.a, e.b)], bool)
        if not ok.any():
            return
        pa = np.stack([g.kf_position[int(a)] for a in e.a[ok]])
        pb = np.stack([g.kf_position[int(b)] for b in e.b[ok]])
        seg = np.stack([pa, pb], axis=1)  # [E, 2, 3]
        h = self.server.scene.add_line_segments(f"/graph/{e.kind}", seg, EDGE_COLORS[e.kind],
                                                thickness=4 if e.kind == "loop" else 2, thickness_units="screen")
        self._set(layer, [h])
        idx = np.nonzero(ok)[0]
        t = np.linspace(0.15, 0.85, 8)  # samples along each edge, off its keyframes' ends
        pts = (pa[:, None] * (1 - t)[None, :, None] + pb[:, None] * t[None, :, None]).reshape(-1, 3)

        def describe(j: int) -> str:
            i = idx[j]
            what = (f"{int(e.value[i])} shared landmarks" if e.kind == "covisibility"
                    else f"error {e.value[i]:.4f} (GTSAM), chi2 {e.chi2[i]:.3f}")
            return f"**{e.kind.replace('_', ' ')} x{e.a[i]} - x{e.b[i]}**: {what}"
        self._pickable(layer, pts, np.repeat(np.arange(len(idx)), len(t)), describe)

    def _draw_planes(self, g: Graph) -> None:
        if not len(g.planes):
            return
        verts, faces = [], []
        for q, (coef, c, s) in enumerate(zip(g.planes, g.plane_centres, g.plane_size)):
            n = coef[:3] / np.linalg.norm(coef[:3])
            u = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
            u /= np.linalg.norm(u)
            v = np.cross(n, u)
            corners = [c + 0.5 * s * (a * u + b * v) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
            verts += corners
            faces += [[4 * q, 4 * q + 1, 4 * q + 2], [4 * q, 4 * q + 2, 4 * q + 3]]
        h = self.server.scene.add_mesh_simple("/graph/planes", np.array(verts, np.float32), np.array(faces, np.int32),
                                              color=(150, 80, 200), opacity=0.35, side="double")
        self._set("planes", [h])
        self._pickable("planes", g.plane_centres, np.arange(len(g.planes)), lambda i: (
            f"**plane p{g.plane_ids[i]}**: n = {np.round(g.planes[i, :3], 3).tolist()}, d = {g.planes[i, 3]:.3f} m, "
            f"{g.plane_obs[i]} observations, plane factor error {g.plane_error[i]:.3f} (GTSAM)"))

    def _draw_gcgr(self, g: Graph, size: float) -> None:
        if not g.gcgr:
            return
        pts, cols, owner = [], [], []
        err = error_colors(np.array([f["rows_rmse"] for f in g.gcgr]))
        for j, f in enumerate(g.gcgr):
            pts.append(f["points"])
            cols.append(np.broadcast_to(err[j], f["points"].shape))
            owner.append(np.full(len(f["points"]), j))
        pts = np.concatenate(pts).astype(np.float32)
        h = self.server.scene.add_point_cloud("/graph/gcgr", pts, np.concatenate(cols), point_size=0.25 * size,
                                              point_shape="square")
        self._set("GCGR factors", [h])
        self._pickable("GCGR factors", pts, np.concatenate(owner), lambda j: (
            f"**{g.gcgr[j]['type'].replace('_', ' ')} factor of x{g.gcgr[j]['kf']}**: {g.gcgr[j]['rows']} pixels ({g.gcgr[j]['valid']} on the map), "
            f"error {g.gcgr[j]['error']:.3f} (GTSAM), rows RMS {g.gcgr[j]['rows_rmse']:.4f}"))

    # -- interaction -------------------------------------------------------------------------------------------
    def _clicked(self, event) -> None:
        with self._lock:
            layers = [p for name, p in self.pickables.items() if self._visible(name)]
        hit = pick(layers, np.asarray(event.ray_origin), np.asarray(event.ray_direction))
        self.selection.content = ("Nothing of the visible graph layers there." if hit is None
                                  else hit[0].describe(hit[1]))

    def add_frame_slider(self, n: int) -> None:
        """A slider over the run's frames: a camera at the frame's pose, the map's render beside the input image."""
        gui = self.server.gui
        with gui.add_folder("Frames"):
            self.slider = gui.add_slider("frame", min=0, max=max(n - 1, 0), step=1, initial_value=0)
            self.frame_caption = gui.add_markdown("Move the slider to render the map at a frame.")
            blank = np.full((8, 8, 3), 255, np.uint8)
            self._frame_images = (gui.add_image(blank, label="map render"), gui.add_image(blank, label="input"))
        self.slider.on_update(lambda _e: self.show_frame(int(self.slider.value)))

    def show_frame(self, row: int) -> None:
        """Move the frame camera to trajectory row ``row`` and show the map's render and the input image there."""
        t = self.layers.trajectories
        T = t.est[row]
        self.server.scene.add_camera_frustum(
            "/trajectory/frame", fov=self.layers.keyframes.fov_y if self.layers.keyframes else 1.0,
            aspect=self.layers.keyframes.aspect if self.layers.keyframes else 4 / 3,
            scale=1.5 * self.frustum_scale, color=(20, 200, 60), thickness=3,
            thickness_units="screen", wxyz=rotation_wxyz(T[:3, :3]), position=T[:3, 3])
        render = self.frames.render(row)
        image, caption = self.frames.input_image(row)
        err = t.error_m[row]
        text = f"frame {self.frames.frame_index(row)}: {caption}"
        if np.isfinite(err):
            text += f"; position error {100 * err:.2f} cm (aligned as the ATE)"
        if isinstance(render, str):
            text += f"; {render}"
        else:
            self._frame_images[0].image = render
        if image is not None:
            self._frame_images[1].image = image
        self.frame_caption.content = text

    def write_summary(self) -> None:
        """Write the side panel's summary of the run and its layers."""
        L = self.layers
        lines = [f"**{L.run_dir.name}**"]
        if L.splats is not None:
            shown = len(L.splats.means)
            lines.append(f"{shown:,} Gaussians" + (f" (most opaque of {L.splats.total:,})" if shown < L.splats.total
                                                   else ""))
        if L.trajectories is not None:
            t = L.trajectories
            lines.append(f"{len(t.est)} frames" + (f", ATE RMSE {100 * t.ate_rmse_m:.2f} cm (trajectory coloured by "
                                                   "error, blue = 0)" if np.isfinite(t.ate_rmse_m) else ""))
        if L.graph is not None:
            c = L.graph.factor_counts
            lines.append(f"{len(L.graph.kf_position)} keyframes, {len(L.graph.landmarks)} landmarks; factors: "
                         + ", ".join(f"{k} {v}" for k, v in sorted(c.items())))
        self.info.content = "  \n".join(lines)
        self.problems.content = "".join(f"- *{k}*: {v}\n" for k, v in L.problems.items())
