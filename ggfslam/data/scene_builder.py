"""The procedural indoor scene of the synthetic sequences: a furnished room as a labelled triangle mesh.

World frame: z up, floor at z = 0, the room spans ``ROOM_MIN`` .. ``ROOM_MAX`` (6 x 5 x 3 m). The geometry
is fixed (trajectories are designed around it); the seed only changes the texture.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from ggfslam.data.textures import ProceduralTexture, lambert

ROOM_MIN = np.array([-3.0, -2.5, 0.0])
ROOM_MAX = np.array([3.0, 2.5, 3.0])
TEXTURELESS_WALL = "wall_yneg"  # the wall the "line" trajectory films
TEXTURELESS_RGB = (0.72, 0.70, 0.66)


@dataclass
class SceneMesh:
    """A labelled scene mesh with its texture: ``shade`` gives the colour of any surface point."""

    mesh: o3d.geometry.TriangleMesh  # vertex colours (shaded albedo at the vertices) and vertex normals
    triangle_labels: np.ndarray  # [F] int32 object index of each triangle
    object_names: list[str]
    planar_object: np.ndarray  # [n_objects] bool: object made of planar faces (False: curved)
    texture: ProceduralTexture
    seed: int = 0
    textureless_wall: bool = False
    room_min: np.ndarray = field(default_factory=lambda: ROOM_MIN.copy())  # [3]
    room_max: np.ndarray = field(default_factory=lambda: ROOM_MAX.copy())  # [3]
    _caster: object = field(default=None, init=False, repr=False, compare=False)  # lazily built ray caster

    @property
    def triangle_planar(self) -> np.ndarray:
        """[F] bool: the triangle belongs to a planar object."""
        return self.planar_object[self.triangle_labels]

    def albedo(self, points: np.ndarray, tri_ids: np.ndarray) -> np.ndarray:
        """Unlit surface colour [N, 3] float32 of world points [N, 3] lying on triangles ``tri_ids`` [N]."""
        return self.texture.albedo(points, self.triangle_labels[np.asarray(tri_ids, dtype=np.int64)])

    def shade(self, points: np.ndarray, tri_ids: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Lit colour [N, 3] float32 in [0, 1] of world points [N, 3] on ``tri_ids`` [N] with world normals [N, 3]."""
        return np.clip(self.albedo(points, tri_ids) * lambert(normals)[:, None], 0.0, 1.0)


class _Builder:
    """Accumulates labelled mesh parts; every part brings its own vertices (no sharing across parts)."""

    def __init__(self, spacing: float):
        self.spacing = spacing
        self.names: list[str] = []
        self.planar: list[bool] = []
        self.verts: list[np.ndarray] = []
        self.normals: list[np.ndarray] = []
        self.tris: list[np.ndarray] = []
        self.labels: list[np.ndarray] = []
        self.n_verts = 0

    def new_object(self, name: str, planar: bool) -> int:
        self.names.append(name)
        self.planar.append(planar)
        return len(self.names) - 1

    def add(self, obj: int, V: np.ndarray, F: np.ndarray, N: np.ndarray) -> None:
        """Add a part (vertices [V, 3], triangles [F, 3], vertex normals [V, 3]), winding fixed to match N."""
        n_face = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])  # [F, 3]
        flip = np.sum(n_face * N[F].sum(axis=1), axis=1) < 0
        F = F.copy()
        F[flip] = F[flip][:, ::-1]
        self.verts.append(V)
        self.normals.append(N / np.linalg.norm(N, axis=1, keepdims=True))
        self.tris.append(F + self.n_verts)
        self.labels.append(np.full(len(F), obj, dtype=np.int32))
        self.n_verts += len(V)

    def quad(self, obj: int, centre, u, v) -> None:
        """A planar rectangle ``centre + a u + b v`` (a, b in [-1, 1]) gridded at ~spacing; normal u x v."""
        centre, u, v = (np.asarray(x, dtype=np.float64) for x in (centre, u, v))
        nu = max(1, int(np.ceil(2 * np.linalg.norm(u) / self.spacing)))
        nv = max(1, int(np.ceil(2 * np.linalg.norm(v) / self.spacing)))
        a, b = np.meshgrid(np.linspace(-1, 1, nu + 1), np.linspace(-1, 1, nv + 1), indexing="ij")
        V = centre + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v  # [(nu+1)(nv+1), 3]
        idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
        q00, q10, q01, q11 = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel()
        F = np.concatenate([np.stack([q00, q10, q11], 1), np.stack([q00, q11, q01], 1)])
        n = np.cross(u, v)
        self.add(obj, V, F, np.tile(n / np.linalg.norm(n), (len(V), 1)))

    def box(self, obj: int, centre, size, yaw_deg: float = 0.0, inward: bool = False,
            skip: tuple[str, ...] = ()) -> None:
        """An axis-aligned (then yawed) box; faces named '+x', '-z', ... in ``skip`` are left out."""
        R = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
        h = np.asarray(size, dtype=np.float64) / 2
        c = np.asarray(centre, dtype=np.float64)
        for k in range(3):
            a, b = (k + 1) % 3, (k + 2) % 3
            for s in (1, -1):
                if f"{'+' if s > 0 else '-'}{'xyz'[k]}" in skip:
                    continue
                u, v = h[a] * R[:, a], h[b] * R[:, b]
                if (s < 0) != inward:  # u x v must point along the wanted normal
                    u, v = v, u
                self.quad(obj, c + s * h[k] * R[:, k], u, v)

    def sphere(self, obj: int, centre, radius: float, n_lat: int = 32, n_lon: int = 64) -> None:
        """A UV sphere with radial vertex normals (pole fans avoid degenerate triangles)."""
        th = np.linspace(0, np.pi, n_lat + 1)[1:-1]  # rings without the poles
        ph = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
        T, P = np.meshgrid(th, ph, indexing="ij")
        dirs = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
        dirs = np.concatenate([dirs, [[0, 0, 1.0], [0, 0, -1.0]]])
        top, bot = len(dirs) - 2, len(dirs) - 1
        idx = np.arange((n_lat - 1) * n_lon).reshape(n_lat - 1, n_lon)
        nxt = np.roll(idx, -1, axis=1)
        q00, q01, q10, q11 = idx[:-1].ravel(), nxt[:-1].ravel(), idx[1:].ravel(), nxt[1:].ravel()
        F = np.concatenate([
            np.stack([q00, q10, q11], 1), np.stack([q00, q11, q01], 1),
            np.stack([np.full(n_lon, top), idx[0], nxt[0]], 1),
            np.stack([np.full(n_lon, bot), nxt[-1], idx[-1]], 1),
        ])
        self.add(obj, np.asarray(centre) + radius * dirs, F, dirs)

    def cylinder(self, obj: int, base, radius: float, height: float, n_seg: int = 64,
                 top_cap: bool = True, bottom_cap: bool = False) -> None:
        """A vertical cylinder standing on ``base`` (side gridded in height; flat caps optional)."""
        base = np.asarray(base, dtype=np.float64)
        ph = np.linspace(0, 2 * np.pi, n_seg, endpoint=False)
        ring = np.stack([np.cos(ph), np.sin(ph), np.zeros(n_seg)], 1)  # [S, 3]
        n_h = max(1, int(np.ceil(height / self.spacing)))
        zs = np.linspace(0, height, n_h + 1)
        V = (base + radius * ring[None] + zs[:, None, None] * np.array([0, 0, 1.0])).reshape(-1, 3)
        idx = np.arange((n_h + 1) * n_seg).reshape(n_h + 1, n_seg)
        nxt = np.roll(idx, -1, axis=1)
        q00, q01, q10, q11 = idx[:-1].ravel(), nxt[:-1].ravel(), idx[1:].ravel(), nxt[1:].ravel()
        F = np.concatenate([np.stack([q00, q01, q11], 1), np.stack([q00, q11, q10], 1)])
        self.add(obj, V, F, np.tile(ring, (n_h + 1, 1)))
        for z, sign, want in ((height, 1.0, top_cap), (0.0, -1.0, bottom_cap)):
            if not want:
                continue
            Vc = np.concatenate([[base + [0, 0, z]], base + radius * ring + [0, 0, z]])
            Fc = np.stack([np.zeros(n_seg, int), 1 + np.arange(n_seg), 1 + (np.arange(n_seg) + 1) % n_seg], 1)
            self.add(obj, Vc, Fc, np.tile([0, 0, sign], (len(Vc), 1)))


def make_scene(seed: int = 0, textureless_wall: bool = False, spacing: float = 0.1) -> SceneMesh:
    """Build the furnished 6 x 5 x 3 m room with a seeded texture (``textureless_wall``: one plain wall)."""
    b = _Builder(spacing)
    centre = (ROOM_MIN + ROOM_MAX) / 2
    size = ROOM_MAX - ROOM_MIN
    h = size / 2
    # room: one object per wall so a single wall can be made textureless; normals face inwards
    b.quad(b.new_object("floor", True), [centre[0], centre[1], ROOM_MIN[2]], [h[0], 0, 0], [0, h[1], 0])
    b.quad(b.new_object("ceiling", True), [centre[0], centre[1], ROOM_MAX[2]], [0, h[1], 0], [h[0], 0, 0])
    b.quad(b.new_object("wall_xneg", True), [ROOM_MIN[0], centre[1], centre[2]], [0, h[1], 0], [0, 0, h[2]])
    b.quad(b.new_object("wall_xpos", True), [ROOM_MAX[0], centre[1], centre[2]], [0, 0, h[2]], [0, h[1], 0])
    b.quad(b.new_object("wall_yneg", True), [centre[0], ROOM_MIN[1], centre[2]], [0, 0, h[2]], [h[0], 0, 0])
    b.quad(b.new_object("wall_ypos", True), [centre[0], ROOM_MAX[1], centre[2]], [h[0], 0, 0], [0, 0, h[2]])
    # table in the middle: top slab + four legs (faces hidden against other faces are left out)
    table = b.new_object("table", True)
    b.box(table, [0.0, 0.0, 0.725], [1.4, 0.8, 0.05])
    for sx in (-1, 1):
        for sy in (-1, 1):
            b.box(table, [sx * 0.62, sy * 0.32, 0.35], [0.05, 0.05, 0.70], skip=("+z", "-z"))
    b.box(b.new_object("box_on_table", True), [-0.3, 0.1, 0.85], [0.3, 0.25, 0.2], yaw_deg=20, skip=("-z",))
    b.sphere(b.new_object("sphere_on_table", False), [0.35, -0.12, 0.9], 0.15)
    b.cylinder(b.new_object("cylinder_on_table", False), [0.05, -0.25, 0.75], 0.06, 0.16, n_seg=48)
    # furniture against the walls
    b.box(b.new_object("cabinet", True), [-2.72, 1.2, 0.55], [0.5, 1.0, 1.1], skip=("-z",))
    b.box(b.new_object("box_on_cabinet", True), [-2.7, 1.0, 1.22], [0.35, 0.45, 0.24], yaw_deg=-12, skip=("-z",))
    b.box(b.new_object("crate_low", True), [2.55, -1.95, 0.25], [0.5, 0.5, 0.5], yaw_deg=15, skip=("-z",))
    b.box(b.new_object("crate_top", True), [2.55, -1.95, 0.675], [0.35, 0.35, 0.35], yaw_deg=-10, skip=("-z",))
    b.box(b.new_object("shelf", True), [1.0, 2.3, 0.9], [1.2, 0.35, 1.8], skip=("-z",))
    b.sphere(b.new_object("sphere_floor", False), [-2.3, -1.9, 0.3], 0.3, n_lat=48, n_lon=96)
    b.cylinder(b.new_object("pillar", False), [2.35, 1.75, 0.0], 0.2, 3.0, top_cap=False)
    b.cylinder(b.new_object("bin", False), [-1.0, -2.1, 0.0], 0.18, 0.5)

    V = np.concatenate(b.verts)  # [V, 3]
    N = np.concatenate(b.normals)  # [V, 3]
    F = np.concatenate(b.tris).astype(np.int32)  # [F, 3]
    labels = np.concatenate(b.labels)  # [F]
    flat = {b.names.index(TEXTURELESS_WALL): TEXTURELESS_RGB} if textureless_wall else None
    texture = ProceduralTexture(seed, len(b.names), flat)
    # a vertex belongs to exactly one part, hence one object: take the label of any triangle using it
    v_obj = np.zeros(len(V), dtype=np.int64)
    v_obj[F.ravel()] = np.repeat(labels, 3)
    colours = np.clip(texture.albedo(V, v_obj) * lambert(N)[:, None], 0, 1)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(F))
    mesh.vertex_normals = o3d.utility.Vector3dVector(N)
    mesh.vertex_colors = o3d.utility.Vector3dVector(colours.astype(np.float64))
    return SceneMesh(mesh=mesh, triangle_labels=labels, object_names=list(b.names),
                     planar_object=np.array(b.planar, dtype=bool), texture=texture, seed=int(seed),
                     textureless_wall=bool(textureless_wall))
