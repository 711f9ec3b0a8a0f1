"""A run folder read into the viewer's layers: plain numpy arrays, no viser.

Every layer is read on its own: a layer whose files are missing or unreadable becomes one line in
``RunLayers.problems`` and the others still show. Everything stays in the run's own world frame (the map's): the
ground truth is brought into it with the inverse of the ATE's alignment, so map, keyframes and graph need no
transform. Poses are camera-to-world ``T_wc`` with OpenCV camera axes.
"""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ggfslam.errors import DatasetError, RunDirError
from ggfslam.rundir import (CONFIG_FILE, GAUSSIANS_FILE, GRAPH_FILE, GROUNDTRUTH_FILE, KEYFRAME_IMAGES_DIR,
                            KEYFRAMES_FILE, MESH_FILE, PLANARITY_FILE, TRAJECTORY_FILE)

THUMB_WIDTH = 160  # keyframe images on the frustums, in pixels (sent to the browser once per keyframe)


class LayerError(Exception):
    """A layer cannot be shown; the message is one line naming the file and what is wrong."""


@dataclass
class Splats:
    """Baked Gaussians as the browser draws them."""

    means: np.ndarray  # [N, 3] world
    covariances: np.ndarray  # [N, 3, 3] world
    colors: np.ndarray  # [N, 3] in [0, 1] (the SH DC colour)
    opacities: np.ndarray  # [N, 1] in [0, 1]
    planar_colors: np.ndarray | None = None  # [N, 3]: P_2D (red = 2D, blue = 3D), from gaussians_planarity.ply
    total: int = 0  # Gaussians in the file (more than shown when capped)


@dataclass
class Mesh:
    """A run's mesh (mesh.ply) as the viewer draws it."""

    vertices: np.ndarray  # [V, 3]
    faces: np.ndarray  # [F, 3] int
    colors: np.ndarray | None  # [V, 3] in [0, 1]


@dataclass
class Trajectories:
    """The estimate and the ground truth (in the estimate's frame, aligned as the ATE aligns them)."""

    stamps: np.ndarray  # [N]
    est: np.ndarray  # [N, 4, 4] T_wc
    gt: np.ndarray | None  # [M, 4, 4] T_wc, or None without ground truth
    error_m: np.ndarray  # [N] translation error after alignment (nan: no ground-truth pose within max_diff)
    ate_rmse_m: float = float("nan")


@dataclass
class Keyframes:
    """A run's keyframes: ids, frame indices and poses."""

    ids: np.ndarray  # [K]
    frame_index: np.ndarray  # [K]
    poses: np.ndarray  # [K, 4, 4] T_wc
    fov_y: float  # vertical field of view, radians
    aspect: float  # width / height
    images: list[np.ndarray | None] = field(default_factory=list)  # [K] thumbnails [h, w, 3] uint8, or None


@dataclass
class Edges:
    """Pose-to-pose edges of one kind between keyframes."""

    kind: str  # covisibility | odometry_link | loop
    a: np.ndarray  # [E] keyframe ids
    b: np.ndarray  # [E]
    value: np.ndarray  # [E]: shared landmarks (covisibility) or the factor's GTSAM error
    chi2: np.ndarray | None = None  # [E] for factors


@dataclass
class Graph:
    """The factor graph of graph.json, placed in the world."""

    kf_position: dict[int, np.ndarray]  # keyframe id -> camera centre [3]
    landmark_ids: np.ndarray  # [P]
    landmarks: np.ndarray  # [P, 3]
    landmark_obs: np.ndarray  # [P] observations
    landmark_error: np.ndarray  # [P] sum of its observation factors' GTSAM error
    landmark_chi2: np.ndarray  # [P] mean chi2 of those factors
    edges: list[Edges]
    plane_ids: np.ndarray  # [Q]
    planes: np.ndarray  # [Q, 4] world n, d (n . x + d = 0)
    plane_centres: np.ndarray  # [Q, 3] where a patch is drawn
    plane_size: np.ndarray  # [Q] patch side, metres
    plane_error: np.ndarray  # [Q] sum of its plane factors' error
    plane_obs: np.ndarray  # [Q]
    gcgr: list[dict] = field(default_factory=list)  # per GCGR factor: type, kf, points [R, 3], error, rows_rmse, rows, valid
    factor_counts: dict = field(default_factory=dict)


@dataclass
class RunLayers:
    """Everything the viewer shows of a run; ``problems``: layer -> why it is not there (one line)."""

    run_dir: Path
    splats: Splats | None = None
    mesh: Mesh | None = None
    trajectories: Trajectories | None = None
    keyframes: Keyframes | None = None
    graph: Graph | None = None
    problems: dict[str, str] = field(default_factory=dict)

    def centre(self) -> np.ndarray:
        """A point the initial view looks at [3]: the map's median, else the trajectory's."""
        if self.splats is not None and len(self.splats.means):
            return np.median(self.splats.means, axis=0)
        if self.trajectories is not None:
            return np.median(self.trajectories.est[:, :3, 3], axis=0)
        return np.zeros(3)


def _need(path: Path, what: str) -> Path:
    if not path.is_file():
        raise LayerError(f"{path.name} missing in {path.parent} ({what})")
    return path


def covariances(quats_wxyz: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """World covariances R diag(s^2) R^T [N, 3, 3] of unit quaternions [N, 4] (w, x, y, z) and scales [N, 3]."""
    import torch

    from ggfslam.render.projection import quat_to_rotmat

    R = quat_to_rotmat(torch.as_tensor(quats_wxyz, dtype=torch.float32))  # [N, 3, 3]
    RS = R * torch.as_tensor(scales, dtype=torch.float32)[:, None, :]
    return (RS @ RS.transpose(1, 2)).numpy()


def load_splats(run_dir: Path, max_splats: int) -> Splats:
    """gaussians.ply (and gaussians_planarity.ply's colours when present), the most opaque ``max_splats``."""
    from ggfslam.gaussians.ply import read_gaussians_ply

    path = _need(run_dir / GAUSSIANS_FILE, "the run wrote no map: it did not finish or ran with mapping.enabled: false")
    try:
        g = read_gaussians_ply(path)
    except DatasetError as e:
        raise LayerError(str(e)) from None
    n = len(g["means"])
    keep = np.arange(n) if n <= max_splats else np.sort(np.argsort(-g["opacities"])[:max_splats])
    planar = None
    if (run_dir / PLANARITY_FILE).is_file():
        try:
            p = read_gaussians_ply(run_dir / PLANARITY_FILE)
        except DatasetError as e:
            raise LayerError(str(e)) from None
        if len(p["means"]) != n:
            raise LayerError(f"{PLANARITY_FILE} holds {len(p['means'])} Gaussians, {GAUSSIANS_FILE} {n}: "
                             "not the same bake")
        planar = np.clip(p["colors"][keep], 0, 1)
    return Splats(g["means"][keep], covariances(g["quats"][keep], g["scales"][keep]),
                  np.clip(g["colors"][keep], 0, 1), g["opacities"][keep, None], planar, n)


def load_mesh(run_dir: Path) -> Mesh:
    """mesh.ply (the TSDF mesh fused from the baked map)."""
    import open3d as o3d

    path = _need(run_dir / MESH_FILE, "the run wrote no mesh: it did not finish, or ran with mapping.enabled: false or "
                 "mapping.mesh: false")
    m = o3d.io.read_triangle_mesh(str(path))
    if len(m.triangles) == 0:
        raise LayerError(f"{path}: no triangles")
    colors = np.asarray(m.vertex_colors, np.float32) if m.has_vertex_colors() else None
    return Mesh(np.asarray(m.vertices, np.float32), np.asarray(m.triangles, np.int32), colors)


def load_trajectories(run_dir: Path, max_diff: float) -> Trajectories:
    """trajectory.txt, and groundtruth.txt brought into the estimate's frame; per-frame error after alignment."""
    from ggfslam.data.trajectory_io import read_tum_trajectory

    stamps, est = read_tum_trajectory(_need(run_dir / TRAJECTORY_FILE, "the run did not finish"))
    if not (run_dir / GROUNDTRUTH_FILE).is_file():
        return align_trajectories(stamps, est, None, None, max_diff)
    return align_trajectories(stamps, est, *read_tum_trajectory(run_dir / GROUNDTRUTH_FILE), max_diff)


def align_trajectories(stamps: np.ndarray, est: np.ndarray, gt_stamps: np.ndarray | None, gt: np.ndarray | None,
                       max_diff: float) -> Trajectories:
    """The estimate [N, 4, 4] with the ground truth [M, 4, 4] (None: none) moved into its frame by the inverse of
    the ATE's alignment, and each frame's translation error there."""
    from ggfslam.eval.trajectory import ATE
    from ggfslam.geometry.se3 import invert

    err = np.full(len(est), np.nan)
    if gt is None:
        return Trajectories(stamps, est, None, err)
    ate = ATE(max_diff)
    try:
        ate.process_data((stamps, est, gt_stamps, gt))
    except ValueError as e:  # too few pairs, a degenerate estimate
        raise LayerError(f"{GROUNDTRUTH_FILE}: cannot align the ground truth to the estimate ({e})") from None
    gt_in_map = invert(ate.alignment)[None] @ gt  # [M, 4, 4]: the ATE maps the estimate onto the ground truth
    j = np.clip(np.searchsorted(gt_stamps, stamps), 1, len(gt_stamps) - 1)
    j = np.where(np.abs(gt_stamps[j - 1] - stamps) < np.abs(gt_stamps[j] - stamps), j - 1, j)  # nearest [N]
    close = np.abs(gt_stamps[j] - stamps) <= max_diff
    err[close] = np.linalg.norm(est[close, :3, 3] - gt_in_map[j[close], :3, 3], axis=1)
    return Trajectories(stamps, est, gt_in_map, err, ate.get_statistic("rmse"))


def thumbnail(rgb: np.ndarray, width: int = THUMB_WIDTH) -> np.ndarray:
    """A colour image resized to ``width`` pixels (aspect kept), as uint8 [h, w, 3] (float images in [0, 1])."""
    import cv2

    if rgb.dtype != np.uint8:
        rgb = (np.clip(rgb, 0, 1) * 255).round().astype(np.uint8)

    h, w = rgb.shape[:2]
    return cv2.resize(rgb, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)


def keyframe_images(run_dir: Path) -> dict[int, Path]:
    """frame index -> the keyframe image file (keyframes/kf_*.npz) of a run."""
    out = {}
    for f in sorted((run_dir / KEYFRAME_IMAGES_DIR).glob("kf_*.npz")):
        try:
            with np.load(f) as z:
                out[int(z["frame_index"])] = f
        except (OSError, KeyError, ValueError):
            continue  # a file cut short by a kill is not a keyframe of the run
    return out


def load_keyframes(run_dir: Path, graph: dict | None) -> Keyframes:
    """Keyframe poses (graph.json's, after the last BA; else keyframes.txt) and their images as thumbnails."""
    from ggfslam.data.trajectory_io import read_tum_trajectory
    from ggfslam.saved_run import run_camera

    cam = run_camera(run_dir)
    files = keyframe_images(run_dir)
    if graph is not None:
        kfs = graph["keyframes"]
        ids = np.array([k["id"] for k in kfs], np.int64)
        frames = np.array([k["frame_index"] for k in kfs], np.int64)
        poses = np.array([k["T_wc"] for k in kfs], np.float64).reshape(-1, 4, 4)
    else:
        _, poses = read_tum_trajectory(_need(run_dir / KEYFRAMES_FILE, "keyframe poses; the odometry baseline has "
                                             "no keyframes"))
        ids = np.arange(len(poses))
        frames = np.array(sorted(files), np.int64)
        if len(frames) != len(poses):
            frames = np.full(len(poses), -1)
    images = []
    for f in frames:
        if int(f) in files:
            with np.load(files[int(f)]) as z:
                images.append(thumbnail(z["rgb"]))
        else:
            images.append(None)
    return Keyframes(ids, frames, poses, 2 * np.arctan(cam.height / (2 * cam.fy)), cam.width / cam.height, images)


def read_graph(run_dir: Path) -> dict:
    """graph.json as written by the run."""
    import json

    path = _need(run_dir / GRAPH_FILE, "the factor graph, written when a run of the ORB system finishes; the "
                 "odometry baseline has none")
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise LayerError(f"{path}: not readable JSON ({e})") from None
    missing = {"meta", "keyframes", "landmarks", "factors", "covisibility"} - set(data)
    if missing:
        raise LayerError(f"{path}: lacks {', '.join(sorted(missing))} (not a ggfslam graph.json)")
    return data


def build_graph(run_dir: Path, data: dict) -> Graph:
    """The graph's layers in the world: landmark errors, edges, plane patches, GCGR pixels lifted by the keyframe's
    depth."""
    kf_pose = {int(k["id"]): np.asarray(k["T_wc"], np.float64).reshape(4, 4) for k in data["keyframes"]}
    kf_frame = {int(k["id"]): int(k["frame_index"]) for k in data["keyframes"]}
    lms = data["landmarks"]
    lm_ids = np.array([m["id"] for m in lms], np.int64)
    row = {int(i): r for r, i in enumerate(lm_ids)}
    lm_err, lm_chi2, lm_nf = np.zeros(len(lms)), np.zeros(len(lms)), np.zeros(len(lms))
    pairs: dict[str, list] = defaultdict(list)
    plane_err: dict[int, float] = defaultdict(float)
    gcgr = []
    for f in data["factors"]:
        t = f["type"]
        if t in ("rgbd_stereo", "projection"):
            r = row.get(int(f["lm"]))
            if r is not None:
                lm_err[r] += f["error"]
                lm_chi2[r] += f["chi2"]
                lm_nf[r] += 1
        elif t in ("odometry_link", "loop"):
            pairs[t].append((int(f["other_kf"]), int(f["kf"]), f["error"], f["chi2"]))
        elif t == "plane":
            plane_err[int(f["plane"])] += f["error"]
        elif t.startswith("gcgr"):
            gcgr.append(f)
    edges = []
    cov = data["covisibility"]
    if cov:
        edges.append(Edges("covisibility", np.array([c["kf_a"] for c in cov]), np.array([c["kf_b"] for c in cov]),
                           np.array([c["shared"] for c in cov], np.float64)))
    for kind, rows in pairs.items():
        a, b, e, c = (np.array(x) for x in zip(*rows))
        edges.append(Edges(kind, a.astype(np.int64), b.astype(np.int64), e.astype(np.float64), c.astype(np.float64)))
    planes = data.get("planes", [])
    centres = np.stack([c[:3, 3] for c in kf_pose.values()]) if kf_pose else np.zeros((1, 3))
    p_coef = np.array([p["coefficients"] for p in planes], np.float64).reshape(-1, 4)
    # a patch under the cameras: their mean centre projected onto the plane, as wide as they stand from it
    c_mean = centres.mean(axis=0)
    dist = p_coef[:, :3] @ c_mean + p_coef[:, 3]  # [Q]
    p_centre = c_mean[None] - dist[:, None] * p_coef[:, :3]
    return Graph(
        kf_position={k: T[:3, 3].copy() for k, T in kf_pose.items()},
        landmark_ids=lm_ids, landmarks=np.array([m["position"] for m in lms], np.float64).reshape(-1, 3),
        landmark_obs=np.array([m["observations"] for m in lms], np.int64),
        landmark_error=lm_err, landmark_chi2=lm_chi2 / np.maximum(lm_nf, 1), edges=edges,
        plane_ids=np.array([p["id"] for p in planes], np.int64), planes=p_coef, plane_centres=p_centre,
        plane_size=np.clip(np.abs(dist), 0.3, 3.0),
        plane_error=np.array([plane_err[int(p["id"])] for p in planes]),
        plane_obs=np.array([p["observations"] for p in planes], np.int64),
        gcgr=_lift_gcgr(run_dir, data, gcgr, kf_pose, kf_frame),
        factor_counts={k: v["count"] for k, v in data["meta"].get("factors_by_type", {}).items()})


def _lift_gcgr(run_dir: Path, data: dict, factors: list[dict], kf_pose: dict, kf_frame: dict) -> list[dict]:
    """Each GCGR factor's valid pixels back-projected with its keyframe's sensor depth (keyframes/*.npz)."""
    if not factors:
        return []
    cam = data["meta"]["camera"]
    files = keyframe_images(run_dir)
    out = []
    for f in factors:
        k = int(f["kf"])
        T = kf_pose.get(k)
        file = files.get(kf_frame.get(k, -1))
        if T is None or file is None:
            continue
        with np.load(file) as z:
            depth = z["depth"]  # [H, W] metres
        uv = np.asarray(f["pixels"], np.float64).reshape(-1, 2)  # [R, 2] at resolution (w, h)
        s = depth.shape[1] / float(f["resolution"][0])
        px = np.clip(np.round(uv * s).astype(np.int64), 0, [depth.shape[1] - 1, depth.shape[0] - 1])
        z_ = depth[px[:, 1], px[:, 0]]
        ok = z_ > 0
        x = (uv[ok, 0] * s - cam["cx"]) / cam["fx"] * z_[ok]
        y = (uv[ok, 1] * s - cam["cy"]) / cam["fy"] * z_[ok]
        pts_c = np.stack([x, y, z_[ok]], 1)  # [R, 3] camera frame
        out.append({"type": f["type"], "kf": k, "points": pts_c @ T[:3, :3].T + T[:3, 3],
                    "error": float(f["error"]), "rows_rmse": float(f.get("rows_rmse", float("nan"))),
                    "rows": int(len(uv)), "valid": int(f.get("valid", len(uv)))})
    return out


def load_run_layers(run_dir: str | Path, max_splats: int = 1_000_000) -> RunLayers:
    """Every layer of a finished (or stopped) run that its files allow; the rest in ``problems``."""
    from ggfslam.config import load_config
    from ggfslam.rundir import require_run_dir

    run_dir = require_run_dir(run_dir)
    layers = RunLayers(run_dir)
    try:
        max_diff = load_config(run_dir / CONFIG_FILE).eval.max_time_diff
    except Exception:  # an unreadable config only costs the default association window
        max_diff = 0.02
    graph_data = None

    def attempt(name: str, fn):
        try:
            return fn()
        except (LayerError, RunDirError, DatasetError) as e:
            layers.problems[name] = str(e)
            return None

    layers.splats = attempt("map", lambda: load_splats(run_dir, max_splats))
    if layers.splats is not None and layers.splats.planar_colors is None:
        layers.problems["P_2D"] = f"{PLANARITY_FILE} missing (the run was made with ggf.enabled: false)"
    layers.mesh = attempt("mesh", lambda: load_mesh(run_dir))
    layers.trajectories = attempt("trajectory", lambda: load_trajectories(run_dir, max_diff))
    if layers.trajectories is not None and layers.trajectories.gt is None and "trajectory" not in layers.problems:
        layers.problems["ground truth"] = f"{GROUNDTRUTH_FILE} missing (the sequence has no ground truth)"
    graph_data = attempt("factor graph", lambda: read_graph(run_dir))
    layers.keyframes = attempt("keyframes", lambda: load_keyframes(run_dir, graph_data))
    if graph_data is not None:
        layers.graph = attempt("factor graph", lambda: build_graph(run_dir, graph_data))
    return layers
