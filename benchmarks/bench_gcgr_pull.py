"""GCGR's pull on each keyframe of finished runs (``ggfslam.eval.gcgr_pull``): the factors alone, started at the
run's final pose and at the ground truth; per variant of the GCGR settings.

Every ``--variant NAME:KEY=VALUE[,KEY=VALUE...]`` (repeatable; ``base`` = the run's own ``gcgr.*`` settings is always
first) measures the same keyframes with those GCGR settings, so candidates for what pulls keyframes away from the
ground truth (pixel selection, range, weights, a keyframe's own anchors) can be compared on one map.

One JSON document goes to stdout (per run and variant: the summary per start and the per-keyframe rows); a
table of the summaries goes to stderr.

Usage: ``python benchmarks/bench_gcgr_pull.py RUN_DIR [RUN_DIR ...] [--variant own:gcgr.exclude_own_anchors=true]
[--every 2]``
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_tracking import finish_report, log, start_report  # noqa: E402


def parse_variant(text: str) -> tuple[str, list[str]]:
    """``NAME:KEY=VALUE,KEY=VALUE`` -> (name, overrides)."""
    name, sep, rest = text.partition(":")
    if not sep or not name or "=" not in rest:
        raise argparse.ArgumentTypeError(f"--variant {text!r}: expected NAME:KEY=VALUE[,KEY=VALUE...]")
    return name, [o.strip() for o in rest.split(",") if o.strip()]


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print its JSON report; returns the exit status (1 if any run failed)."""
    from ggfslam.eval.gcgr_pull import keyframe_pulls

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="finished ggfslam run folders with a map and ground truth")
    ap.add_argument("--variant", type=parse_variant, action="append", default=[], metavar="NAME:KEY=VALUE,...")
    ap.add_argument("--every", type=int, default=1, help="measure every n-th keyframe")
    ap.add_argument("--prior", type=float, nargs=2, default=(0.2, 0.2), metavar=("RAD", "M"),
                    help="sigmas of the weak prior at the start pose")
    args = ap.parse_args(argv)
    variants = [("base", [])] + args.variant
    report, stdout = start_report("gcgr_pull", [], variants={n: o for n, o in variants})
    failed = False
    for run in args.runs:
        for name, overrides in variants:
            log(f"{run} ({name})")
            try:
                r = keyframe_pulls(run, overrides, prior_sigmas=tuple(args.prior), every=args.every)
            except Exception as e:  # noqa: BLE001 - one bad run is reported, the others still run
                report["runs"].append({"run": run, "variant": name, "error": f"{type(e).__name__}: {e}"})
                log(f"  failed: {type(e).__name__}: {e}")
                failed = True
                continue
            report["runs"].append({"variant": name, **r})
            for start, s in r["summary"].items():
                if s.get("keyframes"):
                    log(f"  from {start:13s}: {s['keyframes']} kf, moved {s['moved_cm']:.2f} cm {s['moved_deg']:.2f} deg; "
                        f"to GT {s['gt_before_cm']:.2f} -> {s['gt_after_cm']:.2f} cm "
                        f"{s['gt_before_deg']:.2f} -> {s['gt_after_deg']:.2f} deg (nearer {100 * s['nearer_gt']:.0f}%); "
                        f"calibrated GT {s['cal_before_cm']:.2f} -> {s['cal_after_cm']:.2f} cm "
                        f"{s['cal_before_deg']:.2f} -> {s['cal_after_deg']:.2f} deg (nearer {100 * s['nearer_cal']:.0f}%); "
                        f"depth bias {s['depth_bias_mm']:.1f} mm (|.| {s['depth_abs_mm']:.1f})")
            c = r["calibration_offset"]
            log(f"  ground truth's constant camera offset against the run: {c['cm']:.2f} cm, {c['deg']:.2f} deg")
    return finish_report(report, stdout, Path(tempfile.gettempdir()), keep=True, failed=failed)


if __name__ == "__main__":
    sys.exit(main())
