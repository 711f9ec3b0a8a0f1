"""Geometry of a rendered map against the ground-truth mesh: depth L1 and normal error per frame.

The estimated trajectory lives in its own world frame; an SE(3) alignment fitted to all frames' poses
(``ground_truth_alignment``) maps it onto the ground truth, so frame i is ray cast in the mesh at
``A @ T_est_i`` while the map is rendered at ``T_est_i``: pose errors remain in the figures as they would for any user of the map, and
sensor noise does not (the reference is the mesh, not the noisy input depth). With the dataset given, only
pixels where the input frame had depth count (the surface the map was asked to learn: not the ranges and
edges a depth sensor drops, where the mesh has depth and the map has none).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d

from ggfslam.data.types import Camera
from ggfslam.eval.image import depth_l1_cm, normal_error_deg
from ggfslam.eval.trajectory import ATE, associate
from ggfslam.geometry.depth import normals_from_depth
from ggfslam.geometry.se3 import mean_rotation
from ggfslam.mapping.keyframe_store import resize_depth


def ground_truth_alignment(est_stamps: np.ndarray, est_poses: np.ndarray, gt_stamps: np.ndarray,
                           gt_poses: np.ndarray, max_diff: float = 0.02) -> tuple[np.ndarray, float]:
    """SE(3) [4, 4] taking the estimate's world frame onto the ground truth's, and the ATE RMSE (cm).

    The transform is the chordal mean over timestamp-matched frames of ``T_gt_i inv(T_est_i)``: it uses the
    orientations, not only the positions. The ATE's position-only Umeyama fit leaves the rotation about a
    short, nearly straight path loose; a degree of it moves a wall 3 m away by 5 cm."""
    ate = ATE(max_diff)
    ate.process_data((est_stamps, est_poses, gt_stamps, gt_poses))
    ref, est = associate(est_stamps, est_poses, gt_stamps, gt_poses, max_diff)
    gt, es = np.asarray(ref.poses_se3), np.asarray(est.poses_se3)  # [M, 4, 4] each, matched
    rel = gt @ np.linalg.inv(es)  # [M, 4, 4], each T_gt inv(T_est)
    R = mean_rotation(rel[:, :3, :3])
    A = np.eye(4)
    A[:3, :3] = R
    A[:3, 3] = (gt[:, :3, 3] - es[:, :3, 3] @ R.T).mean(axis=0)
    return A, 100 * ate.get_statistic("rmse")


def mesh_geometry_metrics(mapper, mesh: o3d.geometry.TriangleMesh | str | Path, est_stamps: np.ndarray,
                          est_poses: np.ndarray, gt_stamps: np.ndarray, gt_poses: np.ndarray, intr,
                          stride: int = 5, max_diff: float = 0.02, dataset=None) -> dict:
    """Mean depth L1 (cm) and normal error (degrees) of the map rendered at every ``stride``-th estimated pose
    [N, 4, 4] against the mesh ray cast at the aligned pose (intrinsics ``intr``), and the ATE; with
    ``dataset`` (frame i = pose i) only over pixels where frame i has depth."""
    from ggfslam.data.synthetic import MeshRaycaster

    if not isinstance(mesh, o3d.geometry.TriangleMesh):
        mesh = o3d.io.read_triangle_mesh(str(mesh))
        if len(mesh.triangles) == 0:
            raise ValueError(f"{mesh}: no triangles")
    A, ate_cm = ground_truth_alignment(est_stamps, est_poses, gt_stamps, gt_poses, max_diff)
    caster = MeshRaycaster(mesh)
    cam = Camera(fx=intr.fx, fy=intr.fy, cx=intr.cx, cy=intr.cy, width=intr.width, height=intr.height)
    depth_l1, normal_err = [], []
    for i in range(0, len(est_poses), stride):
        ref = caster.cast(cam, A @ est_poses[i])["depth"].astype(np.float32)  # [H, W], 0 = no hit
        if dataset is not None:
            ref = np.where(resize_depth(dataset[i].depth, intr) > 0, ref, 0.0).astype(np.float32)
        out = mapper.render(est_poses[i], intr, planar=False)
        depth_l1.append(depth_l1_cm(out.depth.numpy(), ref))
        ref_n = normals_from_depth(ref, intr.fx, intr.fy, intr.cx, intr.cy)
        normal_err.append(normal_error_deg(out.normals.numpy(), ref_n))
    return {"mesh_depth_l1_cm": float(np.nanmean(depth_l1)), "mesh_normal_error_deg": float(np.nanmean(normal_err)),
            "mesh_frames": len(depth_l1), "ate_rmse_cm": ate_cm}
