"""Procedural, seeded solid textures for the synthetic scene (rich in corners so ORB has plenty to find).

The albedo of a surface point is a function of its world position and the object it lies on, so it is
independent of mesh resolution and of the viewpoint. Each object gets its own random rotation and offset
of texture space; a stack of hashed 3D cell grids (coarse to fine) paints a patchwork of colours, then
balls, boxes and thin bars of random colour on top ("dead leaves"). Where a surface cuts those solids it
shows discs, polygons and strokes of many sizes: non-repetitive, high-contrast and full of corners.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

# (cell size in metres, probability that a cell holds a shape); the first layer fills whole cells
_PATCH_CELL = 0.9
_SHAPE_LAYERS = ((0.45, 0.9), (0.22, 0.9), (0.11, 0.85), (0.055, 0.8))

# fixed directional light + ambient; |n . l| makes it two-sided so a surface looks the same from any side
LIGHT_DIR = np.array([0.35, 0.55, 0.76]) / np.linalg.norm([0.35, 0.55, 0.76])
AMBIENT = 0.5
DIFFUSE = 0.5

_M1 = np.uint32(0x7FEB352D)
_M2 = np.uint32(0x846CA68B)
_P = (np.uint32(0x9E3779B1), np.uint32(0x85EBCA77), np.uint32(0xC2B2AE3D), np.uint32(0x27D4EB2F))


def _mix(x: np.ndarray) -> np.ndarray:
    """Avalanche a uint32 array (the 'lowbias32' integer hash)."""
    x = x ^ (x >> np.uint32(16))
    x = x * _M1
    x = x ^ (x >> np.uint32(15))
    x = x * _M2
    return x ^ (x >> np.uint32(16))


def hash_cells(cells: np.ndarray, salt: np.ndarray) -> np.ndarray:
    """uint32 hash [N] of integer cells [N, 3] and a per-point salt [N] (uint32)."""
    c = cells.astype(np.int64).astype(np.uint32)  # wrap negatives; only the bits matter
    h = _mix(salt ^ (c[:, 0] * _P[0]))
    h = _mix(h ^ (c[:, 1] * _P[1]))
    return _mix(h ^ (c[:, 2] * _P[2]))


def _bytes(h: np.ndarray) -> np.ndarray:
    """Four uniform values in [0, 1) [N, 4] from the bytes of a uint32 hash [N]."""
    shifts = np.array([0, 8, 16, 24], dtype=np.uint32)
    return ((h[:, None] >> shifts) & np.uint32(0xFF)).astype(np.float32) * np.float32(1.0 / 256.0)


def _random_colour(u: np.ndarray) -> np.ndarray:
    """Colour [N, 3] from uniforms [N, 3]: spread brightness wide so the grey image (ORB's) has contrast."""
    grey = 0.08 + 0.87 * u[:, :1]  # [N, 1]
    tint = (u[:, 1:3] - 0.5) * 0.9  # [N, 2]
    rgb = np.concatenate([grey + tint[:, :1], grey - 0.5 * (tint[:, :1] + tint[:, 1:]), grey + tint[:, 1:]], axis=1)
    return np.clip(rgb, 0.02, 0.98)


class ProceduralTexture:
    """Seeded albedo function over (world point, object id); objects listed in ``flat_colours`` are plain."""

    def __init__(self, seed: int, n_objects: int, flat_colours: dict[int, tuple[float, float, float]] | None = None):
        rng = np.random.default_rng([int(seed), 7919])
        self.seed = int(seed)
        self.n_objects = int(n_objects)
        self.rotations = Rotation.random(n_objects, random_state=rng).as_matrix().astype(np.float64)  # [n, 3, 3]
        # large offsets keep different objects (and seeds) in unrelated parts of texture space
        self.offsets = rng.uniform(0.0, 1000.0, size=(n_objects, 3))  # [n, 3]
        self.salts = rng.integers(0, 2**32, size=n_objects, dtype=np.uint64).astype(np.uint32)  # [n]
        self.flat = np.zeros(n_objects, dtype=bool)
        self.flat_rgb = np.zeros((n_objects, 3), dtype=np.float32)
        for obj, rgb in (flat_colours or {}).items():
            self.flat[obj] = True
            self.flat_rgb[obj] = rgb

    def albedo(self, points: np.ndarray, object_ids: np.ndarray) -> np.ndarray:
        """Surface colour [N, 3] float32 in [0, 1] of world points [N, 3] on objects ``object_ids`` [N]."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        obj = np.asarray(object_ids, dtype=np.int64).reshape(-1)
        q = np.einsum("nij,nj->ni", self.rotations[obj], points) + self.offsets[obj]  # [N, 3] texture space
        salt = self.salts[obj]  # [N]
        # coarse patchwork: every cell one colour
        cells = np.floor(q / _PATCH_CELL)
        h = hash_cells(cells, salt)
        out = _random_colour(_bytes(h)[:, :3])  # [N, 3]
        for layer, (size, prob) in enumerate(_SHAPE_LAYERS):
            self._paint_layer(q, salt ^ np.uint32(0x1000193 * (layer + 1)), size, prob, out)
        out = out.astype(np.float32)
        flat = self.flat[obj]
        if flat.any():
            out[flat] = self.flat_rgb[obj[flat]]
        return out

    @staticmethod
    def _paint_layer(q: np.ndarray, salt: np.ndarray, size: float, prob: float, out: np.ndarray) -> None:
        """Paint one layer of random balls / boxes / bars (one per cell, inside its cell) over ``out`` in place."""
        cells = np.floor(q / size)  # [N, 3]
        local = q / size - cells  # [N, 3] in [0, 1): position inside the cell
        h1 = hash_cells(cells, salt)
        u1 = _bytes(h1)  # exists, kind, ... [N, 4]
        has = u1[:, 0] < prob
        if not has.any():
            return
        idx = np.nonzero(has)[0]
        loc = local[idx]
        u1 = u1[idx]
        u2 = _bytes(_mix(h1[idx] ^ np.uint32(0xA511E9B3)))  # shape extent
        u3 = _bytes(_mix(h1[idx] ^ np.uint32(0x63D83595)))  # centre + colour
        u4 = _bytes(_mix(h1[idx] ^ np.uint32(0x2C1B3C6D)))  # colour
        kind = u1[:, 1]
        # half extents in cell units; bars have one long and two thin axes (stroke-like marks)
        half = 0.12 + 0.33 * u2[:, :3]  # [M, 3]
        bar = kind >= 0.7
        thin = np.array([0.03, 0.045, 0.06], dtype=np.float32)
        long_axis = (u2[:, 3] * 3).astype(np.int64).clip(0, 2)
        half_bar = np.tile(thin, (len(idx), 1))
        half_bar[np.arange(len(idx)), long_axis] = 0.25 + 0.2 * u2[np.arange(len(idx)), long_axis]
        half = np.where(bar[:, None], half_bar, half)
        ball = kind < 0.35
        radius = half[:, 0]
        ext = np.where(ball[:, None], radius[:, None], half)  # [M, 3] keep the shape inside its cell
        centre = ext + u3[:, :3] * (1.0 - 2.0 * ext)
        d = loc - centre
        inside = np.where(ball, np.sum(d * d, axis=1) < radius * radius, np.all(np.abs(d) < half, axis=1))
        if not inside.any():
            return
        colour = _random_colour(np.stack([u4[:, 0], u4[:, 1], u3[:, 3]], axis=1))
        out[idx[inside]] = colour[inside]


def lambert(normals: np.ndarray) -> np.ndarray:
    """Two-sided Lambertian + ambient light factor [N] for world normals [N, 3] (view-independent)."""
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    return (AMBIENT + DIFFUSE * np.abs(n @ LIGHT_DIR)).astype(np.float32)
