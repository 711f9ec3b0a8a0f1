"""GCGR's pull on the keyframes of a finished run: where the map's rendered depth and normals alone take each pose.

For every keyframe of a run with a Gaussian map and ground truth, and for each start pose (``estimate``: the run's
final keyframe pose; ``gt``: the ground truth brought into the run's world frame by an SE(3) alignment of all
frames that uses their orientations;
``gt_calibrated``: the same with one constant camera offset removed, ``gt_i X`` with X the rigid mean of
``gt_i^-1 est_i`` over the keyframes, i.e. the ground truth as it would be with the estimate's camera-to-marker
calibration: a motion-capture ground truth whose hand-eye rotation is a degree off tilts every pose alike, and at
2 m a degree moves the rendered surface by 3.5 cm, which the factors would read as a pose error), the
keyframe's GCGR factors (``factors/gcgr.py``, built as local BA builds them, with the run's ``gcgr.*`` settings or
overrides) are optimized alone under a weak prior at the start pose (it only fixes directions the map leaves
free, e.g. along a single wall). Reported per keyframe and start:
- the pull: how far the pose moved (cm, degrees), and its distance to the ground truth before and after;
- what the factors saw: usable pixels, the map's depth bias against the sensor depth at those pixels (median
  ``D_hat - D``, mm) and its spread, and the bias by depth range (Kinect depth noise grows with depth squared).
If GCGR is right, both starts converge near the ground truth; if they converge on each other away from it, the map
and the sensor depth agree with each other and not with the ground truth; if the estimate stays put and the
ground-truth start is pulled onto it, the map confirms the poses it was built from (self-confirmation).

Conventions: poses are camera-to-world ``T_wc`` [4, 4] in the run's world frame (OpenCV camera axes); a pose
difference is measured as ``T_a^-1 T_b`` (rotation angle in degrees, translation length in cm).
"""
from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from ggfslam.errors import RunDirError
from ggfslam.geometry.se3 import invert, make_pose, mean_rotation, rotation_angle

DEPTH_BINS = (0.0, 1.0, 2.0, 3.0, 4.0, np.inf)  # m, for the bias by depth range
STARTS = ("estimate", "gt", "gt_calibrated")


def pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(translation cm, rotation degrees) of ``T_a^-1 T_b`` for camera-to-world poses [4, 4]."""
    D = invert(T_a) @ T_b
    return 100.0 * float(np.linalg.norm(D[:3, 3])), float(np.degrees(rotation_angle(D[:3, :3])))


def rigid_mean(Ts: np.ndarray) -> np.ndarray:
    """Mean [4, 4] of rigid transforms [N, 4, 4]: chordal mean rotation, mean translation."""
    return make_pose(mean_rotation(Ts[:, :3, :3]), Ts[:, :3, 3].mean(axis=0))


def run_keyframes(run_dir: Path, ckpt: dict) -> tuple[list[int], dict[int, np.ndarray], dict[int, np.ndarray]]:
    """The run's keyframe ids, their final poses and their ground-truth poses in the run's world frame, aligned over
    all frames with their orientations (``ground_truth_alignment``: the ATE's position-only fit leaves the rotation
    about a short path loose, 6 degrees on a 24-frame synthetic run, which renders as a pull); keyframes without
    ground truth are left out."""
    from ggfslam.data.trajectory_io import read_tum_trajectory
    from ggfslam.data.tum import associate
    from ggfslam.eval.mesh_geometry import ground_truth_alignment
    from ggfslam.render_run import tracking_log
    from ggfslam.rundir import GROUNDTRUTH_FILE, TRACKING_LOG_FILE, TRAJECTORY_FILE

    for name in (GROUNDTRUTH_FILE, TRAJECTORY_FILE, TRACKING_LOG_FILE):
        if not (run_dir / name).is_file():
            raise RunDirError(f"{run_dir}: {name} missing (GCGR's pull is measured against the ground truth of a "
                              f"finished run)")
    est_stamps, est_poses = read_tum_trajectory(run_dir / TRAJECTORY_FILE)
    gt_stamps, gt_poses = read_tum_trajectory(run_dir / GROUNDTRUTH_FILE)
    A, _ = ground_truth_alignment(est_stamps, est_poses, gt_stamps, gt_poses)
    to_run = invert(A)  # ground-truth world -> the run's world
    index, stamps, _ = tracking_log(run_dir / TRACKING_LOG_FILE)
    frame_stamp = dict(zip(index.tolist(), stamps.tolist()))
    poses = {int(k): np.asarray(T, np.float64) for k, T in ckpt["keyframe_poses"].items()}
    kf_frames = {int(k): int(v) for k, v in ckpt["kf_frames"].items()}
    logged = [k for k in sorted(poses) if kf_frames.get(k, -1) in frame_stamp]
    kf_idx, gt_idx = associate(np.array([frame_stamp[kf_frames[k]] for k in logged]), gt_stamps, 0.02)
    gt = {logged[i]: to_run @ gt_poses[j] for i, j in zip(kf_idx, gt_idx)}
    ids = [k for k in sorted(poses) if k in gt]
    return ids, poses, gt


def pull_keyframe(source, kf_id: int, T_start: np.ndarray, prior_sigmas: tuple[float, float] = (0.2, 0.2),
                  iterations: int = 20) -> dict | None:
    """Optimize one keyframe's pose with its GCGR factors alone (a weak prior of ``prior_sigmas`` rad, m at the
    start); returns the end pose and what the factors saw, or None when the keyframe gets no factor."""
    from factors.gcgr import DEPTH_WEIGHT, residual_rows
    from ggfslam.backend.local_ba import IndeterminateSystem, optimize_lm

    model = source.build(kf_id, T_start)
    if model is None:
        return None
    fs = model.factors()
    if not fs:
        return None
    rd, _, valid = residual_rows(model.view, model.sensor, model.pixels)
    d = model.sensor.depth.reshape(-1)[model.pixels][valid]  # [N] sensor depth at the used pixels, m
    bias = rd[valid] / DEPTH_WEIGHT  # [N] D_hat - D, m
    by_range = {}
    for lo, hi in zip(DEPTH_BINS[:-1], DEPTH_BINS[1:]):
        sel = (d >= lo) & (d < hi)
        if sel.sum() >= 10:
            by_range[f"{lo:g}-{hi:g}m"] = {"pixels": int(sel.sum()), "bias_mm": 1000 * float(np.median(bias[sel]))}
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(X(kf_id), gtsam.Pose3(T_start), gtsam.noiseModel.Diagonal.Sigmas(
        np.array([prior_sigmas[0]] * 3 + [prior_sigmas[1]] * 3))))
    for f in fs.values():
        graph.add(f)
    values = gtsam.Values()
    values.insert(X(kf_id), gtsam.Pose3(T_start))
    try:
        T_end = optimize_lm(graph, values, iterations).atPose3(X(kf_id)).matrix()
    except IndeterminateSystem:
        return None
    return {"T_end": T_end, "pixels": int(len(model)), "valid": int(valid.sum()),
            "depth_bias_mm": 1000 * float(np.median(bias)) if len(bias) else float("nan"),
            "depth_abs_mm": 1000 * float(np.median(np.abs(bias))) if len(bias) else float("nan"),
            "bias_by_depth": by_range}


def keyframe_pulls(run_dir: str | Path, overrides: list[str] | None = None, starts: tuple[str, ...] = STARTS,
                   prior_sigmas: tuple[float, float] = (0.2, 0.2), every: int = 1) -> dict:
    """GCGR's pull on every ``every``-th keyframe of a finished run from each start (module docstring): per-keyframe
    rows and a summary per start."""
    from ggfslam.backend.gcgr_source import GCGRSource
    from ggfslam.config import load_config
    from ggfslam.rundir import CONFIG_FILE
    from ggfslam.saved_run import load_mapper, run_camera

    unknown = set(starts) - set(STARTS)
    if unknown:
        raise ValueError(f"unknown start(s) {sorted(unknown)}; choose from {', '.join(STARTS)}")
    run_dir = Path(run_dir)
    config, mapper, ckpt = load_mapper(run_dir)
    gcfg = load_config(run_dir / CONFIG_FILE, list(overrides or [])).gcgr if overrides else config.gcgr
    # every model here is rendered on purpose (``build``), and again as GCGR alone moves it: the per-BA render
    # budget and gcgr.relinearize do not apply
    gcfg = gcfg.model_copy(update={"renders_per_ba": max(gcfg.renders_per_ba or 0, 1), "relinearize": "render"})
    ids, est, gt = run_keyframes(run_dir, ckpt)
    if not ids:
        raise RunDirError(f"{run_dir}: no keyframe has a ground-truth pose")
    X_cal = rigid_mean(np.stack([np.linalg.inv(gt[k]) @ est[k] for k in ids]))  # [4, 4] constant camera offset
    cal = {k: gt[k] @ X_cal for k in ids}
    # one source serves every start: ``build`` renders at the start pose and replaces the keyframe's cached model
    source = GCGRSource(mapper, run_camera(run_dir), gcfg)
    rows = []
    for k in ids[::every]:
        for start in starts:
            T0 = {"estimate": est, "gt": gt, "gt_calibrated": cal}[start][k]
            r = pull_keyframe(source, k, T0, prior_sigmas)
            if r is None:
                rows.append({"kf": k, "start": start, "pixels": 0})
                continue
            T1 = r.pop("T_end")
            moved = pose_difference(T0, T1)
            row = {"kf": k, "start": start, **r, "moved_cm": moved[0], "moved_deg": moved[1]}
            for name, ref in (("gt", gt[k]), ("cal", cal[k])):
                before, after = pose_difference(ref, T0), pose_difference(ref, T1)
                row |= {f"{name}_before_cm": before[0], f"{name}_before_deg": before[1],
                        f"{name}_after_cm": after[0], f"{name}_after_deg": after[1]}
            to_est = pose_difference(est[k], T1)
            rows.append(row | {"est_after_cm": to_est[0], "est_after_deg": to_est[1]})
    offset = pose_difference(np.eye(4), X_cal)
    return {"run": str(run_dir), "calibration_offset": {"cm": offset[0], "deg": offset[1]},
            "gcgr": {"width": source.intr.width, "height": source.intr.height, "overrides": list(overrides or [])},
            "prior_sigmas": list(prior_sigmas), "keyframes": len(ids[::every]), "rows": rows,
            "summary": {s: summarize([r for r in rows if r["start"] == s]) for s in starts}}


def summarize(rows: list[dict]) -> dict:
    """Medians over keyframes of one start's rows, and the shares of keyframes the pull brought nearer the ground
    truth and the calibrated ground truth (translation)."""
    used = [r for r in rows if r.get("pixels", 0) > 0]
    if not used:
        return {"keyframes": 0}

    def med(key):
        return float(np.median([r[key] for r in used]))

    bins = sorted({b for r in used for b in r["bias_by_depth"]}, key=lambda b: float(b.split("-")[0]))
    dist = {f"{n}_{w}_{u}": med(f"{n}_{w}_{u}")
            for n in ("gt", "cal") for w in ("before", "after") for u in ("cm", "deg")}
    return {"keyframes": len(used), "pixels": med("pixels"), "moved_cm": med("moved_cm"), "moved_deg": med("moved_deg"),
            **dist, "est_after_cm": med("est_after_cm"), "depth_bias_mm": med("depth_bias_mm"),
            "depth_abs_mm": med("depth_abs_mm"),
            "nearer_gt": float(np.mean([r["gt_after_cm"] < r["gt_before_cm"] for r in used])),
            "nearer_cal": float(np.mean([r["cal_after_cm"] < r["cal_before_cm"] for r in used])),
            "bias_by_depth_mm": {b: float(np.median([r["bias_by_depth"][b]["bias_mm"] for r in used
                                                     if b in r["bias_by_depth"]])) for b in bins}}
