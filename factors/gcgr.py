"""GCGR factors (METHOD.md §7, paper §4.3): the Gaussian map's rendered depth and normals pull a keyframe's pose.

Conventions (the project's, stated once in ``ggfslam.render.types``): poses are camera-to-world ``T_wc`` [4, 4],
OpenCV camera axes (x right, y down, z forward); GTSAM's ``Pose3`` tangent is ``xi = [omega, v]`` and perturbs on
the right, ``T_wc * Exp(xi)`` (the camera moves in its own frame); normals are camera-frame unit vectors that
face the camera.

One keyframe gives two factors on its ``X(k)``, both over the same sampled pixels (those whose rendered planar
weight is high, where the map is opaque and the sensor has depth):
- depth rows ``0.5 (D_hat - D)``: signed, so the row and its Jacobian exist at zero; its magnitude is
  METHOD's ``0.5 |D_hat - D|`` and the squared error is the same;
- normal rows ``0.05 (1 - N_hat . N)``.
Each row is whitened by one noise ``sigma * sqrt(N / effective_pixels)`` (keeping METHOD's 0.5 : 0.05
weighting; the factor holds the information of ``effective_pixels`` independent pixels, since the map's errors are
correlated over a surface) and robustified by a Huber kernel per row (GTSAM's scalar reweighting:
``error() = sum_i rho(r_i / row_sigma)``).

Jacobians (``jacobian`` in ``GCGRConfig``):
- ``analytic``: the pixels are planar by selection, so the rendered surface at a pixel is the plane through
  ``p = D_hat K^-1 [u, v, 1]`` with the rendered normal ``n``. Moving the camera by xi moves the ray's hit on
  that plane: ``dD/domega = -(p x n) / (n . r)``, ``dD/dv = -n / (n . r)`` with ``r = K^-1 [u, v, 1]``; the
  normal turns with the camera: ``d(N_hat . N)/domega = -(N_hat x N)``, and does not change with v. One render.
- ``central``: central differences of renders at ``T_wc * Exp(+-h e_j)``, 13 renders.
Both are checked against ``gtsam.utils.numerical_derivative`` of fresh renders in ``tests/test_gcgr.py``.
Measured there (80x60 corner scene, 2026-11-26), relative Frobenius error against numerical derivatives with
the factor's trust-region step (5-10 mm / mrad): depth rows 2.8-3.1 % analytic vs 6 % central (h = 1 mm); normal
rows 33-43 % analytic vs 180 % central (rendered normals are central differences of a blended depth map, noisy at
the pixel scale; a 1 mm central difference follows that noise). Cost: 1 render against 13. Hence ``analytic``
is the default. (The renderer's reverse-mode pose gradient gives J^T r, one backward pass per row for J.)

GTSAM evaluates ``error()`` at every trial step, so a factor never renders per call: it keeps the rows and
Jacobian of its last render (the linearization point) and returns the first-order model
``r0 + J Log(T0^-1 T)``; only when the optimizer linearizes at a pose past ``relinearize_rotation`` /
``relinearize_translation`` does it render again there (both factors of a keyframe share that render): trial
steps, which Levenberg-Marquardt often rejects, never render.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import gtsam
import numpy as np

from ggfslam.config import GCGRConfig
from ggfslam.geometry.depth import normals_from_depth
from ggfslam.render.types import Intrinsics

from factors.gcgr_linear import KINDS, MIN_PIXELS, LinearGCGR, moved_past

DEPTH_WEIGHT = 0.5  # METHOD.md eq. 10
NORMAL_WEIGHT = 0.05


@dataclass
class SensorView:
    """A keyframe's own depth at the factors' resolution and the normals of that depth."""

    depth: np.ndarray  # [H, W] m, 0 = no depth
    normals: np.ndarray  # [H, W, 3] camera frame, 0 where undefined
    intr: Intrinsics

    @staticmethod
    def from_depth(depth: np.ndarray, intr: Intrinsics) -> SensorView:
        """Sensor view of a depth map [H, W] already at ``intr``'s size."""
        if depth.shape != (intr.height, intr.width):
            raise ValueError(f"depth of shape {depth.shape} for intrinsics of size {intr.height}x{intr.width}")
        depth = np.asarray(depth, np.float64)
        return SensorView(depth, normals_from_depth(depth, intr.fx, intr.fy, intr.cx, intr.cy), intr)


@dataclass
class MapView:
    """What a render of the map at one pose gives the factors (numpy, camera frame)."""

    depth: np.ndarray  # [H, W] m, 0 where the map is empty
    normals: np.ndarray  # [H, W, 3] normals of the rendered depth
    alpha: np.ndarray  # [H, W]
    weight: np.ndarray  # [H, W] planar weight: alpha-blended P_2D (alpha without the field)

    @staticmethod
    def from_render(out) -> MapView:
        """From a ``RenderOutput`` whose ``extras[..., 0]`` is the planar weight (alpha stands in without it)."""
        alpha = out.alpha.detach().double().cpu().numpy()
        weight = alpha if out.extras is None else out.extras[..., 0].detach().double().cpu().numpy()
        return MapView(out.depth.detach().double().cpu().numpy(), out.normals.detach().double().cpu().numpy(),
                       alpha, weight)


RenderFn = Callable[[np.ndarray], MapView]  # T_wc [4, 4] -> the map seen from there


def select_pixels(view: MapView, sensor: SensorView, cfg: GCGRConfig) -> np.ndarray:
    """Flat indices [N] of usable pixels (planar, opaque, locally flat in the render, depth and normals on both
    sides, residual within the gate), at most ``cfg.pixels`` spread evenly in raster order."""
    ok = ((view.weight >= cfg.planar_threshold) & (view.alpha >= cfg.min_alpha) & (view.depth > 0)
          & (sensor.depth > 0) & (np.abs(view.depth - sensor.depth) <= cfg.max_depth_residual)
          & _has_normal(view.normals) & _has_normal(sensor.normals)
          & locally_flat(view.normals, np.cos(np.radians(cfg.flat_degrees)))
          & (np.sum(view.normals * sensor.normals, axis=-1) >= np.cos(np.radians(cfg.max_normal_degrees))))
    idx = np.flatnonzero(ok)
    if len(idx) > cfg.pixels:
        idx = idx[np.linspace(0, len(idx) - 1, cfg.pixels).round().astype(np.int64)]
    return idx


def _has_normal(n: np.ndarray) -> np.ndarray:
    return np.abs(n).sum(-1) > 0


def locally_flat(normals: np.ndarray, cos_min: float) -> np.ndarray:
    """[H, W] pixels whose normal [H, W, 3] is within acos(cos_min) of each of its four neighbours' (all
    defined): off creases and depth edges, where the render is not one plane and its derivative jumps."""
    ok = _has_normal(normals)
    ok[0, :] = ok[-1, :] = ok[:, 0] = ok[:, -1] = False
    c = normals[1:-1, 1:-1]
    for nb in (normals[:-2, 1:-1], normals[2:, 1:-1], normals[1:-1, :-2], normals[1:-1, 2:]):
        ok[1:-1, 1:-1] &= np.sum(c * nb, axis=-1) >= cos_min
    return ok


def residual_rows(view: MapView, sensor: SensorView, pix: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth rows [N], normal rows [N] and validity [N] at flat pixels ``pix``; invalid rows are 0."""
    d_hat, d = view.depth.reshape(-1)[pix], sensor.depth.reshape(-1)[pix]
    n_hat, n = view.normals.reshape(-1, 3)[pix], sensor.normals.reshape(-1, 3)[pix]  # [N, 3]
    valid = (d_hat > 0) & (d > 0) & _has_normal(n_hat) & _has_normal(n)
    rd = np.where(valid, DEPTH_WEIGHT * (d_hat - d), 0.0)
    rn = np.where(valid, NORMAL_WEIGHT * (1.0 - np.sum(n_hat * n, axis=1)), 0.0)
    return rd, rn, valid


def ray_plane_jacobians(view: MapView, sensor: SensorView, pix: np.ndarray, valid: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Analytic Jacobians [N, 6] of the depth and normal rows w.r.t. xi (module docstring); 0 on invalid rows
    and where the ray grazes the rendered plane (|n . r| < 0.05 |r|)."""
    i = sensor.intr
    u, v = pix % i.width, pix // i.width
    r = np.stack([(u - i.cx) / i.fx, (v - i.cy) / i.fy, np.ones(len(pix))], axis=1)  # [N, 3] ray, z = 1
    n_hat = view.normals.reshape(-1, 3)[pix]  # [N, 3]
    n = sensor.normals.reshape(-1, 3)[pix]
    p = view.depth.reshape(-1)[pix][:, None] * r  # [N, 3] rendered point, camera frame
    nr = np.sum(n_hat * r, axis=1)  # [N]
    ok = valid & (np.abs(nr) >= 0.05 * np.linalg.norm(r, axis=1))
    inv = np.where(ok, 1.0 / np.where(ok, nr, 1.0), 0.0)[:, None]
    Jd = DEPTH_WEIGHT * np.concatenate([-np.cross(p, n_hat) * inv, -n_hat * inv], axis=1)
    Jn = np.zeros((len(pix), 6))
    Jn[:, :3] = NORMAL_WEIGHT * np.cross(n_hat, n)
    Jn[~valid] = 0.0
    return Jd, Jn


def eliminate_offset(rows: np.ndarray, J: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows [N] and Jacobian [N, 6] with a free constant offset of the valid rows eliminated: both minus their
    means over the valid rows (the Schur complement of an unconstrained offset under equal row weights); invalid
    rows stay 0."""
    if not valid.any():
        return rows, J
    rows = np.where(valid, rows - rows[valid].mean(), 0.0)
    J = np.where(valid[:, None], J - J[valid].mean(axis=0), 0.0)
    return rows, J


class GCGRModel(LinearGCGR):
    """The GCGR residuals of one keyframe: renders the map, samples the pixels once, and keeps the rows and
    Jacobians of its last render (a ``LinearGCGR`` that renders again when linearized too far from it);
    ``factors()`` are the GTSAM factors reading it, ``frozen()`` the model without its renderer."""

    def __init__(self, key: int, render: RenderFn, sensor: SensorView, T_wc: np.ndarray, cfg: GCGRConfig,
                 view: MapView | None = None, relinearize: bool = True):
        self.key, self.render, self.sensor, self.cfg = key, render, sensor, cfg
        self.relinearizes = relinearize  # False: the first-order model holds wherever it is linearized
        self.renders = 0
        self.render_seconds = 0.0
        view = view if view is not None else self._render(T_wc)
        self.pixels = select_pixels(view, sensor, cfg)  # [N] flat indices, fixed for the model's life
        self._linearize(T_wc, view)

    def _render(self, T_wc: np.ndarray) -> MapView:
        t0 = time.perf_counter()
        view = self.render(np.asarray(T_wc, np.float64))
        self.render_seconds += time.perf_counter() - t0
        self.renders += 1
        return view

    def _linearize(self, T_wc: np.ndarray, view: MapView | None = None) -> None:
        view = view if view is not None else self._render(T_wc)
        rd, rn, valid = residual_rows(view, self.sensor, self.pixels)
        if self.cfg.jacobian == "analytic":
            Jd, Jn = ray_plane_jacobians(view, self.sensor, self.pixels, valid)
        else:
            Jd, Jn = self.central_jacobians(T_wc, self.cfg.step)
            Jd[~valid], Jn[~valid] = 0.0, 0.0
        if self.cfg.free_depth_offset:
            rd, Jd = eliminate_offset(rd, Jd, valid)
        self.T0 = gtsam.Pose3(np.asarray(T_wc, np.float64))
        self.view, self.valid = view, valid
        self.rows0 = {"depth": rd, "normal": rn}  # [N] each, at T0
        self.jacobians = {"depth": Jd, "normal": Jn}  # [N, 6] each

    def relinearize(self, T_wc: np.ndarray) -> None:
        """Render again at T_wc [4, 4] and take it as the linearization point (same pixels)."""
        self._linearize(T_wc)

    def rendered_rows(self, T_wc: np.ndarray) -> dict[str, np.ndarray]:
        """Exact rows [N] of a fresh render at T_wc (not cached; for checks and diagnostics)."""
        rd, rn, _ = residual_rows(self._render(T_wc), self.sensor, self.pixels)
        return {"depth": rd, "normal": rn}

    def central_jacobians(self, T_wc: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
        """Jacobians [N, 6] of the depth and normal rows by central differences of 12 renders (step h)."""
        T0 = gtsam.Pose3(np.asarray(T_wc, np.float64))
        J = {k: np.zeros((len(self.pixels), 6)) for k in KINDS}
        for j in range(6):
            e = np.zeros(6)
            e[j] = h
            plus = residual_rows(self._render(T0.retract(e).matrix()), self.sensor, self.pixels)
            minus = residual_rows(self._render(T0.retract(-e).matrix()), self.sensor, self.pixels)
            both = plus[2] & minus[2]
            for c, k in enumerate(KINDS):
                J[k][:, j] = np.where(both, (plus[c] - minus[c]) / (2 * h), 0.0)
        return J["depth"], J["normal"]

    def evaluate(self, kind: str, pose: gtsam.Pose3, H: list | None = None) -> np.ndarray:
        """Rows [N] of ``kind`` at ``pose`` from the first-order model; fills ``H[0]`` with the Jacobian [N, 6]
        when asked, and then (a linearization, at a point the optimizer accepted) renders again first if the
        pose is past the threshold and the model ``relinearizes``. Error-only calls (trial steps, often rejected)
        never render."""
        if H is not None and self.relinearizes and moved_past(self.T0.localCoordinates(pose), self.cfg):
            self._linearize(pose.matrix())
        return super().evaluate(kind, pose, H)


def whitened_rows(model: GCGRModel, kind: str, pose: gtsam.Pose3) -> np.ndarray:
    """Rows [N] divided by the row sigma, before the robust kernel (what ``error()`` sums the Huber loss of)."""
    return model.evaluate(kind, pose) / model.row_sigma


__all__ = ["GCGRModel", "LinearGCGR", "MapView", "SensorView", "RenderFn", "select_pixels", "residual_rows",
           "ray_plane_jacobians", "locally_flat", "eliminate_offset", "moved_past", "whitened_rows", "DEPTH_WEIGHT",
           "NORMAL_WEIGHT", "KINDS", "MIN_PIXELS"]
