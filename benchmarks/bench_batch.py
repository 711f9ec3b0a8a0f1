"""Batch throughput on this machine: the same runs one at a time, several at a time through ``ggfslam batch``
(threads pinned), and several at a time as plain background processes (threads not pinned, as a shell loop with
``&`` would start them). Prints JSON.

    python benchmarks/bench_batch.py [--runs 4] [--frames 60] [--width 320] [--keep DIR]

Run it alone: it uses every core on purpose.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]


def _plan(folder: Path, runs: int, frames: int, width: int, num_cpus: int) -> Path:
    cfg = {"name": "room", "dataset": {"kind": "synthetic", "synthetic": {
        "n_frames": frames, "width": width, "height": width * 3 // 4}}, "mapping": {"mesh": False}}
    (folder / "room.yaml").write_text(yaml.safe_dump(cfg))
    plan = {"name": f"bench-{num_cpus}cpu", "sequences": ["room.yaml"],
            "variants": {"ggf": ["ggf.enabled=true"], "base": ["ggf.enabled=false"]},
            "repeats": max(1, runs // 2), "num_cpus": num_cpus}
    path = folder / f"plan_{num_cpus}.yaml"
    path.write_text(yaml.safe_dump(plan))
    return path


def _batch(plan: Path, out: Path) -> tuple[float, list[dict]]:
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "ggfslam.cli", "batch", str(plan), "--out", str(out)],
                       capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"batch failed ({r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
    return wall, json.loads((out / "results.json").read_text())["rows"]


def _unpinned(plan: Path, out: Path, parallel: int) -> tuple[float, list[dict]]:
    """The plan's runs as ``ggfslam run`` processes, ``parallel`` at a time, with every thread pool at its
    default (all cores)."""
    from ggfslam.batch import load_plan

    runs = load_plan(plan, out).runs
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS",
                                                           "NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
    t0 = time.perf_counter()
    queue, running = list(runs), []
    while queue or running:
        while queue and len(running) < parallel:
            spec = queue.pop(0)
            sets = [a for o in spec.overrides + ["runtime.num_threads=0"] for a in ("--set", o)]
            running.append(subprocess.Popen([sys.executable, "-m", "ggfslam.cli", "run", str(spec.config_path),
                                             "--out", str(spec.run_dir), "--no-progress", *sets],
                                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env))
        time.sleep(0.5)
        for p in [p for p in running if p.poll() is not None]:
            running.remove(p)
            if p.returncode != 0:
                raise SystemExit(f"a run failed ({p.returncode})")
    wall = time.perf_counter() - t0
    from ggfslam.batch.results import metric_columns

    return wall, [metric_columns(json.loads((spec.run_dir / "metrics.json").read_text())) for spec in runs]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=4, help="runs in the plan (2 variants x runs/2 seeds)")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--keep", type=Path, help="keep the run folders here")
    args = ap.parse_args()
    cores = len(os.sched_getaffinity(0))
    folder = Path(tempfile.mkdtemp(prefix="bench_batch-")) if args.keep is None else args.keep
    folder.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("GGFSLAM_CACHE", str(folder / "cache"))
    # the sequence is rendered before any timing starts
    from ggfslam.batch import load_plan
    from ggfslam.data.sources import open_dataset_from_config

    one_at_a_time = _plan(folder, args.runs, args.frames, args.width, cores)
    open_dataset_from_config(load_plan(one_at_a_time, folder / "tmp").runs[0].config.dataset)
    result = {"cores": cores, "runs": args.runs, "frames": args.frames,
              "resolution": f"{args.width}x{args.width * 3 // 4}", "modes": {}}
    modes = [("batch, one at a time, all cores each", lambda: _batch(one_at_a_time, folder / "seq")),
             (f"batch, {cores} at a time, 1 thread each (pinned)",
              lambda: _batch(_plan(folder, args.runs, args.frames, args.width, 1), folder / "par")),
             (f"plain processes, {cores} at a time, threads not pinned",
              lambda: _unpinned(one_at_a_time, folder / "loop", cores))]
    for name, fn in modes:
        wall, rows = fn()
        result["modes"][name] = {"wall_s": round(wall, 1), "runs_per_hour": round(3600 * len(rows) / wall, 2),
                                 "ate_cm": [round(r["ate_rmse_cm"], 4) for r in rows],
                                 "psnr_db": [round(r["psnr"], 3) for r in rows],
                                 "run_wall_s": [round(r["wall_s"], 1) for r in rows]}
        print(json.dumps({name: result["modes"][name]}), file=sys.stderr, flush=True)
    base = result["modes"]["batch, one at a time, all cores each"]["wall_s"]
    result["speedup_vs_one_at_a_time"] = {k: round(base / v["wall_s"], 2) for k, v in result["modes"].items()}
    print(json.dumps(result, indent=1))
    if args.keep is None:
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
