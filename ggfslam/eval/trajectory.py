"""Trajectory metrics through evo: ATE (SE(3) Umeyama alignment, no scale) and RPE, timestamp-associated."""
from __future__ import annotations

import numpy as np
from evo.core import metrics as evo_metrics
from evo.core import sync
from evo.core.geometry import GeometryException
from evo.core.trajectory import PoseTrajectory3D

from ggfslam.eval.base import Metric
from ggfslam.geometry.se3 import pose_to_tum


def to_evo(stamps: np.ndarray, poses: np.ndarray) -> PoseTrajectory3D:
    """evo trajectory from timestamps [N] and camera-to-world poses [N, 4, 4]."""
    tum = np.stack([pose_to_tum(T) for T in poses])  # [N, 7] tx ty tz qx qy qz qw
    quat_wxyz = tum[:, [6, 3, 4, 5]]  # evo stores w first
    return PoseTrajectory3D(tum[:, :3], quat_wxyz, np.asarray(stamps, dtype=np.float64))


def associate(
    est_stamps: np.ndarray, est_poses: np.ndarray, gt_stamps: np.ndarray, gt_poses: np.ndarray, max_diff: float
) -> tuple[PoseTrajectory3D, PoseTrajectory3D]:
    """Pair estimated and ground-truth poses by nearest timestamp within ``max_diff`` seconds."""
    ref, est = to_evo(gt_stamps, gt_poses), to_evo(est_stamps, est_poses)
    try:
        ref, est = sync.associate_trajectories(ref, est, max_diff=max_diff)
    except sync.SyncException as e:
        raise ValueError(f"cannot associate estimated and ground-truth poses: {e}") from None
    return ref, est


class ATE(Metric):
    """Absolute trajectory error (translation, metres) after SE(3) Umeyama alignment without scale."""

    name, unit = "ATE", "m"

    def __init__(self, max_diff: float = 0.02, align: bool = True) -> None:
        super().__init__()
        self.max_diff, self.align = max_diff, align
        self.num_pairs = 0
        self.alignment: np.ndarray | None = None  # [4, 4] applied to the estimate

    def process_data(self, data) -> None:
        """``data`` = (est_stamps [N], est_poses [N,4,4], gt_stamps [M], gt_poses [M,4,4])."""
        est_stamps, est_poses, gt_stamps, gt_poses = data
        ref, est = associate(est_stamps, est_poses, gt_stamps, gt_poses, self.max_diff)
        if self.align:
            if ref.num_poses < 3:
                raise ValueError(f"ATE alignment needs at least 3 associated poses, got {ref.num_poses}")
            try:
                r, t, _ = est.align(ref, correct_scale=False)
            except GeometryException as e:  # e.g. every estimate at one point: a lost tracker
                raise ValueError(f"cannot align the trajectories: {e}") from None
            self.alignment = np.eye(4)
            self.alignment[:3, :3], self.alignment[:3, 3] = r, t
        ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
        ape.process_data((ref, est))
        self.values.extend(np.asarray(ape.error, dtype=np.float64).tolist())
        self.num_pairs += ref.num_poses


class RPE(Metric):
    """Relative pose error (translation, metres) over a fixed frame distance ``delta``."""

    name, unit = "RPE", "m"

    def __init__(self, max_diff: float = 0.02, delta: int = 1, relation: str = "translation") -> None:
        super().__init__()
        self.max_diff, self.delta = max_diff, delta
        self.relation = {
            "translation": evo_metrics.PoseRelation.translation_part,
            "rotation": evo_metrics.PoseRelation.rotation_angle_deg,
        }[relation]
        if relation == "rotation":
            self.unit = "deg"

    def process_data(self, data) -> None:
        """``data`` = (est_stamps [N], est_poses [N,4,4], gt_stamps [M], gt_poses [M,4,4])."""
        ref, est = associate(*data, max_diff=self.max_diff)
        if ref.num_poses <= self.delta:
            raise ValueError(f"RPE with delta {self.delta} needs more than {self.delta} associated poses")
        rpe = evo_metrics.RPE(self.relation, delta=self.delta, delta_unit=evo_metrics.Unit.frames, all_pairs=False)
        rpe.process_data((ref, est))
        self.values.extend(np.asarray(rpe.error, dtype=np.float64).tolist())


def trajectory_metrics(
    est_stamps: np.ndarray, est_poses: np.ndarray, gt_stamps: np.ndarray, gt_poses: np.ndarray,
    max_diff: float = 0.02, rpe_delta: int = 1,
) -> dict[str, float]:
    """ATE RMSE/mean/max (cm), RPE translation RMSE (cm) and rotation RMSE (deg), and the pair count."""
    ate = ATE(max_diff)
    ate.process_data((est_stamps, est_poses, gt_stamps, gt_poses))
    out = {
        "ate_rmse_cm": 100 * ate.get_statistic("rmse"),
        "ate_mean_cm": 100 * ate.get_statistic("mean"),
        "ate_max_cm": 100 * ate.get_statistic("max"),
        "ate_pairs": ate.num_pairs,
    }
    if ate.num_pairs > rpe_delta:
        rpe_t = RPE(max_diff, rpe_delta, "translation")
        rpe_t.process_data((est_stamps, est_poses, gt_stamps, gt_poses))
        rpe_r = RPE(max_diff, rpe_delta, "rotation")
        rpe_r.process_data((est_stamps, est_poses, gt_stamps, gt_poses))
        out["rpe_trans_rmse_cm"] = 100 * rpe_t.get_statistic("rmse")
        out["rpe_rot_rmse_deg"] = rpe_r.get_statistic("rmse")
    return out
