"""Loop detection for keyframes: BoW place recognition, then geometric verification with RGB-D points.

For each new keyframe (ORB-SLAM-like): query the keyframe database, leaving out the keyframe's covisible
neighbours and the most recent keyframes; keep candidates whose score reaches a fraction of the score of
the median covisible neighbour (how similar "the same place" looks right now); optionally require the
candidate region to be found by several consecutive keyframes (temporal consistency); then verify each
candidate geometrically: ORB matching (Hamming, ratio test, one-to-one), RANSAC PnP from the candidate's
3D points to the query's pixels, then a Gauss-Newton refinement on the inliers with reprojection and, where
the query has depth too, 3D-3D residuals (matches whose two back-projections disagree are dropped). A loop
is accepted with at least ``min_inliers`` surviving matches, none of which alone carries the fit, and a
pose covariance inside the gates. Its relative pose and covariance feed a loop edge of the pose graph:
``PoseEdge(match_id, query_id, T_match_query, kind="loop", covariance=...)``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np

from ggfslam.backend.plane_map import plane_to_world
from ggfslam.backend.place_recognition import BowVector, KeyframeDatabase, Vocabulary, hamming_knn2
from ggfslam.data.types import Camera
from ggfslam.geometry.pnp import pnp_ransac
from ggfslam.geometry.se3 import invert, se3_exp

if TYPE_CHECKING:
    from ggfslam.backend.feature_store import FeatureStore

__all__ = ["LoopClosureConfig", "LoopResult", "LoopDetector", "PairVerification", "match_descriptors",
           "verify_loop_pair"]


@dataclass
class LoopClosureConfig:
    """Settings of loop detection (BoW candidate selection and geometric verification)."""

    min_score: float = 0.05
    """Absolute floor on the BoW L1 score of a candidate (scores are ~0.1 between unrelated views)."""
    min_score_ratio: float = 0.75
    """A candidate must score >= this fraction of the median score among the query's covisible neighbours (how
    similar "the same place" looks right now). The median, not the best: with keyframes close together the best
    neighbour is a near-duplicate of the query that no revisit matches (a lap of the synthetic room with keyframes
    10 cm apart found no loop against the best, the correct one against the median; ORB-SLAM takes the lowest)."""
    top_k: int = 5
    """At most this many BoW candidates (best first) are verified geometrically per keyframe."""
    exclude_recent: int = 10
    """The most recently added keyframes (this many) are never loop candidates: they are odometry."""
    min_keyframes: int = 12
    """No detection until the database holds this many keyframes (nothing to close a loop with)."""
    consistency: int = 1
    """Consecutive keyframes whose candidates must hit the same region (candidate + its covisible
    keyframes) before it is verified; 1 verifies at once (geometry alone decides)."""
    ratio_test: float = 0.8
    """Lowe's ratio: best Hamming distance < ratio_test * second best, else the match is ambiguous."""
    max_hamming: int = 64
    """Largest Hamming distance (of 256 bits) of an accepted descriptor match."""
    ransac_reproj_px: float = 3.0
    """RANSAC PnP inlier threshold on the reprojection error, in pixels."""
    ransac_iterations: int = 300
    """RANSAC PnP iterations."""
    ransac_confidence: float = 0.999
    """RANSAC PnP confidence to stop early."""
    refine_reproj_px: float = 2.0
    """Inlier threshold (pixels) after the LM refinement, which leaves inliers much closer."""
    max_point_dist_m: float = 0.05
    """3D-3D check: largest distance (m) between a match's two back-projections in one frame ..."""
    max_point_dist_rel: float = 0.03
    """... or this fraction of the depth, whichever is larger (depth noise grows with range)."""
    pixel_sigma: float = 1.0
    """Keypoint position noise (px) of the refinement and of the reported covariance."""
    depth_sigma_a: float = 0.0015
    """Depth noise model sigma(z) = a + b z^2 (m) of the 3D-3D residuals: constant part ..."""
    depth_sigma_b: float = 0.002
    """... and quadratic part (Kinect-like structured light and ToF sensors both grow with range)."""
    max_sigma_trans_m: float = 0.03
    """Reject a loop whose estimated translation std (largest axis, m) exceeds this: matches bunched on a
    distant plane give a fit with few residuals but a loose pose, and a wrong loop edge costs more than a
    late one."""
    max_sigma_rot_deg: float = 1.0
    """Same gate on the largest rotation std (degrees)."""
    max_leverage: float = 0.5
    """Largest share of the fit (leverage, of 6 degrees of freedom in all) one match may carry: a lone near
    point among matches bunched on a far wall can pin a wrong pose that looks precise; such matches are
    dropped, and the covariance gates judge what is left."""
    min_inliers: int = 40
    """Accept a loop with at least this many verified matches."""
    min_inlier_ratio: float = 0.25
    """... which must also be at least this fraction of the matches tried (rejects lucky fits in clutter)."""
    min_inliers_with_planes: int = 20
    """Where both keyframes carry detected planes (RGB-D), a loop with fewer than ``min_inliers`` (but at least
    this many) RANSAC inliers is accepted when the planes confirm its pose: low-texture scenes rarely give 40
    matches between views a lap apart, yet their floor and walls, measured by every depth pixel, do not lie."""
    plane_check_deg: float = 3.0
    """Plane confirmation: a query plane moved into the match frame by the loop pose must agree with a match
    plane within this angle (degrees) ..."""
    plane_check_m: float = 0.04
    """... and this distance (m) ..."""
    plane_sigma_rad: float = 0.01
    """Noise of a plane's normal (rad) when confirming planes join the loop pose refinement ..."""
    plane_sigma_m: float = 0.01
    """... and of its distance (m)."""
    plane_check_min: int = 2
    """... for at least this many planes whose normals are mutually at least 30 degrees apart (one plane
    leaves three degrees of freedom unchecked; two non-parallel ones leave one)."""
    max_correction_m: float | None = None
    """If set, reject loops whose relative pose differs from the current estimate by more (m): a guard for
    maps whose drift is known to be small. None: no limit (loops exist to fix large drift)."""


@dataclass
class LoopResult:
    """A verified loop between the new keyframe (query) and an old one (match)."""

    query_id: int
    match_id: int
    T_match_query: np.ndarray  # [4, 4] pose of the query camera in the match camera frame
    inliers: int  # number of verified matches
    inlier_pairs: np.ndarray  # [K, 2] int: (query feature index, match feature index)
    score: float  # BoW score of the pair
    reproj_rmse_px: float = 0.0  # RMS reprojection error of the inliers after refinement
    covariance: np.ndarray | None = None  # [6, 6] of xi = [omega, v] in T_match_query * Exp(xi) (GTSAM order)
    candidates: list[tuple[int, float]] = field(default_factory=list)  # all BoW candidates (id, score) tried


@dataclass
class _Keyframe:
    """What the detector keeps per keyframe (descriptors and points None: read from the detector's feature store)."""

    descriptors: np.ndarray | None  # [N, 32] uint8
    points_cam: np.ndarray | None  # [N, 3] float64, NaN without depth
    T_wc: np.ndarray  # [4, 4]
    covisible: set[int]
    bow: BowVector
    planes: list[np.ndarray] = field(default_factory=list)  # [4] camera-frame plane coefficients


# --------------------------------------------------------------------------------------------------
# geometric verification (usable on its own, e.g. for relocalisation)
# --------------------------------------------------------------------------------------------------
def match_descriptors(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float = 0.8,
                      max_distance: int = 64) -> np.ndarray:
    """One-to-one ORB matches [K, 2] (index in a, index in b) passing the ratio test and a distance cap."""
    if len(desc_a) == 0 or len(desc_b) < 2:
        return np.zeros((0, 2), np.int64)
    idx, best, second = hamming_knn2(desc_a, desc_b)  # [N] each
    ok = (best <= max_distance) & (best < ratio * second)
    ia = np.nonzero(ok)[0]
    ib, dist = idx[ia], best[ia]
    # one-to-one: when several a-features pick the same b-feature keep the closest (then the lowest index)
    order = np.lexsort((ia, dist))
    _, first = np.unique(ib[order], return_index=True)
    keep = np.sort(order[first])
    return np.stack([ia[keep], ib[keep]], axis=1).astype(np.int64)


def _valid_points(points: np.ndarray) -> np.ndarray:
    """Rows [N] of camera-frame points [N, 3] that are finite and in front of the camera."""
    return np.all(np.isfinite(points), axis=1) & (points[:, 2] > 1e-6)


def _skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [N, 3, 3] of vectors [N, 3]: skew(a) @ b = a x b."""
    S = np.zeros((len(v), 3, 3))
    S[:, 0, 1], S[:, 0, 2], S[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    S[:, 1, 0], S[:, 2, 0], S[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return S


def _project(camera: Camera, T_cw: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted pixels [N, 2] and depths [N] of points [N, 3] mapped by T_cw into the camera."""
    X = pts @ T_cw[:3, :3].T + T_cw[:3, 3]  # [N, 3]
    z = X[:, 2]
    zs = np.where(np.abs(z) > 1e-9, z, 1e-9)
    uv = np.stack([camera.fx * X[:, 0] / zs + camera.cx, camera.fy * X[:, 1] / zs + camera.cy], axis=1)
    return uv, z


def _reproj_errors(camera: Camera, T_mq: np.ndarray, pts_m: np.ndarray, uv_q: np.ndarray) -> np.ndarray:
    """Pixel errors [N] of match-frame points [N, 3] seen by the query camera at T_mq (inf behind it)."""
    uv, z = _project(camera, invert(T_mq), pts_m)
    return np.where(z > 1e-6, np.linalg.norm(uv - uv_q, axis=1), np.inf)


def _point_sigma(camera: Camera, z: np.ndarray, cfg: "LoopClosureConfig") -> np.ndarray:
    """Std [N] (m) of a back-projected keypoint at depth z [N]: pixel error across the ray plus depth noise."""
    return np.hypot(cfg.pixel_sigma * z / camera.fx, cfg.depth_sigma_a + cfg.depth_sigma_b * z ** 2)


def _joint_refine(camera: Camera, T_mq: np.ndarray, pts_m: np.ndarray, uv_q: np.ndarray, pts_q: np.ndarray,
                  has_q3d: np.ndarray, cfg: "LoopClosureConfig", iterations: int = 10,
                  plane_pairs: list[tuple[np.ndarray, np.ndarray]] | None = None,
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton on T_mq with reprojection (match points -> query pixels) and 3D-3D residuals.

    Depth constrains what reprojection alone leaves loose (translation along the rays of distant points).
    ``plane_pairs`` (query plane [4], match plane [4]) add plane residuals (normal and distance, sigmas
    ``plane_sigma_rad`` and ``plane_sigma_m``): two non-parallel planes fix the rotation far better than a
    few dozen keypoints.
    Returns T_mq [4, 4], the covariance [6, 6] of xi in T_mq * Exp(xi) (xi = [omega, v] as in GTSAM),
    scaled up when the residuals are larger than the noise model says, and the leverage [N] of each match.
    """
    q3 = pts_q[has_q3d]  # [S, 3]
    m3 = pts_m[has_q3d]  # [S, 3]
    w3 = 1.0 / _point_sigma(camera, m3[:, 2], cfg)  # [S]

    pq = np.array([a for a, _ in plane_pairs or []]).reshape(-1, 4)  # [Q, 4] query planes
    pm = np.array([b for _, b in plane_pairs or []]).reshape(-1, 4)  # [Q, 4] their match-frame partners

    def plane_residuals(T: np.ndarray) -> np.ndarray:
        n = pq[:, :3] @ T[:3, :3].T  # [Q, 3] query normals in the match frame
        d = pq[:, 3] - n @ T[:3, 3]  # [Q]
        return np.concatenate([((n - pm[:, :3]) / cfg.plane_sigma_rad).ravel(), (d - pm[:, 3]) / cfg.plane_sigma_m])

    def residuals(T: np.ndarray) -> np.ndarray:
        uv, _ = _project(camera, invert(T), pts_m)
        r_px = ((uv - uv_q) / cfg.pixel_sigma).ravel()  # [2N]
        r_3d = ((q3 @ T[:3, :3].T + T[:3, 3] - m3) * w3[:, None]).ravel()  # [3S]
        return np.concatenate([r_px, r_3d, plane_residuals(T)])

    def jacobian(T: np.ndarray) -> np.ndarray:
        # T' = T Exp([w, v]) ~ (R (I + [w]x), t + R v). A query-frame point X = T'^-1 m moves by
        # Exp(-xi): dX = [X]x w - v. A 3D residual R' q + t' - m moves by -R [q]x w + R v.
        R, t = T[:3, :3], T[:3, 3]
        X = (pts_m - t) @ R  # [N, 3] = R^T (m - t)
        x, y, z = X[:, 0], X[:, 1], np.where(np.abs(X[:, 2]) > 1e-9, X[:, 2], 1e-9)
        P = np.zeros((len(X), 2, 3))  # d(uv)/dX
        P[:, 0, 0] = camera.fx / z
        P[:, 0, 2] = -camera.fx * x / z ** 2
        P[:, 1, 1] = camera.fy / z
        P[:, 1, 2] = -camera.fy * y / z ** 2
        dX = np.concatenate([_skew(X), np.broadcast_to(-np.eye(3), (len(X), 3, 3))], axis=2)  # [N, 3, 6]
        J_px = (P @ dX).reshape(-1, 6) / cfg.pixel_sigma  # [2N, 6]
        J_3d = np.concatenate([-R @ _skew(q3), np.broadcast_to(R, (len(q3), 3, 3))], axis=2)  # [S, 3, 6]
        J_3d = (J_3d * w3[:, None, None]).reshape(-1, 6)  # [3S, 6]
        # a query plane (n, d) maps to (R' n, d - (R' n) . t'): dn/dw = -R [n]x, dd/dw = t^T R [n]x, dd/dv = -n^T
        Sn = _skew(pq[:, :3])  # [Q, 3, 3]
        J_n = np.concatenate([-R @ Sn, np.zeros((len(pq), 3, 3))], axis=2).reshape(-1, 6) / cfg.plane_sigma_rad
        J_d = np.concatenate([np.einsum("i,qij->qj", t @ R, Sn), -pq[:, :3]], axis=1) / cfg.plane_sigma_m  # [Q, 6]
        return np.concatenate([J_px, J_3d, J_n, J_d])

    T = T_mq.copy()
    for _ in range(iterations):
        r, J = residuals(T), jacobian(T)
        H = J.T @ J
        try:
            dx = -np.linalg.solve(H, J.T @ r)
        except np.linalg.LinAlgError:
            break
        T_new = T @ se3_exp(dx)
        if np.sum(residuals(T_new) ** 2) > np.sum(r ** 2):  # no progress: keep the better pose
            break
        T = T_new
        if np.linalg.norm(dx) < 1e-10:
            break
    r, J = residuals(T), jacobian(T)
    dof = max(len(r) - 6, 1)
    try:
        H_inv = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return T, np.full((6, 6), np.inf), np.ones(len(pts_m))
    cov = H_inv * max(1.0, float(r @ r) / dof)
    # leverage of each match: its share of the fit (diagonal of the hat matrix J H^-1 J^T, summed over its
    # rows; all matches together sum to 6)
    h = np.einsum("ij,jk,ik->i", J, H_inv, J)  # [R]
    n = len(pts_m)
    lev = h[: 2 * n].reshape(n, 2).sum(axis=1)
    lev[has_q3d] += h[2 * n: 2 * n + 3 * len(q3)].reshape(-1, 3).sum(axis=1)
    return T, cov, lev


@dataclass
class PairVerification:
    """Geometric verification of two keyframes."""

    T_match_query: np.ndarray  # [4, 4] query camera in the match camera frame
    pairs: np.ndarray  # [K, 2] int inlier matches: (query feature index, match feature index)
    reproj_rmse_px: float  # RMS reprojection error of the inliers
    covariance: np.ndarray  # [6, 6] of xi = [omega, v] in T_match_query * Exp(xi)
    n_matches: int  # descriptor matches with a 3D point on the match side (the RANSAC input)


def matching_planes(T_mq: np.ndarray, planes_q: list[np.ndarray], planes_m: list[np.ndarray],
                    cfg: LoopClosureConfig) -> list[tuple[np.ndarray, np.ndarray]]:
    """Pairs (query plane [4], match plane [4]) that coincide once the query plane ([4], camera frame,
    n . x + d = 0) is moved into the match frame by T_mq [4, 4] (within ``plane_check_deg`` / ``plane_check_m``)."""
    cos_ok = np.cos(np.radians(cfg.plane_check_deg))
    pairs = []
    for pq in planes_q:
        moved = plane_to_world(pq, T_mq)  # the query plane in the match frame
        n, d = moved[:3], moved[3]
        close = [pm for pm in planes_m if float(n @ pm[:3]) >= cos_ok and abs(d - pm[3]) <= cfg.plane_check_m]
        if close:
            pairs.append((pq, min(close, key=lambda pm: abs(d - pm[3]))))
    return pairs


def planes_agree(T_mq: np.ndarray, planes_q: list[np.ndarray], planes_m: list[np.ndarray],
                 cfg: LoopClosureConfig) -> bool:
    """Whether at least ``cfg.plane_check_min`` mutually non-parallel query planes, moved into the match frame
    by T_mq [4, 4], coincide with planes of the match keyframe (see ``matching_planes``)."""
    agreeing: list[np.ndarray] = []
    for pq, _ in matching_planes(T_mq, planes_q, planes_m, cfg):
        n = T_mq[:3, :3] @ pq[:3]
        if all(abs(float(n @ a)) < np.cos(np.radians(30.0)) for a in agreeing):
            agreeing.append(n)
    return len(agreeing) >= cfg.plane_check_min


def verify_loop_pair(camera: Camera, uv_q: np.ndarray, desc_q: np.ndarray, pts_q: np.ndarray,
                     desc_m: np.ndarray, pts_m: np.ndarray,
                     cfg: LoopClosureConfig | None = None, planes_q: list[np.ndarray] | None = None,
                     planes_m: list[np.ndarray] | None = None) -> PairVerification | None:
    """Relative pose of a query keyframe in a match keyframe from their features (RGB-D), or None.

    Query: pixels ``uv_q`` [N, 2] of ``camera`` (distorted if it has distortion), ``desc_q`` [N, 32] uint8,
    camera-frame points ``pts_q`` [N, 3] (NaN rows: no depth). Match: ``desc_m`` [M, 32], ``pts_m`` [M, 3]
    (its pixels are not needed: its 3D points are projected into the query). Optional planes of both
    keyframes (camera coefficients [4]) allow a loop with fewer matches when they confirm it (see
    ``LoopClosureConfig.min_inliers_with_planes``).
    """
    cfg = cfg or LoopClosureConfig()
    out = _verify_by_features(camera, uv_q, desc_q, pts_q, desc_m, pts_m, cfg)
    if out is not None or not planes_q or not planes_m or cfg.min_inliers_with_planes >= cfg.min_inliers:
        return out
    return _verify_with_planes(camera, uv_q, desc_q, pts_q, desc_m, pts_m, planes_q, planes_m, cfg)


def _ransac_pnp(camera: Camera, uv_q, desc_q, pts_q, desc_m, pts_m, cfg: LoopClosureConfig, min_inliers: int):
    """Descriptor matches and a RANSAC PnP pose of the query in the match frame, or None with too few inliers.

    Returns (pairs [K, 2], match points obj [K, 3], query pixels img [K, 2] (undistorted), query points
    q3d [K, 3], has_q3d [K], RANSAC inlier mask [K], T_mq [4, 4])."""
    pairs = match_descriptors(desc_q, desc_m, cfg.ratio_test, cfg.max_hamming)  # [K, 2]
    pairs = pairs[_valid_points(pts_m[pairs[:, 1]])]  # PnP needs the match's 3D point
    if len(pairs) < max(min_inliers, 6):
        return None
    obj = np.ascontiguousarray(pts_m[pairs[:, 1]], np.float64)  # [K, 3] in the match camera
    img = np.ascontiguousarray(uv_q[pairs[:, 0]], np.float64)  # [K, 2] query pixels
    if camera.distortion:  # work on ideal pinhole pixels from here on
        img = cv2.undistortPoints(img.reshape(-1, 1, 2), camera.K, np.asarray(camera.distortion, np.float64),
                                  P=camera.K).reshape(-1, 2)
    found = pnp_ransac(obj, img, camera.K, cfg.ransac_iterations, cfg.ransac_reproj_px, cfg.ransac_confidence)
    if found is None or len(found[1]) < min_inliers:
        return None
    T_mq, inl = found
    keep = np.zeros(len(pairs), bool)
    keep[inl] = True
    q3d = pts_q[pairs[:, 0]]  # [K, 3] the query's own back-projections (NaN without depth)
    return pairs, obj, img, q3d, _valid_points(q3d), keep, T_mq


def _verify_with_planes(camera: Camera, uv_q, desc_q, pts_q, desc_m, pts_m, planes_q, planes_m,
                        cfg: LoopClosureConfig) -> PairVerification | None:
    """Few-match verification: RANSAC PnP, one joint refinement of its inliers, then the planes must agree."""
    found = _ransac_pnp(camera, uv_q, desc_q, pts_q, desc_m, pts_m, cfg, cfg.min_inliers_with_planes)
    if found is None:
        return None
    pairs, obj, img, q3d, has_q3d, keep, T_mq = found
    if keep.sum() < cfg.min_inlier_ratio * len(pairs):
        return None
    T_mq, cov, _ = _joint_refine(camera, T_mq, obj[keep], img[keep], q3d[keep], has_q3d[keep], cfg)
    if not _covariance_ok(cov, cfg) or not planes_agree(T_mq, planes_q, planes_m, cfg):
        return None
    # the planes measure the rotation better than a few dozen keypoints: refine with them
    T_mq, cov, _ = _joint_refine(camera, T_mq, obj[keep], img[keep], q3d[keep], has_q3d[keep], cfg,
                                 plane_pairs=matching_planes(T_mq, planes_q, planes_m, cfg))
    if not planes_agree(T_mq, planes_q, planes_m, cfg):
        return None
    return _verified(camera, T_mq, cov, pairs, obj, img, keep)


def _verify_by_features(camera: Camera, uv_q, desc_q, pts_q, desc_m, pts_m,
                        cfg: LoopClosureConfig) -> PairVerification | None:
    """Verification from matches alone (enough of them, none carrying the fit alone, a tight covariance)."""
    found = _ransac_pnp(camera, uv_q, desc_q, pts_q, desc_m, pts_m, cfg, cfg.min_inliers)
    if found is None:
        return None
    pairs, obj, img, q3d, has_q3d, keep, T_mq = found
    tol = np.maximum(cfg.max_point_dist_m, cfg.max_point_dist_rel * obj[:, 2])  # [K]
    banned = np.zeros(len(pairs), bool)  # matches that alone carried too much of the fit
    for _ in range(8):  # refine on the inliers, then re-select them with the tighter thresholds
        if keep.sum() < 6:
            return None
        T_mq, cov, lev = _joint_refine(camera, T_mq, obj[keep], img[keep], q3d[keep], has_q3d[keep], cfg)
        banned[np.nonzero(keep)[0][lev > cfg.max_leverage]] = True
        gap = np.linalg.norm(q3d @ T_mq[:3, :3].T + T_mq[:3, 3] - obj, axis=1)  # NaN without query depth
        new = (_reproj_errors(camera, T_mq, obj, img) < cfg.refine_reproj_px) & ~banned
        new &= ~has_q3d | (gap < tol)  # where the query has depth, both back-projections must agree
        if np.array_equal(new, keep):
            break
        keep = new
    else:
        if keep.sum() < 6:
            return None
        T_mq, cov, _ = _joint_refine(camera, T_mq, obj[keep], img[keep], q3d[keep], has_q3d[keep], cfg)
    n_in = int(keep.sum())
    if n_in < cfg.min_inliers or n_in < cfg.min_inlier_ratio * len(pairs):
        return None
    if not _covariance_ok(cov, cfg):
        return None
    return _verified(camera, T_mq, cov, pairs, obj, img, keep)


def _covariance_ok(cov: np.ndarray, cfg: LoopClosureConfig) -> bool:
    """Whether a pose covariance [6, 6] (rotation rad, then translation m) is finite and inside the gates."""
    std = np.sqrt(np.abs(np.diag(cov)))  # [6]
    return bool(np.all(np.isfinite(std)) and std[3:].max() <= cfg.max_sigma_trans_m
                and np.degrees(std[:3].max()) <= cfg.max_sigma_rot_deg)


def _verified(camera: Camera, T_mq, cov, pairs, obj, img, keep) -> PairVerification:
    """The accepted verification: pose, inlier pairs, their RMS reprojection error and the covariance."""
    rmse = float(np.sqrt(np.mean(_reproj_errors(camera, T_mq, obj[keep], img[keep]) ** 2)))
    return PairVerification(T_mq, pairs[keep], rmse, cov, len(pairs))


# --------------------------------------------------------------------------------------------------
# detector
# --------------------------------------------------------------------------------------------------
class LoopDetector:
    """Keeps every keyframe's features and BoW vector and reports verified loops as keyframes arrive.

    Given the SLAM map's ``feature_store`` (a ``FeatureStore`` holding every keyframe it is told about), it keeps
    no copy of the keyframes' descriptors and points: a candidate's are read from the store when it is verified."""

    def __init__(self, camera: Camera, vocabulary: Vocabulary | None = None, cfg: LoopClosureConfig | None = None,
                 feature_store: FeatureStore | None = None):
        self.camera = camera
        self.feature_store = feature_store
        self.vocabulary = vocabulary if vocabulary is not None else Vocabulary.default()
        self.cfg = cfg or LoopClosureConfig()
        self.database = KeyframeDatabase()
        self.keyframes: dict[int, _Keyframe] = {}  # insertion order = keyframe order
        self._groups: list[tuple[set[int], int]] = []  # consistent candidate regions of the last query
        self.last_candidates: list[tuple[int, float]] = []  # BoW candidates of the last query (diagnostics)

    def __len__(self) -> int:
        return len(self.keyframes)

    def remove_keyframe(self, kf_id: int) -> None:
        """Forget a culled keyframe."""
        self.keyframes.pop(int(kf_id), None)
        self.database.remove(int(kf_id))

    def update_poses(self, poses: dict[int, np.ndarray]) -> None:
        """Take new pose estimates T_wc [4, 4] (after bundle adjustment or a pose-graph optimisation)."""
        for k, T in poses.items():
            if int(k) in self.keyframes:
                self.keyframes[int(k)].T_wc = np.asarray(T, np.float64).copy()

    def set_covisible(self, kf_id: int, covisible: set[int]) -> None:
        """Replace a keyframe's covisible set (the covisibility graph grows after it is added)."""
        if int(kf_id) in self.keyframes:
            self.keyframes[int(kf_id)].covisible = {int(c) for c in covisible}

    def add_keyframe(self, kf_id: int, uv: np.ndarray, descriptors: np.ndarray, points_cam: np.ndarray,
                     T_wc: np.ndarray, covisible: set[int] | None = None,
                     planes: list[np.ndarray] | None = None) -> LoopResult | None:
        """Add a keyframe (uv [N, 2], descriptors [N, 32] uint8, points_cam [N, 3] NaN = no depth, optional
        planes: camera-frame coefficients [4] each) and return a verified loop to an older keyframe, or None."""
        kf_id = int(kf_id)
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        descriptors = np.ascontiguousarray(descriptors, np.uint8).reshape(-1, 32)
        points_cam = np.asarray(points_cam, np.float64).reshape(-1, 3)
        if not len(uv) == len(descriptors) == len(points_cam):
            raise ValueError(f"keyframe {kf_id}: uv, descriptors and points_cam must have the same length, got "
                             f"{len(uv)}, {len(descriptors)}, {len(points_cam)}")
        covisible = {int(c) for c in (covisible or set())} - {kf_id}
        bow = self.vocabulary.transform(descriptors)
        planes = [np.asarray(p, np.float64).reshape(4) for p in (planes or [])]
        result = self._detect(kf_id, uv, descriptors, points_cam, np.asarray(T_wc, np.float64), covisible, bow,
                              planes)
        self.remove_keyframe(kf_id)  # re-adding an id replaces it
        kept = (None, None) if self.feature_store is not None else (descriptors, points_cam)
        self.keyframes[kf_id] = _Keyframe(*kept, np.asarray(T_wc, np.float64).copy(), covisible, bow, planes)
        self.database.add(kf_id, bow)
        return result

    # ---- steps ----
    def _candidates(self, kf_id: int, covisible: set[int], bow: BowVector) -> list[tuple[int, float]]:
        """BoW candidates (id, score) above the adaptive threshold, best first."""
        cfg = self.cfg
        if len(self.keyframes) < cfg.min_keyframes or len(bow) == 0:
            return []
        recent = list(self.keyframes)[-cfg.exclude_recent:] if cfg.exclude_recent > 0 else []
        exclude = covisible | set(recent) | {kf_id}
        ref = list(self.database.score(bow, covisible).values())
        threshold = max(cfg.min_score, cfg.min_score_ratio * (float(np.median(ref)) if ref else 0.0))
        return self.database.query(bow, top_k=cfg.top_k, exclude=exclude, min_score=threshold)

    def _consistent(self, candidates: list[tuple[int, float]]) -> list[tuple[int, float]]:
        """Candidates whose region was also found by the previous keyframes (``consistency`` in a row)."""
        need = self.cfg.consistency
        groups: list[tuple[set[int], int]] = []
        passed = []
        for cid, score in candidates:
            region = {cid} | self.keyframes[cid].covisible
            count = 1 + max((c for g, c in self._groups if g & region), default=0)
            groups.append((region, count))
            if count >= need:
                passed.append((cid, score))
        self._groups = groups
        return passed

    def _detect(self, kf_id, uv, desc, pts, T_wc, covisible, bow, planes=None) -> LoopResult | None:
        """Candidates, then geometric verification; the verified candidate with most inliers wins."""
        cands = self._candidates(kf_id, covisible, bow)
        if self.cfg.consistency > 1:
            cands = self._consistent(cands)
        self.last_candidates = cands
        best: LoopResult | None = None
        for cid, score in cands:
            kf = self.keyframes[cid]
            if kf.descriptors is None:
                f = self.feature_store.get(cid)
                kf_desc, kf_pts = f.descriptors, f.points_cam
            else:
                kf_desc, kf_pts = kf.descriptors, kf.points_cam
            out = verify_loop_pair(self.camera, uv, desc, pts, kf_desc, kf_pts, self.cfg, planes, kf.planes)
            if out is None:
                continue
            if self.cfg.max_correction_m is not None:
                predicted = invert(kf.T_wc) @ T_wc  # current estimate of the same relative pose
                if np.linalg.norm(predicted[:3, 3] - out.T_match_query[:3, 3]) > self.cfg.max_correction_m:
                    continue
            if best is None or len(out.pairs) > best.inliers:
                best = LoopResult(kf_id, cid, out.T_match_query, len(out.pairs), out.pairs, score,
                                  out.reproj_rmse_px, out.covariance, list(cands))
        return best
