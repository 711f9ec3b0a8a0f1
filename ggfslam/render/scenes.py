"""Synthetic Gaussian scenes for tests and benchmarks (numpy float32 arrays; see ``types`` for conventions)."""
from __future__ import annotations

import math

import numpy as np

ROOM = (4.0, 3.0, 2.5)  # x, y, z extent of the benchmark room; floor at z = 0, centred in x and y


def rotmat_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Quaternions [..., 4] (w, x, y, z) of rotation matrices [..., 3, 3]."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(np.asarray(R).reshape(-1, 3, 3)).as_quat()  # xyzw
    return np.concatenate([q[:, 3:], q[:, :3]], axis=1).reshape(np.shape(R)[:-2] + (4,))


def random_gaussians(n: int, seed: int = 0, center=(0.0, 0.0, 4.0), spread=(1.0, 0.8, 0.5),
                     scale_range=(0.02, 0.22), opacity_range=(0.05, 0.95), n_extras: int = 0) -> dict:
    """N random Gaussians in a box in front of an identity camera (anisotropic, random rotations)."""
    rng = np.random.default_rng(seed)
    out = {
        "means": (rng.normal(size=(n, 3)) * np.asarray(spread) + np.asarray(center)).astype(np.float32),
        "quats": rng.normal(size=(n, 4)).astype(np.float32),
        "scales": rng.uniform(*scale_range, size=(n, 3)).astype(np.float32),
        "opacities": rng.uniform(*opacity_range, size=n).astype(np.float32),
        "colors": rng.uniform(0, 1, size=(n, 3)).astype(np.float32),
    }
    if n_extras:
        out["extras"] = rng.uniform(0, 1, size=(n, n_extras)).astype(np.float32)
    return out


def room_scene(n: int, seed: int = 0) -> dict:
    """N Gaussians spread uniformly over the six faces of a 4 x 3 x 2.5 m room (z up), flattened onto them.

    Tangential std = 0.7 x mean spacing (jittered +-30 %), normal std = 0.05 x spacing, random spin about
    the face normal, opacity uniform in [0.5, 1], smooth random colours. Also returns ``spacing`` (m)."""
    rng = np.random.default_rng(seed)
    lx, ly, lz = ROOM
    faces = [  # (origin, u axis, v axis, normal pointing into the room)
        ((-lx / 2, -ly / 2, 0.0), (lx, 0, 0), (0, ly, 0), (0, 0, 1)),  # floor
        ((-lx / 2, -ly / 2, lz), (lx, 0, 0), (0, ly, 0), (0, 0, -1)),  # ceiling
        ((-lx / 2, -ly / 2, 0.0), (lx, 0, 0), (0, 0, lz), (0, 1, 0)),  # wall y = -ly/2
        ((-lx / 2, ly / 2, 0.0), (lx, 0, 0), (0, 0, lz), (0, -1, 0)),  # wall y = +ly/2
        ((-lx / 2, -ly / 2, 0.0), (0, ly, 0), (0, 0, lz), (1, 0, 0)),  # wall x = -lx/2
        ((lx / 2, -ly / 2, 0.0), (0, ly, 0), (0, 0, lz), (-1, 0, 0)),  # wall x = +lx/2
    ]
    areas = np.array([np.linalg.norm(np.cross(u, v)) for _, u, v, _ in faces])
    spacing = math.sqrt(areas.sum() / n)
    face = rng.choice(len(faces), size=n, p=areas / areas.sum())
    means = np.empty((n, 3))
    quats = np.empty((n, 4))
    for f, (o, u, v, nrm) in enumerate(faces):
        sel = face == f
        k = int(sel.sum())
        if k == 0:
            continue
        a, b = rng.random(k), rng.random(k)
        means[sel] = np.asarray(o) + a[:, None] * np.asarray(u) + b[:, None] * np.asarray(v)
        z = np.asarray(nrm, float)
        x = np.asarray(u, float) / np.linalg.norm(u)
        R0 = np.stack([x, np.cross(z, x), z], axis=1)  # local z -> face normal
        th = rng.random(k) * 2 * np.pi
        c, s = np.cos(th), np.sin(th)
        Rs = np.zeros((k, 3, 3))
        Rs[:, 0, 0], Rs[:, 0, 1], Rs[:, 1, 0], Rs[:, 1, 1], Rs[:, 2, 2] = c, -s, s, c, 1
        quats[sel] = rotmat_to_quat_wxyz(R0[None] @ Rs)
    means += rng.normal(scale=0.1 * spacing, size=means.shape)
    scales = np.empty((n, 3))
    scales[:, :2] = 0.7 * spacing * rng.uniform(0.7, 1.3, size=(n, 2))
    scales[:, 2] = 0.05 * spacing
    opac = rng.uniform(0.5, 1.0, size=n)
    colors = 0.5 + 0.35 * np.sin(means @ rng.normal(size=(3, 3)) * 2.0) + rng.normal(scale=0.05, size=(n, 3))
    return {
        "means": means.astype(np.float32), "quats": quats.astype(np.float32), "scales": scales.astype(np.float32),
        "opacities": opac.astype(np.float32), "colors": np.clip(colors, 0, 1).astype(np.float32),
        "spacing": spacing,
    }


def room_camera(width: int, height: int) -> tuple[tuple, np.ndarray]:
    """Benchmark camera of ``room_scene``: ((fx, fy, cx, cy, W, H), T_cw [4, 4] float64). It stands near a
    corner at (-1.8, -1.3, 1.2) looking across the room at (2.0, 1.5, 1.2), fx = fy = 0.7 W (71 deg
    horizontal field of view): about 43 % of the room's Gaussians are in view."""
    from ggfslam.geometry.se3 import invert, look_at

    f = 0.7 * width
    T_wc = look_at(np.array([-1.8, -1.3, 1.2]), np.array([2.0, 1.5, 1.2]))
    return (f, f, width / 2 - 0.5, height / 2 - 0.5, width, height), invert(T_wc)
