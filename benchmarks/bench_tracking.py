"""Benchmark of camera tracking: the ORB + GTSAM system and the Open3D RGB-D odometry baseline, side by side.

Sequences (positional, one or more):

* a dataset folder (TUM layout, or anything ``dataset.kind: auto`` recognises);
* a config YAML file (its ``dataset`` section is used as is);
* ``synthetic:N``: the procedural room, N frames at 640x480, orbit trajectory, Kinect-like depth noise;
* ``synthetic-loop:N``: the same room along the loop trajectory;
* ``replica:N``: Replica office0 rendered from the shared mesh along its traj.txt, N frames at 600x340.

The rendered sequences (``synthetic:N``, ``synthetic-loop:N``, ``replica:N``) trust depth as the configs of rendered
sequences do (``tracking.virtual_baseline: 0.5``: their depth is registered to the colour exactly); ``--set``
overrides it.

Every (sequence, method) pair is one ``ggfslam.slam.run`` into a scratch run directory, in a fresh process
so that peak RSS is that run's own. Reported per run: ATE RMSE (cm, all frames, lost frames included at
their last pose), frames, frames lost, tracking frames/s (time in ``tracker.track`` only, image loading
excluded; in sequential backend mode it includes the bundle adjustment of new keyframes), BA ms per
keyframe (mean, max), keyframes, landmarks, loops, wall seconds (tracking loop with loading and the
backend's finish) and peak RSS (MiB). Synthetic sequences are generated once (cached in ``GGFSLAM_CACHE``)
before any run, so rendering is never timed.

One JSON document goes to stdout; progress goes to stderr.

Usage: ``python benchmarks/bench_tracking.py synthetic:60 ../shared/data/tum_fr3_cabinet_kf
[--methods orb,o3d_odometry] [--set tracking.n_features=1000] [--keep runs/]``
"""
from __future__ import annotations

import argparse
import concurrent.futures as cf
import json
import multiprocessing
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

METHODS = ("orb", "o3d_odometry")


def log(msg: str) -> None:
    """A progress line on stderr."""
    # named after the script that runs (bench_mapping uses the helpers below too)
    print(f"[{Path(sys.argv[0]).stem or 'bench_tracking'}] {msg}", file=sys.stderr, flush=True)


def sequence_config(spec: str, overrides: list[str]) -> dict:
    """Raw config dict (before validation) for a sequence spec, with ``--set`` overrides applied."""
    import yaml

    from ggfslam.cli import RENDERED_VIRTUAL_BASELINE
    from ggfslam.config import apply_overrides
    from ggfslam.errors import ConfigError

    kind, _, count = spec.partition(":")
    if kind in ("synthetic", "synthetic-loop", "replica") and count:
        try:
            n = int(count)
        except ValueError:
            raise ConfigError(f"{spec}: expected {kind}:N with N a number of frames") from None
        if kind == "replica":
            syn = {"source": "replica", "n_frames": n, "width": 600, "height": 340, "depth_noise": False}
        else:
            syn = {"source": "procedural", "n_frames": n, "width": 640, "height": 480, "depth_noise": True,
                   "trajectory": "loop" if kind == "synthetic-loop" else "orbit"}
        data = {"name": f"{kind}-{n}", "dataset": {"kind": "synthetic", "synthetic": syn},
                "tracking": {"virtual_baseline": RENDERED_VIRTUAL_BASELINE}}
    else:
        path = Path(spec)
        if path.is_file() and path.suffix in (".yaml", ".yml"):
            data = yaml.safe_load(path.read_text()) or {}
        elif path.is_dir():
            data = {"name": path.name, "dataset": {"kind": "auto", "path": str(path.resolve())}}
        else:
            raise ConfigError(f"{spec}: not a dataset folder, a config .yaml, synthetic:N, synthetic-loop:N "
                              f"or replica:N")
    return apply_overrides(data, list(overrides))


def _run_one(raw: dict, method: str, out_dir: str) -> dict:
    """One tracking run (in a worker process); returns the benchmark figures."""
    os.dup2(2, 1)  # libraries that print (C++ included) must not mix into the JSON on stdout
    from ggfslam import slam
    from ggfslam.config import apply_overrides, config_from_dict

    cfg = config_from_dict(apply_overrides(dict(raw), [f"tracking.method={method}", "mapping.enabled=false"]))
    m = slam.run(cfg, out_dir, progress=False)
    traj, be, tr, system = m.get("trajectory", {}), m.get("backend", {}), m["tracking"], m["system"]
    return {
        "ate_rmse_cm": traj.get("ate_rmse_cm"), "ate_max_cm": traj.get("ate_max_cm"),
        "ate_pairs": traj.get("ate_pairs"), "frames": tr["frames"], "frames_lost": tr["frames_lost"],
        "tracking_fps": tr["fps"], "tracking_ms_per_frame": 1000.0 / tr["fps"] if tr["fps"] else None,
        "ba_ms_mean": be.get("ba_ms_mean"), "ba_ms_max": be.get("ba_ms_max"), "ba_runs": be.get("ba_runs"),
        "keyframes": be.get("keyframes"), "landmarks": be.get("landmarks"), "loops": be.get("loops"),
        "wall_seconds": system["wall_seconds"], "peak_rss_mb": system["peak_rss_mb"],
        "width": m["sequence"]["width"], "height": m["sequence"]["height"],
    }


def _prepare(raw: dict) -> None:
    """Generate a synthetic sequence now (cached), so no run times the rendering."""
    from ggfslam.config import config_from_dict
    from ggfslam.data.sources import camera_from_config, generate_synthetic

    cfg = config_from_dict(raw)
    if cfg.dataset.kind == "synthetic":
        t0 = time.perf_counter()
        root = generate_synthetic(cfg.dataset.synthetic, camera_from_config(cfg.dataset))
        log(f"sequence {cfg.name}: {root} ({time.perf_counter() - t0:.1f} s)")


def start_report(benchmark: str, overrides: list[str], **extra) -> tuple[dict, object]:
    """The report skeleton and its output channel (the real stdout); fd 1 goes to stderr from here on, so
    library prints cannot corrupt the JSON."""
    stdout = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)
    report = {"benchmark": benchmark, "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
              "host": {"python": platform.python_version(), "machine": platform.machine(), "cpus": os.cpu_count()},
              **extra, "overrides": overrides, "runs": []}
    return report, stdout


def prepared_sequences(specs: list[str], overrides: list[str], report: dict) -> tuple[list[tuple[str, dict]], bool]:
    """(spec, raw config) of each sequence, synthetic ones generated now; specs that fail to load are recorded
    in the report. Returns them and whether any failed."""
    from ggfslam.errors import GGFSlamError

    ready, failed = [], False
    for spec in specs:
        try:
            raw = sequence_config(spec, overrides)
            _prepare(raw)
        except GGFSlamError as e:
            log(f"{spec}: {e}")
            report["runs"].append({"sequence": spec, "error": str(e)})
            failed = True
            continue
        ready.append((spec, raw))
    return ready, failed


def in_fresh_process(fn, *args):
    """``fn(*args)`` in a new (spawned) process, so that its peak RSS is its own; returns its result."""
    ctx = multiprocessing.get_context("spawn")
    with cf.ProcessPoolExecutor(max_workers=1, mp_context=ctx) as pool:
        return pool.submit(fn, *args).result()


def comma_choices(ap, text: str, allowed, what: str) -> list[str]:
    """The comma-separated names in ``text``; an unknown one ends the program with argparse's usage error."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    bad = [n for n in names if n not in allowed]
    if bad:
        ap.error(f"unknown {what}(s) {', '.join(bad)}; choose from {', '.join(allowed)}")
    return names


def guarded_run(label: str, fn, *args) -> dict:
    """``fn(*args)`` in a fresh process; a failure is logged and returned as ``{"error": ...}`` so that one
    failed run does not lose the others' figures."""
    try:
        return in_fresh_process(fn, *args)
    except Exception as e:
        log(f"{label} failed: {type(e).__name__}: {e}")
        return {"error": f"{type(e).__name__}: {e}"}


def finish_report(report: dict, stdout, scratch: Path, keep: bool, failed: bool) -> int:
    """Drop the scratch runs unless kept, write the JSON report; returns the exit status."""
    if not keep:
        import shutil

        shutil.rmtree(scratch, ignore_errors=True)
    json.dump(report, stdout, indent=1, default=float)
    stdout.write("\n")
    stdout.flush()
    return 1 if failed else 0


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print its JSON report; returns the exit status (1 if any run failed)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequences", nargs="+", help="dataset folder, config .yaml, synthetic:N, synthetic-loop:N "
                                                 "or replica:N")
    ap.add_argument("--methods", default=",".join(METHODS), help="comma-separated tracking.method values")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="config override applied to every sequence (repeatable)")
    ap.add_argument("--keep", metavar="DIR", help="keep the run directories under DIR (default: discarded)")
    ap.add_argument("--in-process", action="store_true",
                    help="run everything in this process (faster start; peak RSS is then cumulative)")
    args = ap.parse_args(argv)
    methods = comma_choices(ap, args.methods, METHODS, "method")

    report, stdout = start_report("tracking", args.overrides, methods=methods)
    scratch = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_tracking-"))
    ready, failed = prepared_sequences(args.sequences, args.overrides, report)
    for spec, raw in ready:
        for method in methods:
            out = scratch / f"{raw.get('name', 'run')}-{method}".replace("/", "_")
            log(f"{spec} / {method} -> {out}")
            t0 = time.perf_counter()
            row = {"sequence": spec, "name": raw.get("name", "run"), "method": method}
            try:
                if args.in_process:
                    row.update(_run_one(raw, method, str(out)))
                else:  # a fresh process per run: its peak RSS is its own
                    row.update(in_fresh_process(_run_one, raw, method, str(out)))
            except Exception as e:  # one failed run must not lose the others' figures
                log(f"{spec} / {method} failed: {type(e).__name__}: {e}")
                row["error"] = f"{type(e).__name__}: {e}"
                failed = True
            row["process_seconds"] = time.perf_counter() - t0
            if "error" not in row:
                ate = row["ate_rmse_cm"]
                log(f"  ATE {ate if ate is None else round(ate, 2)} cm, {row['tracking_fps']:.1f} frames/s, "
                    f"{row['frames_lost']} lost, wall {row['wall_seconds']:.1f} s")
            report["runs"].append(row)
    return finish_report(report, stdout, scratch, bool(args.keep), failed)


if __name__ == "__main__":
    sys.exit(main())
