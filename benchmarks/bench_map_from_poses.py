"""Map a sequence from fixed poses and score it: is it the poses or the map that limits the rendering?

For a finished run (``RUN_DIR``, any ``ggfslam run`` folder), the mapper alone is run again on the run's
keyframes (``tracking.txt``) with the same schedule as ``ggfslam run`` (seed each keyframe, its step budget
focused on it, then the final refinement), once per pose source given with ``--poses``:
- ``run``: the run's final estimated poses (``trajectory.txt``; BA and loop closure already applied, so poses do
  not move while the map trains);
- ``gt``: the sequence's ground truth (the map then lives in the ground truth's frame).
Each map is scored like a run (PSNR/SSIM/depth L1 of every ``mapping.eval_stride``-th frame rendered from the
same pose source, and separately at the keyframes). If the ground truth scores far better, the estimated poses
limit the map; if it scores worse, the ground truth disagrees with the images (e.g. 7-Scenes' KinectFusion
poses follow the depth camera, which is not registered to the colour camera; see docs/MEASUREMENTS.md).

With ``--subset N --steps A,B,..`` it asks instead whether the step budget limits the map: only N consecutive
keyframes from the middle of the run are mapped (seeded, no focused steps), trained by error alone, and scored at
those keyframes after A, B, ... steps in all. A run gives each keyframe ``steps / keyframes`` steps; if the subset
fits its keyframes far better at that share, and keeps gaining with more, the budget is the limit.

One JSON document goes to stdout; progress goes to stderr.

Usage: ``GGFSLAM_DATA=../shared/data python benchmarks/bench_map_from_poses.py runs/kitchen --poses run,gt
[--set mapping.train_width=320 --set mapping.eval_width=320]`` (the run's config.yaml is the base config);
``... RUN --poses run --subset 5 --steps 150,500,1000`` for the step budget.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_tracking import finish_report, in_fresh_process, log, start_report  # noqa: E402


def _poses_and_keyframes(run_dir: str, source: str, overrides: list[str]):
    """(config, dataset, frames [M], poses [N, 4, 4] (NaN where none), keyframe frame indices) of a run."""
    from ggfslam.config import load_config
    from ggfslam.data.sources import open_dataset_from_config
    from ggfslam.data.trajectory_io import read_tum_trajectory
    from ggfslam.render_run import keyframe_frames
    from ggfslam.slam import frames_of_stamps

    run = Path(run_dir)
    cfg = load_config(run / "config.yaml", overrides)
    ds = open_dataset_from_config(cfg.dataset)
    if source == "gt":
        if ds.gt_poses is None:
            raise ValueError(f"{cfg.dataset.path}: the sequence has no ground truth")
        frames, poses = np.arange(len(ds)), ds.gt_poses  # [N], [N, 4, 4]
    else:
        stamps, est = read_tum_trajectory(run / "trajectory.txt")
        frames = frames_of_stamps(np.asarray(ds.timestamps), stamps, run / "trajectory.txt")
        poses = np.full((len(ds), 4, 4), np.nan)
        poses[frames] = est
    return cfg, ds, frames, poses, keyframe_frames(run)


def _mapper(cfg, ds, pose_of: dict, store: str):
    from ggfslam.mapping.mapper import Mapper
    from ggfslam.render.types import RenderSettings

    return Mapper(cfg.mapping, ds.camera, RenderSettings(backend=cfg.render.backend), lambda: dict(pose_of),
                  store, cfg.runtime.seed, ggf=cfg.ggf)


def map_from_poses(run_dir: str, source: str, overrides: list[str]) -> dict:
    """Train a map on the run's keyframes from ``source`` poses ('run' or 'gt') and score it."""
    from ggfslam.slam import rendering_metrics

    cfg, ds, frames, poses, kfs = _poses_and_keyframes(run_dir, source, overrides)
    pose_of = {}
    with tempfile.TemporaryDirectory(prefix="ggfslam-map-") as store:
        mapper = _mapper(cfg, ds, pose_of, store)
        t0 = time.perf_counter()
        for k, fi in enumerate(kfs):
            pose_of[k] = poses[fi]
            f = ds[fi]
            mapper.store.add(k, fi, f.rgb, f.depth)
            mapper.seed_keyframe(k)
            mapper.train(mapper.keyframe_budget(k), focus=k)
        mapper.sync_poses()
        mapper.train(cfg.mapping.final_iterations)
        mapper.refit_exposures()
        train_s = time.perf_counter() - t0
        every = rendering_metrics(cfg, mapper, ds, frames, poses[frames])
        cfg.mapping.eval_stride = 1  # every keyframe
        at_kf = rendering_metrics(cfg, mapper, ds, np.array(kfs), poses[kfs])
    scalar = (int, float, str)
    return {"poses": source, "keyframes": len(kfs), "steps": mapper.iteration, "train_seconds": train_s,
            "frames": {k: v for k, v in every.items() if isinstance(v, scalar)},
            "at_keyframes": {k: v for k, v in at_kf.items() if isinstance(v, scalar)}}


def step_budget(run_dir: str, source: str, overrides: list[str], subset: int, steps: list[int]) -> dict:
    """Map ``subset`` consecutive keyframes from the middle of the run (``source`` poses) with error-drawn steps
    only; their scores after each cumulative count in ``steps``."""
    from ggfslam.slam import rendering_metrics

    cfg, ds, _, poses, kfs = _poses_and_keyframes(run_dir, source, overrides)
    if not 0 < subset <= len(kfs):
        raise ValueError(f"--subset {subset}: the run has {len(kfs)} keyframes")
    sel = kfs[(len(kfs) - subset) // 2:][:subset]
    cfg.mapping.eval_stride = 1
    pose_of, rows = {}, []
    with tempfile.TemporaryDirectory(prefix="ggfslam-map-") as store:
        mapper = _mapper(cfg, ds, pose_of, store)
        for k, fi in enumerate(sel):
            pose_of[k] = poses[fi]
            f = ds[fi]
            mapper.store.add(k, fi, f.rgb, f.depth)
            mapper.seed_keyframe(k)
        t0 = time.perf_counter()
        for n in sorted(steps):
            mapper.train(n - mapper.iteration)
            mapper.refit_exposures()
            r = rendering_metrics(cfg, mapper, ds, np.array(sel), poses[sel])
            rows.append({"steps": n, "steps_per_keyframe": n / subset, "seconds": time.perf_counter() - t0,
                         **{k: r[k] for k in ("psnr", "ssim", "depth_l1_cm", "width", "height")}})
            log(f"  {n} steps ({n / subset:.0f} per keyframe): PSNR {r['psnr']:.2f} dB at {r['width']}x{r['height']},"
                f" depth L1 {r['depth_l1_cm']:.2f} cm")
    return {"poses": source, "subset": subset, "keyframe_frames": [int(f) for f in sel], "run_keyframes": len(kfs),
            "scores": rows}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", help="a finished ggfslam run folder")
    ap.add_argument("--poses", default="run,gt", help="comma list of pose sources: run, gt")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="config override on top of the run's config.yaml (repeatable)")
    ap.add_argument("--subset", type=int, default=0, metavar="N",
                    help="step-budget mode: map N consecutive keyframes only (needs --steps)")
    ap.add_argument("--steps", default="", metavar="A,B,..", help="step-budget mode: cumulative step counts to score at")
    args = ap.parse_args(argv)
    run = Path(args.run_dir)
    for name in ("config.yaml", "tracking.txt", "trajectory.txt"):
        if not (run / name).is_file():
            ap.error(f"{run}: no {name} (give the folder of a finished ggfslam run)")
    sources = [s.strip() for s in args.poses.split(",") if s.strip()]
    bad = [s for s in sources if s not in ("run", "gt")]
    if bad:
        ap.error(f"--poses: unknown source {bad[0]!r} (expected run, gt)")
    steps = []
    if args.subset or args.steps:
        try:
            steps = [int(x) for x in args.steps.split(",") if x.strip()]
        except ValueError:
            ap.error(f"--steps {args.steps!r}: expected comma-separated step counts, e.g. 150,500,1000")
        if args.subset <= 0 or not steps or min(steps) <= 0:
            ap.error("the step-budget mode needs --subset N (N > 0) and --steps A,B,.. (positive counts)")
    report, stdout = start_report("map_from_poses", args.overrides, run=str(run))
    if steps:
        for s in sources:
            log(f"mapping {args.subset} keyframes of {run} from {s} poses")
            report["runs"].append(in_fresh_process(step_budget, str(run), s, args.overrides, args.subset, steps))
        return finish_report(report, stdout, Path(tempfile.gettempdir()), keep=True, failed=False)
    for s in sources:
        log(f"mapping {run} from {s} poses")
        r = in_fresh_process(map_from_poses, str(run), s, args.overrides)
        f = r["frames"]
        log(f"  {s}: PSNR {f['psnr']:.2f} dB at {f['width']}x{f['height']}, depth L1 {f['depth_l1_cm']:.2f} cm")
        report["runs"].append(r)
    return finish_report(report, stdout, Path(tempfile.gettempdir()), keep=True, failed=False)


if __name__ == "__main__":
    sys.exit(main())
