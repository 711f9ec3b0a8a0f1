"""Motion-only pose refinement: robust Gauss-Newton on RGB-D (virtual stereo) reprojection residuals.

Each observation of a map point X_w gives the residual [u, v, u_r] - pi(T_cw X_w), where
u_r = u - bf / z is the right-image coordinate of a virtual stereo camera with baseline b (RGB-D ORB-SLAM);
observations without depth use [u, v] only. Huber weights, then outliers are classified by chi-square and
excluded, in four rounds (as ORB-SLAM's PoseOptimization).

The Gauss-Newton system of each iteration comes from ``normal_equations``, a compiled kernel (one pass over the
observations, no GIL: tracking runs beside mapping and the backend); ``normal_equations_reference`` is the same
math in plain numpy, and tests hold the two together.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from ggfslam.data.types import Camera
from ggfslam.geometry.se3 import invert, so3_exp

CHI2_STEREO = 7.815  # chi-square 95% with 3 dof
CHI2_MONO = 5.991  # 2 dof


@dataclass
class RefineResult:
    """Refined camera-to-world pose and which observations are inliers."""

    T_wc: np.ndarray  # [4, 4]
    inliers: np.ndarray  # [K] bool
    chi2: np.ndarray  # [K] whitened squared error at the end


def project_stereo(T_cw: np.ndarray, X_w: np.ndarray, camera: Camera, bf: float) -> tuple[np.ndarray, np.ndarray]:
    """Predicted [u, v, u_r] [K, 3] and camera-frame points [K, 3] of world points X_w [K, 3]."""
    p = X_w @ T_cw[:3, :3].T + T_cw[:3, 3]  # [K, 3]
    z = np.where(np.abs(p[:, 2]) > 1e-9, p[:, 2], 1e-9)
    u = camera.fx * p[:, 0] / z + camera.cx
    v = camera.fy * p[:, 1] / z + camera.cy
    return np.stack([u, v, u - bf / z], axis=1), p


def stereo_measurement(uv: np.ndarray, depth: np.ndarray, bf: float) -> np.ndarray:
    """Measured [u, v, u_r] [K, 3] from pixels [K, 2] and depth [K] (u_r meaningless where depth is 0)."""
    ur = uv[:, 0] - bf / np.where(depth > 0, depth, 1.0)
    return np.column_stack([uv, ur])


def normal_equations_reference(T_cw: np.ndarray, X_w: np.ndarray, meas: np.ndarray, stereo: np.ndarray,
                               w_info: np.ndarray, inlier: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                               bf: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Huber-weighted Gauss-Newton system (H [6, 6], g [6], observations used) of the residuals meas - pi(T_cw X_w)
    over the inliers in front of the camera, for a left perturbation T_cw <- Exp(d) T_cw, d = [omega, v].

    X_w [K, 3], meas [K, 3] (u, v, u_r), stereo [K] (has depth), w_info [K] (1 / sigma^2), inlier [K]."""
    camera = Camera(fx, fy, cx, cy, 0, 0)
    pred, p = project_stereo(T_cw, X_w, camera, bf)
    r = meas - pred  # [K, 3]
    r[~stereo, 2] = 0.0
    chi2 = w_info * np.sum(r ** 2, axis=1)
    delta_h = np.sqrt(np.where(stereo, CHI2_STEREO, CHI2_MONO))
    e = np.sqrt(chi2)
    huber = np.where(e <= delta_h, 1.0, delta_h / np.maximum(e, 1e-12))  # IRLS weights
    use = inlier & (p[:, 2] > 1e-6)
    x, y, z = p[use, 0], p[use, 1], p[use, 2]
    iz, iz2 = 1.0 / z, 1.0 / z ** 2
    n = len(x)
    Jp = np.zeros((n, 3, 3))  # d[u, v, u_r]/d p_c
    Jp[:, 0, 0] = fx * iz
    Jp[:, 0, 2] = -fx * x * iz2
    Jp[:, 1, 1] = fy * iz
    Jp[:, 1, 2] = -fy * y * iz2
    Jp[:, 2, 0] = fx * iz
    Jp[:, 2, 2] = -(fx * x - bf) * iz2
    Jp[~stereo[use], 2, :] = 0.0
    Jd = np.zeros((n, 3, 6))  # dp/dd = [-[p]_x, I]
    Jd[:, 0, 1], Jd[:, 0, 2] = z, -y
    Jd[:, 1, 0], Jd[:, 1, 2] = -z, x
    Jd[:, 2, 0], Jd[:, 2, 1] = y, -x
    Jd[:, :, 3:] = np.eye(3)
    J = -np.einsum("nij,njk->nik", Jp, Jd)  # d r / d d  [n, 3, 6]
    W = (w_info[use] * huber[use])[:, None, None]
    H = np.einsum("nij,nik->jk", J * W, J)
    g = np.einsum("nij,ni->j", J * W, r[use])
    return H, g, n


@njit(cache=True, nogil=True)
def normal_equations(T_cw, X_w, meas, stereo, w_info, inlier, fx, fy, cx, cy, bf):
    """``normal_equations_reference`` compiled: one pass, no temporaries."""
    H = np.zeros((6, 6))
    g = np.zeros(6)
    J = np.zeros((3, 6))
    r = np.zeros(3)
    n = 0
    d_stereo, d_mono = np.sqrt(CHI2_STEREO), np.sqrt(CHI2_MONO)
    for k in range(X_w.shape[0]):
        px = T_cw[0, 0] * X_w[k, 0] + T_cw[0, 1] * X_w[k, 1] + T_cw[0, 2] * X_w[k, 2] + T_cw[0, 3]
        py = T_cw[1, 0] * X_w[k, 0] + T_cw[1, 1] * X_w[k, 1] + T_cw[1, 2] * X_w[k, 2] + T_cw[1, 3]
        pz = T_cw[2, 0] * X_w[k, 0] + T_cw[2, 1] * X_w[k, 1] + T_cw[2, 2] * X_w[k, 2] + T_cw[2, 3]
        if not inlier[k] or not pz > 1e-6:
            continue
        iz = 1.0 / pz
        iz2 = iz * iz
        u = fx * px * iz + cx
        r[0] = meas[k, 0] - u
        r[1] = meas[k, 1] - (fy * py * iz + cy)
        r[2] = meas[k, 2] - (u - bf * iz) if stereo[k] else 0.0
        chi2 = w_info[k] * (r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
        delta = d_stereo if stereo[k] else d_mono
        e = np.sqrt(chi2)
        w = w_info[k] * (1.0 if e <= delta else delta / max(e, 1e-12))
        # J = -Jp Jd with Jd = [-[p]_x, I]; rows of Jp: (fx/z, 0, -fx x/z^2), (0, fy/z, -fy y/z^2), u_r row
        rows = 3 if stereo[k] else 2
        for i in range(rows):
            if i == 0:
                a0, a1, a2 = fx * iz, 0.0, -fx * px * iz2
            elif i == 1:
                a0, a1, a2 = 0.0, fy * iz, -fy * py * iz2
            else:
                a0, a1, a2 = fx * iz, 0.0, -(fx * px - bf) * iz2
            # (a0, a1, a2) [-[p]_x | I]: -[p]_x = [[0, z, -y], [-z, 0, x], [y, -x, 0]]
            J[i, 0] = -(a1 * -pz + a2 * py)
            J[i, 1] = -(a0 * pz + a2 * -px)
            J[i, 2] = -(a0 * -py + a1 * px)
            J[i, 3], J[i, 4], J[i, 5] = -a0, -a1, -a2
        for i in range(rows):
            for a in range(6):
                g[a] += w * J[i, a] * r[i]
                for b in range(6):
                    H[a, b] += w * J[i, a] * J[i, b]
        n += 1
    return H, g, n


def refine_pose(
    T_wc: np.ndarray, X_w: np.ndarray, uv: np.ndarray, depth: np.ndarray, sigma: np.ndarray, camera: Camera,
    baseline: float, rounds: int = 4, iterations: int = 10,
) -> RefineResult:
    """Refine T_wc [4, 4] from world points X_w [K, 3] seen at uv [K, 2] with depth [K] (0 = none), noise sigma [K] px."""
    bf = camera.fx * baseline
    T_cw = invert(T_wc)
    X_w = np.ascontiguousarray(X_w, np.float64)
    meas = stereo_measurement(np.asarray(uv, np.float64), depth, bf)  # [K, 3]
    stereo = depth > 0  # [K]
    w_info = 1.0 / np.asarray(sigma, np.float64) ** 2  # [K]
    inlier = np.ones(len(X_w), dtype=bool)
    chi2 = np.zeros(len(X_w))
    for rnd in range(rounds):
        for _ in range(iterations):
            H, g, n = normal_equations(T_cw, X_w, meas, stereo, w_info, inlier, camera.fx, camera.fy, camera.cx,
                                       camera.cy, bf)
            if n < 4:
                break
            try:
                d = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
            except np.linalg.LinAlgError:
                break
            dT = np.eye(4)
            dT[:3, :3] = so3_exp(d[:3])
            dT[:3, 3] = d[3:]  # first-order translation part is enough for small steps
            T_cw = dT @ T_cw
            if np.linalg.norm(d) < 1e-7:  # 1e-7 rad / 0.1 um: far below what pixels can resolve
                break
        pred, p = project_stereo(T_cw, X_w, camera, bf)
        r = meas - pred
        r[~stereo, 2] = 0.0
        chi2 = w_info * np.sum(r ** 2, axis=1)
        new_inlier = (chi2 < np.where(stereo, CHI2_STEREO, CHI2_MONO)) & (p[:, 2] > 0)
        settled = np.array_equal(new_inlier, inlier)
        inlier = new_inlier
        if inlier.sum() < 4 or settled:  # the same inlier set would give the same optimum
            break
    # re-orthonormalise: the first-order updates drift off SO(3) by ~1e-12 per step
    U, _, Vt = np.linalg.svd(T_cw[:3, :3])
    T_cw[:3, :3] = U @ Vt
    return RefineResult(invert(T_cw), inlier, chi2)
