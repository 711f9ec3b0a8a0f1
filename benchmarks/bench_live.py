"""Benchmark of live operation: a sequence replayed on time (``ggfslam live --source replay``) against the offline
run of the same config, with the targets of live input (issue 20) checked.

Runs, each a fresh ``ggfslam`` process, one after the other (run it alone: two cores are easily oversubscribed):

* offline: ``ggfslam run CONFIG`` (the reference ATE and PSNR; ``--offline RUN_DIR`` reuses a finished run);
* live at each ``--rates`` (default 1.0 and 0.25): ``ggfslam live CONFIG --source replay --rate R``.

Reported per live run: frames received / processed / dropped, processed share, arrival-to-pose latency p50 / p95,
tracking frames/s, ATE RMSE (processed frames, estimated poses) and its ratio to the offline ATE, PSNR at the
evaluation resolution and its difference to the offline PSNR, final refinement seconds, mapper steps, wall
seconds. Targets: at 1x, >= 80% processed, p95 <= 100 ms, ATE <= 1.5x offline, PSNR within 1 dB of offline after
<= 60 s of final training; at 0.25x, ATE within 10% of offline.

One JSON document goes to stdout; progress to stderr.

Usage: ``python benchmarks/bench_live.py configs/7scenes/redkitchen_500_registered.yaml [--rates 1,0.25]
[--queue 2] [--offline RUN_DIR] [--keep DIR] [--set KEY=VALUE ...]``
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def log(msg: str) -> None:
    """A progress line on stderr."""
    print(f"[bench_live] {msg}", file=sys.stderr, flush=True)


def ggfslam(args: list[str]) -> float:
    """Run the ggfslam CLI in a fresh process; returns its wall seconds (raises on failure)."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "ggfslam.cli", *args, "--no-progress"], capture_output=True,
                          text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"ggfslam {' '.join(args)} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    return time.perf_counter() - t0


def summary(run_dir: Path, wall: float | None) -> dict:
    """The figures of one run folder."""
    m = json.loads((run_dir / "metrics.json").read_text())
    r, stages = m.get("rendering", {}), m["system"]["stages"]
    out = {"ate_rmse_cm": m.get("trajectory", {}).get("ate_rmse_cm"), "psnr": r.get("psnr"),
           "psnr_resolution": f"{r.get('width')}x{r.get('height')}", "depth_l1_cm": r.get("depth_l1_cm"),
           "tracking_fps": m["tracking"]["fps"], "mapper_steps": m.get("mapping", {}).get("iterations"),
           "final_refinement_s": stages.get("final_refinement", {}).get("seconds"),
           "wall_s": None if wall is None else round(wall, 1), "peak_rss_mb": m["system"]["peak_rss_mb"]}
    if "live" in m:
        lv = m["live"]
        out.update(frames_received=lv["frames_received"], frames_processed=lv["frames_processed"],
                   frames_dropped=lv["frames_dropped"],
                   processed_share=lv["frames_processed"] / max(lv["frames_received"], 1),
                   latency_ms_p50=lv["latency_ms_p50"], latency_ms_p95=lv["latency_ms_p95"])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("config")
    ap.add_argument("--rates", default="1,0.25", help="replay speeds, comma-separated")
    ap.add_argument("--queue", type=int, default=2, help="live: frames waiting at most (1 or 2)")
    ap.add_argument("--offline", type=Path, help="a finished offline run of the config to compare against")
    ap.add_argument("--keep", type=Path, help="keep the run folders here")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="config override (repeatable)")
    args = ap.parse_args()
    sets = [x for o in args.overrides for x in ("--set", o)]
    root = args.keep or Path(tempfile.mkdtemp(prefix="bench_live_"))
    root.mkdir(parents=True, exist_ok=True)
    result = {"config": args.config, "overrides": args.overrides, "queue": args.queue, "machine": {
        "cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()}}
    if args.offline is not None:
        result["offline"] = summary(args.offline, None)
        result["offline"]["run"] = str(args.offline)
    else:
        log("offline run")
        wall = ggfslam(["run", args.config, "--out", str(root / "offline"), "--overwrite", *sets])
        result["offline"] = summary(root / "offline", wall)
    off = result["offline"]
    result["live"] = {}
    for rate in [float(r) for r in args.rates.split(",")]:
        log(f"live replay at {rate:g}x")
        out = root / f"live_{rate:g}x"
        wall = ggfslam(["live", args.config, "--source", "replay", "--rate", str(rate), "--queue", str(args.queue),
                        "--out", str(out), "--overwrite", *sets])
        s = summary(out, wall)
        s["ate_ratio_to_offline"] = s["ate_rmse_cm"] / off["ate_rmse_cm"]
        s["psnr_minus_offline_db"] = s["psnr"] - off["psnr"]
        result["live"][f"{rate:g}x"] = s
    targets = {}
    one = result["live"].get("1x")
    if one is not None:
        targets["1x_processed_share>=0.8"] = one["processed_share"] >= 0.8
        targets["1x_latency_p95<=100ms"] = one["latency_ms_p95"] <= 100
        targets["1x_ate<=1.5x_offline"] = one["ate_ratio_to_offline"] <= 1.5
        targets["1x_psnr_within_1db_after<=60s"] = one["psnr_minus_offline_db"] >= -1.0 and \
            one["final_refinement_s"] <= 61
    quarter = result["live"].get("0.25x")
    if quarter is not None:
        targets["0.25x_ate_within_10%"] = abs(quarter["ate_ratio_to_offline"] - 1) <= 0.10
    result["targets_met"] = targets
    result["runs"] = str(root)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
