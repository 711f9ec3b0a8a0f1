"""Synthetic RGB-D sequences: the embedded default data of the demo and the tests.

A procedural furnished room (``scene_builder``) with seeded solid textures (``textures``) is ray cast on
the CPU with Open3D along smooth hand-held trajectories. Each frame has exact colour, z-depth, normals and
triangle / object ids; an optional Kinect-like noise model degrades the depth. The same ray caster renders
any mesh with vertex colours (e.g. Replica's office0) along given poses.

World frame of the synthetic room: z up, floor at z = 0. Poses are camera-to-world, OpenCV camera axes.
"""
from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from ggfslam.atomic import atomic_path, write_text_atomic
from ggfslam.data.replica import read_cam_params, read_matrix_trajectory
from ggfslam.data.scene_builder import ROOM_MAX, ROOM_MIN, SceneMesh, make_scene
from ggfslam.data.types import Camera, Frame
from ggfslam.data.writer import write_tum_sequence
from ggfslam.errors import DatasetError
from ggfslam.geometry.se3 import look_at, rigidity_error, so3_exp

__all__ = [
    "GENERATOR_VERSION", "TRAJECTORY_KINDS", "SceneMesh", "MeshRaycaster", "SyntheticSequence", "make_scene",
    "synthetic_camera", "trajectory", "render_frame", "kinect_depth_noise", "generate_sequence",
    "write_synthetic_sequence", "render_mesh_sequence", "render_replica_sequence",
]

GENERATOR_VERSION = "ggfslam-synthetic/1"
TRAJECTORY_KINDS = ("orbit", "loop", "line")
DEPTH_SCALE = 5000.0  # TUM convention: depth PNG units per metre

# Cameras walk on this ellipse (semi-axes along x, y) centred on the table; with its +-0.25 m lanes it keeps
# every camera >= 0.5 m from the table and from the furniture along the walls.
_RING_AXES = np.array([1.75, 1.35])
_EYE_HEIGHT = 1.45
_STEP = 0.01  # mean camera step per frame in metres (30 cm/s at 30 fps: a slow hand-held walk)


# --------------------------------------------------------------------------------------------------
# camera and trajectories
# --------------------------------------------------------------------------------------------------
def synthetic_camera(width: int = 640, height: int = 480) -> Camera:
    """Kinect-like pinhole intrinsics (fx = fy = 525 at 640 px wide) for a ``width`` x ``height`` image."""
    f = 525.0 * width / 640.0
    return Camera(fx=f, fy=f, cx=(width - 1) / 2.0, cy=(height - 1) / 2.0, width=int(width), height=int(height),
                  depth_scale=DEPTH_SCALE)


def _ellipse(phi: np.ndarray) -> np.ndarray:
    """Points [N, 2] of the camera ring at angles ``phi`` [N]."""
    return np.stack([_RING_AXES[0] * np.cos(phi), _RING_AXES[1] * np.sin(phi)], axis=-1)


def _ring_perimeter() -> float:
    """Length of the camera ring in metres."""
    return float(np.sum(np.linalg.norm(np.diff(_ellipse(np.linspace(0, 2 * np.pi, 20001)), axis=0), axis=1)))


def _ring_at_arclength(phi0: float, s: np.ndarray, sign: float) -> tuple[np.ndarray, np.ndarray]:
    """Ring points [N, 2] and outward unit normals [N, 2] at arc lengths ``s`` [N] from angle ``phi0``."""
    phi = np.linspace(0.0, 2 * np.pi, 20001)
    seg = np.linalg.norm(np.diff(_ellipse(phi0 + sign * phi), axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])  # [20001]
    ang = phi0 + sign * np.interp(np.mod(s, arc[-1]), arc, phi)  # [N]
    normal = np.stack([np.cos(ang) / _RING_AXES[0], np.sin(ang) / _RING_AXES[1]], axis=-1)
    return _ellipse(ang), normal / np.linalg.norm(normal, axis=1, keepdims=True)


def _resample_closed(curve: np.ndarray, n: int) -> np.ndarray:
    """Parameters [n] in [0, 1) of ``n`` points equally spaced in arc length along a closed curve [M, D] (tau = k/M)."""
    seg = np.linalg.norm(np.diff(np.concatenate([curve, curve[:1]]), axis=0), axis=1)  # [M]
    arc = np.concatenate([[0.0], np.cumsum(seg)])  # [M + 1]
    tau = np.linspace(0.0, 1.0, len(curve) + 1)
    return np.interp(np.arange(n) * arc[-1] / n, arc, tau)


def _aim(eye: np.ndarray, direction: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Camera-to-world poses [N, 4, 4] at ``eye`` [N, 3] looking along ``direction`` [N, 3], rolled ``roll`` [N] rad."""
    poses = np.stack([look_at(e, e + d) for e, d in zip(eye, direction)])
    for T, r in zip(poses, roll):
        T[:3, :3] = T[:3, :3] @ so3_exp(np.array([0.0, 0.0, r]))  # roll about the optical axis
    return poses


def _yawed(v: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Horizontal vectors [N, 2] rotated by ``yaw`` [N] rad."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1]], axis=-1)


def _wobble(amplitude: float, cycles: float, n: int, rate: float) -> float:
    """Amplitude of ``amplitude * sin(2 pi cycles t)`` over n frames, reduced so it changes < ``rate`` per frame."""
    return min(amplitude, rate * n / (2 * np.pi * max(cycles, 1e-9)))


def trajectory(kind: str, n_frames: int, seed: int = 0) -> np.ndarray:
    """Smooth hand-held camera-to-world poses [n_frames, 4, 4] in the synthetic room (~1 cm, < 1 degree per frame).

    ``orbit``: walk along a ring around the table looking into the room (open; a lap takes ~980 frames).
    ``loop``: a closed racetrack along the ring (out on the outer lane, back on the inner one) looking into
    the room; it spans up to half the ring, and its last frame is one step before the first.
    ``line``: translate along the -y wall looking at it (up to 3.2 m).
    """
    if kind not in TRAJECTORY_KINDS:
        raise ValueError(f"unknown trajectory kind {kind!r}; expected one of {', '.join(TRAJECTORY_KINDS)}")
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    n = int(n_frames)
    rng = np.random.default_rng([int(seed), TRAJECTORY_KINDS.index(kind) + 1])
    i = np.arange(n, dtype=np.float64)
    ph = rng.uniform(0, 2 * np.pi, size=8)  # phases of the slow oscillations that make it look hand-held
    phi0 = rng.uniform(0, 2 * np.pi)
    sign = rng.choice([-1.0, 1.0])
    if kind == "orbit":
        steps = _STEP * (1.0 + 0.25 * np.sin(2 * np.pi * i / 90 + ph[0]))  # 0.75 .. 1.25 cm
        xy, _ = _ring_at_arclength(phi0, np.concatenate([[0.0], np.cumsum(steps[:-1])]), sign)  # [N, 2]
        z = _EYE_HEIGHT + 0.08 * np.sin(2 * np.pi * i / 170 + ph[1])
        yaw = np.radians(18.0) * np.sin(2 * np.pi * i / 300 + ph[2])
        d_xy = _yawed(-xy, yaw)  # look towards the room centre, swinging left and right
        z_target = 0.85 + 0.18 * np.sin(2 * np.pi * i / 220 + ph[3])
        roll = np.radians(1.5) * np.sin(2 * np.pi * i / 130 + ph[4])
    elif kind == "loop":
        length = n * _STEP  # wanted path length
        arc_len = min(0.45 * length, 0.45 * _ring_perimeter())  # how far along the ring the loop reaches
        lane = min(0.25, 0.1 * length)  # half the distance between the outward and the return lane
        tau = np.linspace(0.0, 1.0, 4000, endpoint=False)
        c_xy, c_n = _ring_at_arclength(phi0, arc_len * (1 - np.cos(2 * np.pi * tau)) / 2, sign)
        curve = c_xy + (lane * np.sin(2 * np.pi * tau))[:, None] * c_n  # [M, 2] closed racetrack
        t = _resample_closed(curve, n)  # constant speed; the last frame is one step before the first
        xy, normal = _ring_at_arclength(phi0, arc_len * (1 - np.cos(2 * np.pi * t)) / 2, sign)
        xy = xy + (lane * np.sin(2 * np.pi * t))[:, None] * normal
        # wobbles run on the frame fraction u (t races through the turns) with whole numbers of cycles,
        # so the pose comes back to its start
        u = i / n
        dz = _wobble(0.05, 1, n, 0.003)
        z = _EYE_HEIGHT + dz * (np.sin(2 * np.pi * u + ph[1]) - np.sin(ph[1]))
        yaw = _wobble(np.radians(15.0), 3, n, np.radians(0.35)) * np.sin(2 * np.pi * 3 * u)
        d_xy = _yawed(-xy, yaw)  # look towards the room centre
        z_target = 0.85 + _wobble(0.15, 2, n, 0.004) * np.sin(2 * np.pi * 2 * u)
        roll = _wobble(np.radians(1.5), 2, n, np.radians(0.1)) * np.sin(2 * np.pi * 2 * u)
    else:  # line
        length = min(n * _STEP, 3.2)
        x = sign * (-length / 2 + length * i / max(n - 1, 1))
        xy = np.stack([x, -1.2 + 0.03 * np.sin(2 * np.pi * i / 140 + ph[0])], axis=-1)
        z = 1.4 + 0.03 * np.sin(2 * np.pi * i / 110 + ph[1])
        yaw = sign * np.radians(10.0) + np.radians(5.0) * np.sin(2 * np.pi * i / 200 + ph[2])
        d_xy = _yawed(np.tile([0.0, -1.3], (n, 1)), yaw)  # towards the -y wall, 1.3 m away
        z_target = 0.7 + 0.1 * np.sin(2 * np.pi * i / 160 + ph[3])  # low enough to see the floor strip
        roll = np.radians(1.0) * np.sin(2 * np.pi * i / 120 + ph[4])
    eye = np.concatenate([xy, z[:, None]], axis=1)  # [N, 3]
    direction = np.concatenate([d_xy, (z_target - z)[:, None]], axis=1)  # [N, 3]
    return _aim(eye, direction, roll)


_make_trajectory = trajectory  # SyntheticSequence's argument named ``trajectory`` shadows the function


# --------------------------------------------------------------------------------------------------
# ray casting
# --------------------------------------------------------------------------------------------------
class MeshRaycaster:
    """CPU ray caster of a triangle mesh (Open3D ``RaycastingScene``) giving z-depth, ids, normals, colour."""

    def __init__(self, mesh: o3d.geometry.TriangleMesh, smooth_normals: bool = False):
        vertices = np.asarray(mesh.vertices, dtype=np.float32)  # [V, 3]
        self.triangles = np.asarray(mesh.triangles, dtype=np.int64)  # [F, 3]
        self.vertex_colors = np.asarray(mesh.vertex_colors, dtype=np.float32) if mesh.has_vertex_colors() else None
        # Interpolated vertex normals shade curved surfaces smoothly. Only triangles whose vertex normals
        # differ from the face normal need it (few pixels), and it is only right where vertices are not
        # shared across sharp edges: true for SceneMesh, not for arbitrary meshes.
        self.tri_vertex_normals = None  # [F, 3, 3] vertex normals per triangle
        self.tri_curved = None  # [F] bool
        if smooth_normals and mesh.has_vertex_normals():
            vn = np.asarray(mesh.vertex_normals, dtype=np.float32)[self.triangles]  # [F, 3, 3]
            fn = np.cross(vertices[self.triangles[:, 1]] - vertices[self.triangles[:, 0]],
                          vertices[self.triangles[:, 2]] - vertices[self.triangles[:, 0]])  # [F, 3]
            fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-12)
            curved = np.any(np.abs(np.abs(np.einsum("fkj,fj->fk", vn, fn)) - 1.0) > 1e-5, axis=1)  # [F]
            self.tri_vertex_normals = vn
            self.tri_curved = curved
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(self.triangles.astype(np.uint32)))
        self._dirs: dict[tuple, np.ndarray] = {}

    def _camera_dirs(self, camera: Camera) -> np.ndarray:
        """Camera-frame ray directions [H*W, 3] float32 with z = 1, so the ray parameter t is the z-depth."""
        key = (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)
        if key not in self._dirs:
            u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64))
            d = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], axis=-1)
            self._dirs = {key: d.reshape(-1, 3).astype(np.float32)}  # keep one camera: sequences use one
        return self._dirs[key]

    def cast(self, camera: Camera, T_wc: np.ndarray) -> dict:
        """Cast one ray per pixel from pose ``T_wc`` [4, 4].

        Returns depth [H, W] float32 (0 = no hit), tri_ids [H, W] int64 (-1 = none), hit [H, W] bool, and per
        pixel (row-major, meaningless where there is no hit): points [H*W, 3] world, normals_w [H*W, 3]
        world unit normals facing the camera, bary [H*W, 2] barycentric (u, v) and tri [H*W] (0 at misses).
        """
        T_wc = np.asarray(T_wc, dtype=np.float64)
        h, w = camera.height, camera.width
        R = np.ascontiguousarray(T_wc[:3, :3], dtype=np.float32)
        origin = T_wc[:3, 3].astype(np.float32)
        d_w = self._camera_dirs(camera) @ np.ascontiguousarray(R.T)  # [H*W, 3]
        rays = np.empty((h * w, 6), dtype=np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = d_w
        ans = self.scene.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy()  # [H*W], inf at misses
        prim = ans["primitive_ids"].numpy()  # [H*W] uint32
        hit = prim != o3d.t.geometry.RaycastingScene.INVALID_ID
        all_hit = bool(hit.all())
        tri = prim.astype(np.int64)
        bary = ans["primitive_uvs"].numpy()  # [H*W, 2]
        n = ans["primitive_normals"].numpy()  # [H*W, 3]
        if not all_hit:
            t = np.where(hit, t, 0.0).astype(np.float32)
            tri[~hit] = 0
        if self.tri_vertex_normals is not None:
            sel = np.nonzero(self.tri_curved[tri] & hit)[0]
            if len(sel):
                vn = self.tri_vertex_normals[tri[sel]]  # [S, 3, 3]
                b = bary[sel]
                ns = (1 - b.sum(1))[:, None] * vn[:, 0] + b[:, :1] * vn[:, 1] + b[:, 1:] * vn[:, 2]
                n[sel] = ns / np.maximum(np.linalg.norm(ns, axis=1, keepdims=True), 1e-12)
        n *= np.where(np.einsum("ij,ij->i", n, d_w) > 0, -1.0, 1.0).astype(np.float32)[:, None]  # face the camera
        points = origin + t[:, None] * d_w  # [H*W, 3]
        tri_ids = np.where(hit, tri, -1) if not all_hit else tri
        return {"depth": t.reshape(h, w), "tri_ids": tri_ids.reshape(h, w), "hit": hit.reshape(h, w),
                "points": points, "normals_w": n, "bary": bary, "tri": tri}

    def vertex_colour(self, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Barycentric interpolation [M, 3] of vertex colours at hits on triangles ``tri`` [M] with ``bary`` [M, 2]."""
        if self.vertex_colors is None:
            raise ValueError("mesh has no vertex colours")
        vc = self.vertex_colors[self.triangles[tri]]  # [M, 3, 3]
        b = bary.astype(np.float32)
        return (1 - b.sum(1))[:, None] * vc[:, 0] + b[:, :1] * vc[:, 1] + b[:, 1:] * vc[:, 2]


def _scene_caster(scene: SceneMesh) -> MeshRaycaster:
    """The ray caster of a SceneMesh, built once and cached on it."""
    if scene._caster is None:
        scene._caster = MeshRaycaster(scene.mesh, smooth_normals=True)
    return scene._caster


def _assemble(cast: dict, colour: np.ndarray, T_wc: np.ndarray, camera: Camera) -> dict:
    """Images from a cast and the per-pixel colours [H*W, 3] of its hits."""
    h, w = camera.height, camera.width
    R = np.ascontiguousarray(np.asarray(T_wc)[:3, :3], dtype=np.float32)
    normals = cast["normals_w"] @ R  # world -> camera: R^T n, written for row vectors
    rgb = colour.astype(np.float32, copy=False)
    hit = cast["hit"].reshape(-1)
    if not hit.all():
        rgb = np.where(hit[:, None], rgb, 0.0).astype(np.float32)
        normals = np.where(hit[:, None], normals, 0.0).astype(np.float32)
    return {"rgb": rgb.reshape(h, w, 3), "depth": cast["depth"], "normals": normals.reshape(h, w, 3),
            "tri_ids": cast["tri_ids"]}


def render_frame(scene: SceneMesh, camera: Camera, T_wc: np.ndarray) -> dict:
    """Render the synthetic scene from ``T_wc``: rgb [H, W, 3] float32, depth [H, W] float32 z-metres (0 = none),
    normals [H, W, 3] float32 camera frame facing the camera, tri_ids [H, W] int64 and object_ids [H, W] int32
    (-1 = none)."""
    cast = _scene_caster(scene).cast(camera, T_wc)
    out = _assemble(cast, scene.shade(cast["points"], cast["tri"], cast["normals_w"]), T_wc, camera)
    obj = scene.triangle_labels[cast["tri"]].reshape(cast["hit"].shape)
    out["object_ids"] = np.where(cast["hit"], obj, -1).astype(np.int32)
    return out


# --------------------------------------------------------------------------------------------------
# sensor noise
# --------------------------------------------------------------------------------------------------
def kinect_depth_noise(
    depth: np.ndarray,
    rng: np.random.Generator,
    normals: np.ndarray | None = None,
    camera: Camera | None = None,
    max_range: float = 4.5,
    dropout: float = 0.005,
    f_ir: float = 580.0,
    baseline: float = 0.075,
) -> np.ndarray:
    """Kinect-v1-like noisy copy of a z-depth map [H, W] (0 = invalid).

    Axial gaussian noise sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 (Nguyen et al. 2012), disparity quantised to
    1/8 px of the IR camera (``f_ir``, ``baseline``), ragged holes along depth discontinuities, holes at
    grazing incidence (> 80 degrees, when camera-frame ``normals`` [H, W, 3] and the ``camera`` are given),
    random single-pixel dropout and nothing beyond ``max_range``.
    """
    z = np.asarray(depth, dtype=np.float64)
    valid = z > 0
    sigma = 0.0012 + 0.0019 * (z - 0.4) ** 2
    noisy = z + rng.standard_normal(z.shape) * sigma
    fb = f_ir * baseline
    disp = np.round(fb / np.maximum(noisy, 1e-3) * 8.0) / 8.0  # sub-pixel disparity steps of the sensor
    noisy = np.where(disp > 0, fb / np.maximum(disp, 1e-9), 0.0)
    # discontinuities: a neighbour much nearer/farther (or missing) means the projector pattern breaks up
    pad = np.pad(z, 1, mode="edge")
    jump = np.zeros_like(valid)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        nb = pad[dy:dy + z.shape[0], dx:dx + z.shape[1]]
        jump |= np.abs(nb - z) > 0.03 + 0.02 * z
    band = cv2.dilate(jump.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    holes = jump | (band & (rng.random(z.shape) < 0.5))
    if normals is not None and camera is not None:
        u, v = np.meshgrid(np.arange(z.shape[1]), np.arange(z.shape[0]))
        ray = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(u.shape)], -1)
        cos = np.abs(np.sum(ray * normals, axis=-1)) / np.linalg.norm(ray, axis=-1)
        holes |= (cos < np.cos(np.radians(80.0))) & (rng.random(z.shape) < 0.7)
    holes |= rng.random(z.shape) < dropout
    keep = valid & ~holes & (noisy > 0) & (noisy <= max_range)
    return np.where(keep, noisy, 0.0).astype(np.float32)


def _apply_noise(img: dict, camera: Camera, rng: np.random.Generator, depth_noise: bool,
                 rgb_noise: float) -> tuple[np.ndarray, np.ndarray]:
    """Noisy (or clean) rgb and depth of one rendered frame."""
    depth = kinect_depth_noise(img["depth"], rng, img["normals"], camera) if depth_noise else img["depth"]
    rgb = img["rgb"]
    if rgb_noise > 0:
        rgb = np.clip(rgb + rng.normal(0.0, rgb_noise, rgb.shape).astype(np.float32), 0.0, 1.0)
    return rgb, depth


def _frame_rng(seed: int, index: int) -> np.random.Generator:
    """Noise generator of one frame: independent of the order in which frames are rendered."""
    return np.random.default_rng([int(seed), int(index), 0xD0D0])


# --------------------------------------------------------------------------------------------------
# sequences
# --------------------------------------------------------------------------------------------------
class SyntheticSequence:
    """A synthetic RGB-D sequence rendered on demand: ``len``, indexing and iteration give Frames."""

    def __init__(
        self,
        n_frames: int = 120,
        width: int = 640,
        height: int = 480,
        trajectory: str = "orbit",
        seed: int = 0,
        depth_noise: bool = False,
        fps: float = 30.0,
        textureless_wall: bool = False,
        rgb_noise: float = 0.0,
        scene: SceneMesh | None = None,
    ):
        self.scene = scene if scene is not None else make_scene(seed, textureless_wall)
        self.camera = synthetic_camera(width, height)
        self.kind = trajectory
        self.seed = int(seed)
        self.depth_noise = bool(depth_noise)
        self.rgb_noise = float(rgb_noise)
        self.fps = float(fps)
        self.poses = _make_trajectory(trajectory, n_frames, seed)  # [N, 4, 4]
        self.timestamps = np.arange(n_frames) / self.fps  # [N]

    def __len__(self) -> int:
        return len(self.poses)

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame {i} out of range for a sequence of {n}")
        img = render_frame(self.scene, self.camera, self.poses[i])
        rgb, depth = _apply_noise(img, self.camera, _frame_rng(self.seed, i), self.depth_noise, self.rgb_noise)
        meta = {"normals": img["normals"], "object_ids": img["object_ids"]}
        if self.depth_noise:
            meta["depth_gt"] = img["depth"]
        return Frame(index=i, timestamp=float(self.timestamps[i]), rgb=rgb, depth=depth, T_wc=self.poses[i].copy(),
                     name=f"synthetic/{self.kind}/{i:06d}", meta=meta)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]


def generate_sequence(
    n_frames: int = 120,
    width: int = 640,
    height: int = 480,
    trajectory: str = "orbit",
    seed: int = 0,
    depth_noise: bool = False,
    fps: float = 30.0,
    textureless_wall: bool = False,
    rgb_noise: float = 0.0,
) -> Iterator[Frame]:
    """Frames of a synthetic sequence (Frame.meta: 'normals', 'object_ids', and 'depth_gt' when noisy)."""
    return iter(SyntheticSequence(n_frames, width, height, trajectory, seed, depth_noise, fps, textureless_wall,
                                  rgb_noise))


def _write_mesh(path: Path, mesh: o3d.geometry.TriangleMesh) -> None:
    """Binary PLY with vertex normals and colours (byte-identical for identical meshes)."""
    with atomic_path(path) as tmp:
        if not o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False, compressed=False,
                                          write_vertex_normals=True, write_vertex_colors=True, print_progress=False):
            raise DatasetError(path, "cannot write mesh")


def _write_json(path: Path, data: dict) -> None:
    write_text_atomic(path, json.dumps(data, indent=2, sort_keys=False) + "\n")


def write_synthetic_sequence(
    out_dir: str | Path,
    n_frames: int = 120,
    width: int = 640,
    height: int = 480,
    trajectory: str = "orbit",
    seed: int = 0,
    depth_noise: bool = False,
    overwrite: bool = False,
    fps: float = 30.0,
    textureless_wall: bool = False,
    rgb_noise: float = 0.0,
) -> Path:
    """Render a synthetic sequence to ``out_dir``: TUM layout plus mesh.ply, mesh_labels.npy and scene.json."""
    seq = SyntheticSequence(n_frames, width, height, trajectory, seed, depth_noise, fps, textureless_wall, rgb_noise)
    out = write_tum_sequence(out_dir, iter(seq), seq.camera, depth_scale=DEPTH_SCALE, overwrite=overwrite)
    scene = seq.scene
    _write_mesh(out / "mesh.ply", scene.mesh)
    with atomic_path(out / "mesh_labels.npy") as tmp:
        np.save(tmp, scene.triangle_labels.astype(np.int32))  # [F], triangle order of mesh.ply
    _write_json(out / "scene.json", {
        "generator": GENERATOR_VERSION,
        "seed": int(seed),
        "trajectory": trajectory,
        "n_frames": int(n_frames),
        "width": int(width),
        "height": int(height),
        "fps": float(fps),
        "depth_noise": bool(depth_noise),
        "rgb_noise": float(rgb_noise),
        "textureless_wall": bool(textureless_wall),
        "depth_scale": DEPTH_SCALE,
        "camera": seq.camera.to_dict(),
        "room_min": ROOM_MIN.tolist(),
        "room_max": ROOM_MAX.tolist(),
        "world_up": [0.0, 0.0, 1.0],
        "objects": [{"id": k, "name": name, "planar": bool(p)}
                    for k, (name, p) in enumerate(zip(scene.object_names, scene.planar_object))],
        "mesh": "mesh.ply",
        "mesh_labels": "mesh_labels.npy",
    })
    return out


# --------------------------------------------------------------------------------------------------
# sequences from any coloured mesh (e.g. Replica)
# --------------------------------------------------------------------------------------------------
def _load_coloured_mesh(mesh_path: Path) -> o3d.geometry.TriangleMesh:
    """Read a triangle mesh that must have faces and vertex colours."""
    if not mesh_path.is_file():
        raise DatasetError(mesh_path, "mesh file not found")
    mesh = o3d.io.read_triangle_mesh(str(mesh_path), print_progress=False)
    if len(mesh.triangles) == 0:
        raise DatasetError(mesh_path, "mesh has no triangles (unreadable, or a point cloud)")
    if not mesh.has_vertex_colors():
        raise DatasetError(mesh_path, "mesh has no vertex colours")
    return mesh


def render_mesh_sequence(
    mesh_path: str | Path,
    poses: np.ndarray,
    camera: Camera,
    out_dir: str | Path,
    timestamps: np.ndarray | None = None,
    depth_noise: bool = False,
    seed: int = 0,
    overwrite: bool = False,
) -> Path:
    """Render a mesh with vertex colours along camera-to-world ``poses`` [N, 4, 4] to ``out_dir`` (TUM + mesh.ply)."""
    mesh_path = Path(mesh_path)
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
        raise ValueError(f"poses must have shape [N, 4, 4] with N >= 1, got {poses.shape}")
    for k, T in enumerate(poses):
        err = rigidity_error(T)
        if err is not None:
            raise ValueError(f"pose {k}: {err}")
    stamps = np.arange(len(poses)) / 30.0 if timestamps is None else np.asarray(timestamps, dtype=np.float64)
    if stamps.shape != (len(poses),):
        raise ValueError(f"timestamps must have shape [{len(poses)}], got {stamps.shape}")
    caster = MeshRaycaster(_load_coloured_mesh(mesh_path), smooth_normals=False)
    camera = replace(camera, distortion=())  # the renders are ideal pinhole images, and camera.yaml says so

    def frames() -> Iterator[Frame]:
        for k, T in enumerate(poses):
            cast = caster.cast(camera, T)
            img = _assemble(cast, caster.vertex_colour(cast["tri"], cast["bary"]), T, camera)
            rgb, depth = _apply_noise(img, camera, _frame_rng(seed, k), depth_noise, 0.0)
            yield Frame(index=k, timestamp=float(stamps[k]), rgb=rgb, depth=depth, T_wc=T,
                        meta={"depth_gt": img["depth"]} if depth_noise else {})

    out = write_tum_sequence(out_dir, frames(), camera, depth_scale=DEPTH_SCALE, overwrite=overwrite)
    if mesh_path.resolve() != (out / "mesh.ply").resolve():
        shutil.copyfile(mesh_path, out / "mesh.ply")
    _write_json(out / "scene.json", {
        "generator": GENERATOR_VERSION,
        "source_mesh": mesh_path.name,
        "n_frames": len(poses),
        "depth_noise": bool(depth_noise),
        "seed": int(seed),
        "depth_scale": DEPTH_SCALE,
        "camera": camera.to_dict(),
        "mesh": "mesh.ply",
    })
    return out


def render_replica_sequence(
    replica_root: str | Path,
    out_dir: str | Path,
    n_frames: int = 200,
    width: int = 600,
    height: int = 340,
    stride: int = 1,
    depth_noise: bool = False,
    seed: int = 0,
    overwrite: bool = False,
    mesh_name: str | None = None,
) -> Path:
    """Render a Replica scene (NICE-SLAM layout: ``*_mesh.ply``, ``traj.txt``, ``cam_params.json``) along its poses.

    Uses every ``stride``-th pose of traj.txt (camera-to-world, OpenCV axes, one row-major 4x4 per line), up
    to ``n_frames`` of them, with the intrinsics scaled to ``width`` x ``height``; timestamps are pose index / 30.
    """
    root = Path(replica_root)
    if not root.is_dir():
        raise DatasetError(root, "Replica folder not found")
    if stride < 1 or n_frames < 1:
        raise ValueError(f"stride and n_frames must be >= 1, got stride={stride} n_frames={n_frames}")
    if mesh_name is None:
        found = sorted(root.glob("*_mesh.ply")) or sorted(root.glob("*.ply"))
        if not found:
            raise DatasetError(root, "no mesh (*_mesh.ply) in the Replica folder")
        mesh_path = found[0]
    else:
        mesh_path = root / mesh_name
    camera = read_cam_params(root / "cam_params.json").resized(width, height)
    poses = read_matrix_trajectory(root / "traj.txt")
    index = np.arange(0, len(poses), stride)[:n_frames]
    return render_mesh_sequence(mesh_path, poses[index], camera, out_dir, timestamps=index / 30.0,
                                depth_noise=depth_noise, seed=seed, overwrite=overwrite)
