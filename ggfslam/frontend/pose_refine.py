"""Motion-only pose refinement: robust Gauss-Newton on RGB-D (virtual stereo) reprojection residuals.

Each observation of a map point X_w gives the residual [u, v, u_r] - pi(T_cw X_w), where
u_r = u - bf / z is the right-image coordinate of a virtual stereo camera with baseline b (RGB-D ORB-SLAM);
observations without depth use [u, v] only. Huber weights, then outliers are classified by chi-square and
excluded, in four rounds (as ORB-SLAM's PoseOptimization).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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


def refine_pose(
    T_wc: np.ndarray, X_w: np.ndarray, uv: np.ndarray, depth: np.ndarray, sigma: np.ndarray, camera: Camera,
    baseline: float, rounds: int = 4, iterations: int = 10,
) -> RefineResult:
    """Refine T_wc [4, 4] from world points X_w [K, 3] seen at uv [K, 2] with depth [K] (0 = none), noise sigma [K] px."""
    bf = camera.fx * baseline
    T_cw = invert(T_wc)
    meas = stereo_measurement(uv, depth, bf)  # [K, 3]
    stereo = depth > 0  # [K]
    w_info = 1.0 / sigma ** 2  # [K]
    inlier = np.ones(len(X_w), dtype=bool)
    chi2 = np.zeros(len(X_w))
    for rnd in range(rounds):
        for _ in range(iterations):
            pred, p = project_stereo(T_cw, X_w, camera, bf)
            r = meas - pred  # [K, 3]
            r[~stereo, 2] = 0.0
            chi2 = w_info * np.sum(r ** 2, axis=1)
            thr = np.where(stereo, CHI2_STEREO, CHI2_MONO)
            delta_h = np.sqrt(thr)
            e = np.sqrt(chi2)
            huber = np.where(e <= delta_h, 1.0, delta_h / np.maximum(e, 1e-12))  # IRLS weights
            use = inlier & (p[:, 2] > 1e-6)
            if use.sum() < 4:
                break
            x, y, z = p[use, 0], p[use, 1], p[use, 2]
            iz, iz2 = 1.0 / z, 1.0 / z ** 2
            fx, fy = camera.fx, camera.fy
            n = len(x)
            Jp = np.zeros((n, 3, 3))  # d[u, v, u_r]/d p_c
            Jp[:, 0, 0] = fx * iz
            Jp[:, 0, 2] = -fx * x * iz2
            Jp[:, 1, 1] = fy * iz
            Jp[:, 1, 2] = -fy * y * iz2
            Jp[:, 2, 0] = fx * iz
            Jp[:, 2, 2] = -(fx * x - bf) * iz2
            Jp[~stereo[use], 2, :] = 0.0
            # left perturbation T_cw <- Exp(d) T_cw with d = [omega, v]: dp/dd = [-[p]_x, I]
            Jd = np.zeros((n, 3, 6))
            Jd[:, 0, 1], Jd[:, 0, 2] = z, -y
            Jd[:, 1, 0], Jd[:, 1, 2] = -z, x
            Jd[:, 2, 0], Jd[:, 2, 1] = y, -x
            Jd[:, :, 3:] = np.eye(3)
            J = -np.einsum("nij,njk->nik", Jp, Jd)  # d r / d d  [n, 3, 6]
            W = (w_info[use] * huber[use])[:, None, None]
            H = np.einsum("nij,nik->jk", J * W, J)
            g = np.einsum("nij,ni->j", J * W, r[use])
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
