"""Benchmark of the live viewer's cost to a run: the same run with and without ``--view``, side by side.

Each run is ``ggfslam.slam.run`` in a fresh process on the demo's synthetic room (``--frames`` frames at
``--width`` x ``--height``; the demo's settings otherwise). With the viewer on, a stand-in for a remote browser is
connected the whole time: a websocket client that receives every message the viewer sends (scene updates, splats,
images) and counts the bytes, so the server does all of its work while no local browser competes for the two
cores (a real browser draws on the user's machine). Reported per run: tracking frames/s (time in the tracker
only, the issue's measure), wall seconds, the viewer's pose and map updates, the seconds they took and the bytes
sent; and the ratio of tracking frames/s with the viewer to without (target >= 0.9).

One JSON document goes to stdout; progress goes to stderr.

Usage: ``python benchmarks/bench_viewer.py [--frames 120] [--width 640 --height 480] [--set k=v]``
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_tracking import _prepare, guarded_run, log  # noqa: E402


def _browser_stand_in(port: int, counts, stop) -> None:
    """Receive everything the viewer sends, as a browser tab would (in a process of its own, as a browser is)."""
    import viser
    from websockets.sync.client import connect

    with connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None,
                 open_timeout=30) as ws:
        while not stop.is_set():
            try:
                msg = ws.recv(timeout=0.5)
            except TimeoutError:
                continue
            except Exception:  # the server closed: the run is over
                return
            counts[0] += 1
            counts[1] += len(msg)


def _one_run(raw: dict, view: bool, out_dir: str) -> dict:
    from ggfslam import slam
    from ggfslam.config import config_from_dict

    cfg = config_from_dict(raw, "bench_viewer")
    ctx = multiprocessing.get_context("spawn")
    viewer, stop, counts, browser = None, ctx.Event(), ctx.Array("d", 2), None
    if view:
        from ggfslam.viewer.live import LiveViewer

        viewer = LiveViewer("127.0.0.1", 0)
        browser = ctx.Process(target=_browser_stand_in, args=(viewer.port, counts, stop), daemon=True)
        browser.start()
        time.sleep(3.0)  # connected before the first frame
    t0 = time.perf_counter()
    try:
        metrics = slam.run(cfg, Path(out_dir) / ("view" if view else "plain"), progress=False, observer=viewer)
    finally:
        stop.set()
        if viewer is not None:
            viewer.close()
        if browser is not None:
            browser.join(10)
    out = {"tracking_fps": metrics["tracking"]["fps"], "wall_s": round(time.perf_counter() - t0, 1),
           "ate_rmse_cm": metrics.get("trajectory", {}).get("ate_rmse_cm"),
           "keyframes": metrics["backend"]["keyframes"]}
    if viewer is not None:
        out["viewer"] = {**{k: round(v, 3) if isinstance(v, float) else v for k, v in viewer.updates.items()},
                         "messages_received": int(counts[0]), "mb_received": round(counts[1] / 2**20, 1)}
    return out


def main(argv: list[str] | None = None) -> int:
    from ggfslam.cli import DEMO_CONFIG
    from ggfslam.config import apply_overrides

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="config override k=v")
    args = ap.parse_args(argv)
    raw = json.loads(json.dumps(DEMO_CONFIG))
    raw["dataset"]["synthetic"].update(n_frames=args.frames, width=args.width, height=args.height)
    raw = apply_overrides(raw, args.overrides)
    report = {"benchmark": "viewer", "frames": args.frames, "size": [args.width, args.height],
              "overrides": args.overrides}
    _prepare(raw)  # the sequence is rendered (and cached) before either run is timed
    with tempfile.TemporaryDirectory(prefix="bench_viewer_") as tmp:
        for view in (False, True):
            log(f"run with the viewer {'on' if view else 'off'} ...")
            report["view" if view else "plain"] = guarded_run("run", _one_run, raw, view, tmp)
    a, b = report["plain"], report["view"]
    if "tracking_fps" in a and "tracking_fps" in b:
        report["tracking_fps_ratio"] = round(b["tracking_fps"] / a["tracking_fps"], 3)
        report["wall_ratio"] = round(b["wall_s"] / a["wall_s"], 3)
    json.dump(report, sys.stdout, indent=2)
    print()
    return 0 if "tracking_fps_ratio" in report else 1


if __name__ == "__main__":
    raise SystemExit(main())
