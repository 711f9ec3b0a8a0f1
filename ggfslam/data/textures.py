"""Procedural, seeded solid textures for the synthetic scene (rich in corners so ORB has plenty to find).

The albedo of a surface point is a function of its world position and the object it lies on, so it is
independent of mesh resolution and of the viewpoint. Each object gets its own random rotation and offset
of texture space; a stack of hashed 3D cell grids (coarse to fine) paints a patchwork of colours, then
balls, boxes and thin bars of random colour on top ("dead leaves"). Where a surface cuts those solids it
shows discs, polygons and strokes of many sizes: non-repetitive, high-contrast and full of corners.
"""
from __future__ import annotations

import numpy as np
from numba import njit
from scipy.spatial.transform import Rotation

# (cell size in metres, probability that a cell holds a shape); the first layer fills whole cells
_PATCH_CELL = 0.9
_LAYERS = np.array([(0.45, 0.9), (0.22, 0.9), (0.11, 0.85), (0.055, 0.8)])

# fixed directional light + ambient; |n . l| makes it two-sided so a surface looks the same from any side
LIGHT_DIR = np.array([0.35, 0.55, 0.76]) / np.linalg.norm([0.35, 0.55, 0.76])
AMBIENT = 0.5
DIFFUSE = 0.5

_MASK = 0xFFFFFFFF
_MIN_BAR = 0.0075  # half thickness in metres of the thinnest bar


@njit(inline="always")
def _mix(x: int) -> int:
    """Avalanche a 32-bit value (the 'lowbias32' integer hash) held in an int64: products wrap, low bits stay exact."""
    x = x ^ (x >> 16)
    x = (x * 0x7FEB352D) & _MASK
    x = x ^ (x >> 15)
    x = (x * 0x846CA68B) & _MASK
    return x ^ (x >> 16)


@njit(inline="always")
def _hash3(c0: float, c1: float, c2: float, salt: int) -> int:
    """Hash of an integer cell (given as floats from floor) and a salt."""
    h = _mix(salt ^ ((np.int64(c0) * 0x9E3779B1) & _MASK))
    h = _mix(h ^ ((np.int64(c1) * 0x85EBCA77) & _MASK))
    return _mix(h ^ ((np.int64(c2) * 0xC2B2AE3D) & _MASK))


@njit(inline="always")
def _byte(h: int, k: int) -> float:
    """k-th byte of a hash as a uniform value in [0, 1)."""
    return ((h >> (8 * k)) & 0xFF) / 256.0


@njit(inline="always")
def _colour(u0: float, u1: float, u2: float) -> tuple[float, float, float]:
    """Random colour from three uniforms; brightness spread wide so the grey image (ORB's) has contrast."""
    grey = 0.08 + 0.87 * u0
    t0 = (u1 - 0.5) * 0.9
    t1 = (u2 - 0.5) * 0.9
    return (min(max(grey + t0, 0.02), 0.98), min(max(grey - 0.5 * (t0 + t1), 0.02), 0.98),
            min(max(grey + t1, 0.02), 0.98))


@njit(inline="always")
def _offset(q: float, c: float, size: float, half: float, u: float) -> float:
    """Signed offset (cell units) of q from a shape centre placed by u so that the shape stays in its cell."""
    return (q / size - c) - (half + u * (1.0 - 2.0 * half))


# serial on purpose: ~35 ms for 640x480 on one core, and no threading layer to fight BLAS/torch threads
@njit(cache=True)
def _albedo_kernel(points, obj, rotations, offsets, salts, layers, patch_cell, out):  # pragma: no cover (jit)
    """Fill out [N, 3] with the albedo of points [N, 3] on objects obj [N] (see ProceduralTexture)."""
    for i in range(points.shape[0]):
        o = obj[i]
        p0, p1, p2 = points[i, 0], points[i, 1], points[i, 2]
        q0 = rotations[o, 0, 0] * p0 + rotations[o, 0, 1] * p1 + rotations[o, 0, 2] * p2 + offsets[o, 0]
        q1 = rotations[o, 1, 0] * p0 + rotations[o, 1, 1] * p1 + rotations[o, 1, 2] * p2 + offsets[o, 1]
        q2 = rotations[o, 2, 0] * p0 + rotations[o, 2, 1] * p1 + rotations[o, 2, 2] * p2 + offsets[o, 2]
        salt = salts[o]
        # coarse patchwork: every cell one colour
        h = _hash3(np.floor(q0 / patch_cell), np.floor(q1 / patch_cell), np.floor(q2 / patch_cell), salt)
        col = _colour(_byte(h, 0), _byte(h, 1), _byte(h, 2))
        for layer in range(layers.shape[0]):
            size = layers[layer, 0]
            c0, c1, c2 = np.floor(q0 / size), np.floor(q1 / size), np.floor(q2 / size)
            h1 = _hash3(c0, c1, c2, salt ^ ((0x1000193 * (layer + 1)) & _MASK))
            if _byte(h1, 0) >= layers[layer, 1]:
                continue
            h2 = _mix(h1 ^ 0xA511E9B3)  # shape extent
            h3 = _mix(h1 ^ 0x63D83595)  # centre
            kind = _byte(h1, 1)
            if kind < 0.35:  # ball
                r = 0.12 + 0.33 * _byte(h2, 0)
                d0 = _offset(q0, c0, size, r, _byte(h3, 0))
                d1 = _offset(q1, c1, size, r, _byte(h3, 1))
                d2 = _offset(q2, c2, size, r, _byte(h3, 2))
                hit = d0 * d0 + d1 * d1 + d2 * d2 < r * r
            else:
                e0 = 0.12 + 0.33 * _byte(h2, 0)
                e1 = 0.12 + 0.33 * _byte(h2, 1)
                e2 = 0.12 + 0.33 * _byte(h2, 2)
                if kind >= 0.7:  # bar: one long and two thin axes, like a pen stroke
                    axis = min(int(_byte(h2, 3) * 3), 2)
                    thin = max(0.03, _MIN_BAR / size)  # thinner than ~1.5 cm would alias into sparkle
                    e0 = 0.25 + 0.2 * _byte(h2, 0) if axis == 0 else thin
                    e1 = 0.25 + 0.2 * _byte(h2, 1) if axis == 1 else 1.5 * thin
                    e2 = 0.25 + 0.2 * _byte(h2, 2) if axis == 2 else 2.0 * thin
                hit = (abs(_offset(q0, c0, size, e0, _byte(h3, 0))) < e0
                       and abs(_offset(q1, c1, size, e1, _byte(h3, 1))) < e1
                       and abs(_offset(q2, c2, size, e2, _byte(h3, 2))) < e2)
            if hit:
                h4 = _mix(h1 ^ 0x2C1B3C6D)  # colour
                col = _colour(_byte(h4, 0), _byte(h4, 1), _byte(h3, 3))
        out[i, 0] = col[0]
        out[i, 1] = col[1]
        out[i, 2] = col[2]


class ProceduralTexture:
    """Seeded albedo function over (world point, object id); objects listed in ``flat_colours`` are plain."""

    def __init__(self, seed: int, n_objects: int, flat_colours: dict[int, tuple[float, float, float]] | None = None):
        rng = np.random.default_rng([int(seed), 7919])
        self.seed = int(seed)
        self.n_objects = int(n_objects)
        self.rotations = Rotation.random(n_objects, random_state=rng).as_matrix().astype(np.float64)  # [n, 3, 3]
        # large offsets keep different objects (and seeds) in unrelated parts of texture space
        self.offsets = rng.uniform(0.0, 1000.0, size=(n_objects, 3))  # [n, 3]
        self.salts = rng.integers(0, 2**32, size=n_objects, dtype=np.uint64).astype(np.int64)  # [n]
        self.flat = np.zeros(n_objects, dtype=bool)
        self.flat_rgb = np.zeros((n_objects, 3), dtype=np.float32)
        for obj, rgb in (flat_colours or {}).items():
            self.flat[obj] = True
            self.flat_rgb[obj] = rgb

    def albedo(self, points: np.ndarray, object_ids: np.ndarray) -> np.ndarray:
        """Surface colour [N, 3] float32 in [0, 1] of world points [N, 3] on objects ``object_ids`` [N]."""
        points = np.asarray(points)
        if points.dtype != np.float32:  # one compiled kernel: float32 points (um precision in a room)
            points = points.astype(np.float32)
        points = np.ascontiguousarray(points).reshape(-1, 3)
        obj = np.ascontiguousarray(object_ids, dtype=np.int64).reshape(-1)
        out = np.empty((len(points), 3), dtype=np.float32)
        if len(points):
            _albedo_kernel(points, obj, self.rotations, self.offsets, self.salts, _LAYERS, _PATCH_CELL, out)
        flat = self.flat[obj]
        if flat.any():
            out[flat] = self.flat_rgb[obj[flat]]
        return out


def lambert(normals: np.ndarray) -> np.ndarray:
    """Two-sided Lambertian + ambient light factor [N] for world normals [N, 3] (view-independent)."""
    n = np.asarray(normals, dtype=np.float32).reshape(-1, 3)
    return AMBIENT + DIFFUSE * np.abs(n @ LIGHT_DIR.astype(np.float32))
