"""Benchmark of the Gaussian map: rendering quality, mapping speed and memory of whole runs, plus the
mapper's raw throughput.

Sequences (positional; same forms as ``bench_tracking.py``): a dataset folder, a config YAML,
``synthetic:N``, ``synthetic-loop:N`` or ``replica:N`` (Replica office0 rendered from the shared mesh,
600x340). Each is one ``ggfslam.slam.run`` (tracking + mapping, sequential mode unless ``--set
mapping.concurrent=true``) in a fresh process. Reported per run: PSNR (and without gross-error regions:
``psnr_without_gross``), SSIM, depth L1 (cm; against the
noise-free mesh depth where the sequence has it) and normal error (degrees) over every
``eval_stride``-th frame rendered from the estimated poses, the render resolution, ATE RMSE (cm), mapping
iterations and iterations/s, anchors, Gaussians, wall seconds (whole run, outputs included), peak RSS (MiB)
and RSS sampled every 100 frames (memory against sequence length).

``--baseline`` runs every sequence a second time with the settings ggfslam had before the map became a
product (``LEGACY``: 320 px training, 100 steps per keyframe and 300 final ones, Scaffold-GS's view-dependent
decoders), side by side with the current defaults; both are scored the same way (all frames, estimated poses,
the sequence's resolution unless ``--set mapping.eval_width=...``).

``--throughput`` adds the mapper's steps/s on the procedural room at ``--throughput-width`` (default 320x240)
with keyframes added (ground-truth poses) until about ``--throughput-gaussians`` (default 100k) Gaussians
keep a positive opacity after a 20-step warm-up. Measured per kind of step: whole images at the training size,
crops of half the width and height (``mapping.crop=0.5``) and whole images at half the size (coarse steps).
Reported: anchors, candidate children (anchors x k), Gaussians with positive opacity, those in view of a whole
image, and per kind of step the steps/s and ms of the median step (this VM's speed drifts by 15-30%), the 10th and
90th percentiles of the step time, the mean steps/s and pixels per step.

One JSON document goes to stdout; progress goes to stderr.

Usage: ``python benchmarks/bench_mapping.py replica:200 ../shared/data/tum_fr3_cabinet_kf [--throughput]
[--set mapping.iterations_per_keyframe=150] [--keep runs/]``
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_tracking import (finish_report, guarded_run, in_fresh_process, log, prepared_sequences,  # noqa: E402
                            start_report)


def _run_one(raw: dict, out_dir: str) -> dict:
    """One SLAM + mapping run (in a worker process); returns the benchmark figures."""
    os.dup2(2, 1)
    from ggfslam import slam
    from ggfslam.config import config_from_dict

    cfg = config_from_dict(raw)
    t0 = time.perf_counter()
    m = slam.run(cfg, out_dir, progress=False)
    total = time.perf_counter() - t0
    r, mp, traj, system = m["rendering"], m["mapping"], m.get("trajectory", {}), m["system"]
    return {
        "psnr": r["psnr"], "psnr_without_gross": r.get("psnr_without_gross"), "ssim": r["ssim"],
        "depth_l1_cm": r["depth_l1_cm"],
        "normal_error_deg": r.get("normal_error_deg"), "lpips": r["lpips"],
        "eval_frames": r["frames"], "eval_resolution": f"{r['width']}x{r['height']}",
        "train_resolution": f"{mp['train_width']}x{mp['train_height']}",
        "ate_rmse_cm": traj.get("ate_rmse_cm"), "frames": m["tracking"]["frames"],
        "tracking_fps": m["tracking"]["fps"], "mapping_iterations": mp["iterations"],
        "mapping_iterations_per_s": mp["iterations_per_s"], "keyframes": mp["keyframes"],
        "anchors": mp["anchors"], "gaussians": mp["gaussians"], "render_fps": r["render_fps"],
        "run_seconds": total, "wall_seconds_tracking_and_mapping": system["wall_seconds"],
        "peak_rss_mb": system["peak_rss_mb"], "rss_mb_by_frame": system["rss_mb_by_frame"],
        "concurrent": cfg.mapping.concurrent,
        "ply_psnr": mp["ply_fidelity"]["psnr_ply"], "ply_psnr_exposed": mp["ply_fidelity"]["psnr_ply_exposed"],
        "ply_map_psnr": mp["ply_fidelity"]["psnr_map"], "ply_keyframes": mp["ply_fidelity"]["keyframes"],
        "wall_seconds_outputs": system["stages"].get("map_outputs", {}).get("seconds"),
    }


LEGACY = ["mapping.train_width=320", "mapping.iterations_per_keyframe=100", "mapping.iterations_per_frame=0",
          "mapping.final_iterations=300", "mapping.view_dependent=true", "mapping.sh_degree=0",
          "mapping.coarse_fraction=0", "mapping.crop=1.0", "mapping.init_opacity=0.1", "mapping.n_offsets=10"]
"""The mapping settings before the map became a product (2026-11-26 defaults)."""


def throughput(width: int, target: int, spacing: int, steps: int = 60, overrides: list[str] | None = None) -> dict:
    """Mapper steps/s at ``width`` (4:3) on the procedural room with about ``target`` decoded Gaussians, from
    keyframes ``spacing`` frames apart (10: each sees nearly all of the map; at 70 two keyframes a quarter-lap apart
    already hold ~100k)."""
    from ggfslam.config import apply_overrides, config_from_dict
    from ggfslam.data.sources import open_dataset_from_config
    from ggfslam.mapping.mapper import Mapper
    from ggfslam.render.types import RenderSettings
    from ggfslam.slam import setup_runtime

    height = width * 3 // 4
    cfg = config_from_dict(apply_overrides({"dataset": {"kind": "synthetic", "synthetic": {
        "n_frames": 980, "width": width, "height": height}}, "mapping": {"train_width": width}}, list(overrides or [])))
    ds = open_dataset_from_config(cfg.dataset)
    setup_runtime(cfg)  # seeded as a run is (the decoders' initial weights): the same scene in every process
    poses: dict = {}
    m = Mapper(cfg.mapping, ds.camera, RenderSettings(backend="cpu"), lambda: dict(poses), tempfile.mkdtemp(),
               ggf=cfg.ggf)
    kf = 0
    for fi in range(0, len(ds), spacing):
        poses[kf] = ds.gt_poses[fi]
        f = ds[fi]
        m.add_keyframe(kf, fi, f.rgb, f.depth)
        kf += 1
        # the decoders learn to switch children off within a few steps: count only after a warm-up
        if m.n_gaussians() >= target:
            m.train(20)  # also the warm-up (numba cache load, allocator)
            if m.n_gaussians() >= target:
                break
    visible = []
    for k in range(min(kf, 8)):
        g, _ = m._decode_view(poses[k], m.intr)
        visible.append(len(g))
    before = m.n_gaussians()
    kinds = {}
    ids = sorted(poses)
    i = m.intr
    for kind, (level, frac) in {"whole": (0, 1.0), "crop_half": (0, 0.5), "coarse": (1, 1.0)}.items():
        w, h = (i.width, i.height) if level == 0 else (m.store.level_intrinsics(1).width,
                                                          m.store.level_intrinsics(1).height)
        cw, ch = int(round(frac * w)), int(round(frac * h))
        times = []
        for s in range(steps):
            crop = None if frac >= 1 else (int(m.rng.integers(w - cw + 1)), int(m.rng.integers(h - ch + 1)), cw, ch)
            t0 = time.perf_counter()
            m.step(ids[s % len(ids)], level, crop)
            times.append(time.perf_counter() - t0)
        # this 2-core VM's speed drifts by 15-30% between processes and within one: the median step is the figure,
        # the 10th-90th percentiles show the spread
        ms = 1000 * np.asarray(times)
        kinds[kind] = {"iterations_per_s": 1000 / float(np.median(ms)), "ms_per_iteration": float(np.median(ms)),
                       "ms_p10": float(np.percentile(ms, 10)), "ms_p90": float(np.percentile(ms, 90)),
                       "mean_iterations_per_s": steps / (ms.sum() / 1000), "pixels": cw * ch}
    return {"resolution": f"{width}x{height}", "keyframe_spacing": spacing, "keyframes": kf, "anchors": m.map.n_anchors,
            "children": m.map.n_anchors * m.map.k, "gaussians_at_start": before, "gaussians": m.n_gaussians(),
            "gaussians_in_view_mean": float(sum(visible) / len(visible)), "steps": steps, "kinds": kinds,
            "iterations_per_s": kinds["whole"]["iterations_per_s"],
            "ms_per_iteration": kinds["whole"]["ms_per_iteration"]}


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print its JSON report; returns the exit status (1 if any run failed)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequences", nargs="*", help="dataset folder, config .yaml, synthetic:N, synthetic-loop:N or replica:N")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="config override applied to every sequence (repeatable)")
    ap.add_argument("--keep", metavar="DIR", help="keep the run directories under DIR (default: discarded)")
    ap.add_argument("--baseline", action="store_true",
                    help="also run every sequence with the settings before this release (LEGACY), side by side")
    ap.add_argument("--throughput", action="store_true", help="also measure the mapper's iterations/s")
    ap.add_argument("--throughput-width", type=int, default=320)
    ap.add_argument("--throughput-gaussians", type=int, default=100_000)
    ap.add_argument("--throughput-spacing", type=int, default=10,
                    help="frames between the throughput map's keyframes (10: each sees nearly all of it)")
    args = ap.parse_args(argv)
    if not args.sequences and not args.throughput:
        ap.error("give at least one sequence or --throughput")

    report, stdout = start_report("mapping", args.overrides)
    scratch = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_mapping-"))
    ready, failed = prepared_sequences(args.sequences, args.overrides, report)
    variants = {"current": []} | ({"legacy": LEGACY} if args.baseline else {})
    for spec, raw in ready:
        for variant, extra in variants.items():
            from ggfslam.config import apply_overrides

            cfg = apply_overrides(raw, extra + list(args.overrides))  # the user's --set still wins
            out = scratch / f"{raw.get('name', 'run')}-{variant}".replace("/", "_")
            log(f"{spec} ({variant}) -> {out}")
            row = {"sequence": spec, "name": raw.get("name", "run"), "settings": variant}
            row.update(guarded_run(spec, _run_one, cfg, str(out)))
            failed |= "error" in row
            if "error" not in row:
                log(f"  PSNR {row['psnr']:.2f} dB at {row['eval_resolution']}, depth L1 {row['depth_l1_cm']:.2f} cm, "
                    f"PLY {row['ply_psnr']:.2f} dB vs map {row['ply_map_psnr']:.2f} dB, "
                    f"{row['mapping_iterations_per_s']:.1f} it/s, run {row['run_seconds']:.0f} s")
            report["runs"].append(row)
    if args.throughput:
        log(f"throughput at {args.throughput_width} px, ~{args.throughput_gaussians} Gaussians")
        report["throughput"] = in_fresh_process(throughput, args.throughput_width, args.throughput_gaussians,
                                                  args.throughput_spacing, 60, args.overrides)
        for kind, r in report["throughput"]["kinds"].items():
            log(f"  {kind}: {r['iterations_per_s']:.1f} it/s ({r['pixels']} px a step)")
    return finish_report(report, stdout, scratch, bool(args.keep), failed)


if __name__ == "__main__":
    sys.exit(main())
