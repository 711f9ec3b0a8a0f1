"""Rendering quality of a Gaussian map over every frame of a sequence, from the estimated poses."""
from __future__ import annotations

import time

import numpy as np

from ggfslam.eval.image import (COLOUR_SPLIT_KEYS, DEPTH_SPLIT_KEYS, LPIPS, colour_error_split, depth_error_split,
                                depth_l1_cm, normal_error_deg, psnr, ssim_np)
from ggfslam.geometry.depth import normals_from_depth
from ggfslam.mapping.keyframe_store import resize_depth, resize_rgbd


def nearest_keyframes(frame_indices: np.ndarray, kf_frames: dict[int, int]) -> np.ndarray:
    """For each frame index [N], the keyframe id whose frame is closest in the sequence (-1 if none)."""
    if not kf_frames:
        return np.full(len(frame_indices), -1, np.int64)
    ids = np.array(sorted(kf_frames, key=lambda k: kf_frames[k]))
    at = np.array([kf_frames[k] for k in ids])
    pos = np.searchsorted(at, frame_indices).clip(1, len(at) - 1) if len(at) > 1 else np.zeros(len(frame_indices), int)
    if len(at) == 1:
        return np.full(len(frame_indices), ids[0])
    left = np.abs(frame_indices - at[pos - 1]) <= np.abs(at[pos] - frame_indices)
    return np.where(left, ids[pos - 1], ids[pos])


def render_metrics(mapper, dataset, poses: np.ndarray, indices: np.ndarray, intr, lpips: LPIPS | None = None) -> dict:
    """PSNR, SSIM, depth L1 (cm), normal error (degrees) and LPIPS of renders at ``poses`` [N, 4, 4] against
    frames ``indices`` [M].

    Frames are resized to ``intr``; each frame uses the exposure of its nearest keyframe. Depth L1 and the
    normal error (rendered normals against normals of the reference depth, both by the same finite
    differences) use the noise-free depth of the ground-truth mesh where the dataset has it
    (``frame.meta['depth_gt']``, synthetic sequences with depth noise), else the sensor depth; with
    ``depth_gt`` the L1 against the sensor depth is also reported (``depth_l1_sensor_cm``). Where the depth L1
    comes from (holes, the tail beyond 5 cm and its part at depth discontinuities, the median) is split out as
    ``depth_error_split`` does; what gross-error regions (changing content) take from the PSNR as
    ``colour_error_split`` does. Returns the means, the render speed and the per-frame values."""
    kf_frames = {k: mapper.store.frame_index(k) for k in mapper.store.ids()}
    exposure = nearest_keyframes(np.asarray(indices), kf_frames)
    rows, render_s = [], 0.0
    for i, e in zip(indices, exposure):
        frame = dataset[int(i)]
        gt_depth = frame.meta.get("depth_gt")
        rgb, sensor_depth = resize_rgbd(frame.rgb, frame.depth, intr)
        depth = sensor_depth if gt_depth is None else resize_depth(gt_depth, intr)
        t0 = time.perf_counter()
        out = mapper.render(poses[int(i)], intr, exposure_kf=int(e) if e >= 0 else None, planar=False)
        render_s += time.perf_counter() - t0
        img, depth_img = out.color.numpy(), out.depth.numpy()  # [H, W, 3], [H, W]
        ref_normals = normals_from_depth(depth, intr.fx, intr.fy, intr.cx, intr.cy)
        # the rendered depth's normals by the compiled rule (out.normals is the same rule in torch, ~4x slower)
        normals = normals_from_depth(depth_img, intr.fx, intr.fy, intr.cx, intr.cy)
        row = {"index": int(i), "psnr": psnr(img, rgb), **colour_error_split(img, rgb), "ssim": ssim_np(img, rgb),
               "depth_l1_cm": depth_l1_cm(depth_img, depth), "normal_error_deg": normal_error_deg(normals, ref_normals),
               **depth_error_split(depth_img, depth)}
        if gt_depth is not None:
            row["depth_l1_sensor_cm"] = depth_l1_cm(depth_img, sensor_depth)
        if lpips is not None and lpips.available:
            row["lpips"] = lpips(img, rgb)
        rows.append(row)
    n = len(rows)

    def mean(key):
        vals = [r[key] for r in rows if key in r and np.isfinite(r[key])]
        return float(np.mean(vals)) if vals else float("nan")

    res = {"psnr": mean("psnr"), **{k: mean(k) for k in COLOUR_SPLIT_KEYS}, "ssim": mean("ssim"),
           "depth_l1_cm": mean("depth_l1_cm"),
           "normal_error_deg": mean("normal_error_deg"),
           **{k: mean(k) for k in DEPTH_SPLIT_KEYS},
           **({"depth_l1_sensor_cm": mean("depth_l1_sensor_cm")} if any("depth_l1_sensor_cm" in r for r in rows) else {}),
           "lpips": mean("lpips") if lpips is not None and lpips.available else "no weights",
           "frames": n, "width": intr.width, "height": intr.height,
           "render_fps": n / render_s if render_s > 0 else 0.0, "per_frame": rows}
    return res


def ply_fidelity(mapper, baked) -> dict:
    """How much of the map a standard viewer gets: PSNR against the keyframes' training images of the map's own
    render (each keyframe's exposure), of the baked Gaussians (``ExplicitGaussians``, e.g. gaussians.ply read
    back) at the same poses (``psnr_ply``: the file's one brightness, the mapper's ``reference_exposure``), and of
    that render brought to each keyframe's exposure and the camera's vignetting (``psnr_ply_exposed``: the file
    against the map under the same camera model; with auto-exposure or vignetting the two PLY figures differ)."""
    rows = []
    poses = mapper.pose_source()
    for k in mapper.store.ids():
        if k not in poses:
            continue
        item = mapper.store.get(k)
        own = mapper.render(poses[k], exposure_kf=k, planar=False).color.numpy()
        ply = baked.render(poses[k], mapper.intr, mapper.settings).color
        exposed = mapper.reexpose(ply, k, mapper.intr).clamp(0, 1).numpy()
        rows.append((psnr(own, item.rgb), psnr(ply.clamp(0, 1).numpy(), item.rgb), psnr(exposed, item.rgb)))
    a = np.asarray(rows, np.float64).reshape(-1, 3)
    mean = a.mean(axis=0) if len(a) else np.full(3, np.nan)
    return {"keyframes": len(rows), "psnr_map": float(mean[0]), "psnr_ply": float(mean[1]),
            "psnr_ply_exposed": float(mean[2]), "width": mapper.intr.width, "height": mapper.intr.height}
