"""Does GTSAM's optimizer run in parallel with Python code of the same process? (issue 20: where bundle adjustment
must live so that tracking never waits for it).

A bundle adjustment problem like local BA's (``--poses`` poses, ``--points`` points, robust projection factors) is
optimized over and over (Levenberg-Marquardt, 10 iterations) while the main thread runs a pure-Python loop (a
stand-in for tracking, which holds the interpreter lock most of the time). The loop is timed alone, beside the
optimizer in a thread of this process, and beside it in another process. If GTSAM released the lock while it
optimizes, the thread case would cost what the process case costs (the cores' share only); the ratio of the
two is the lock's cost.

One JSON document goes to stdout. Usage: ``python benchmarks/bench_backend_gil.py [--poses 30 --points 3000]``
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import threading
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X


def ba_problem(n_poses: int, n_points: int, seed: int = 0) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Poses along a line looking at a box of points, 30% of the visible projections observed with 1 px noise,
    starting values perturbed by ~1 cm / 0.1 deg and 2 cm."""
    rng = np.random.default_rng(seed)
    K = gtsam.Cal3_S2(525, 525, 0, 320, 240)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345),
                                           gtsam.noiseModel.Isotropic.Sigma(2, 1.0))
    points = rng.uniform([-2, -2, 3], [2, 2, 6], (n_points, 3))  # [P, 3]
    poses = [gtsam.Pose3(gtsam.Rot3.Ry(0.01 * i), gtsam.Point3(0.05 * i, 0, 0)) for i in range(n_poses)]
    for i, pose in enumerate(poses):
        cam = gtsam.PinholeCameraCal3_S2(pose, K)
        for j in range(n_points):
            uv = cam.project(points[j])
            if 0 <= uv[0] < 640 and 0 <= uv[1] < 480 and rng.random() < 0.3:
                graph.add(gtsam.GenericProjectionFactorCal3_S2(uv + rng.normal(0, 1, 2), noise, X(i), L(j), K))
        values.insert(X(i), pose.compose(gtsam.Pose3(gtsam.Rot3.Rz(0.002), gtsam.Point3(0.01, 0, 0))))
    for j in range(n_points):
        values.insert(L(j), points[j] + rng.normal(0, 0.02, 3))
    for i in (0, 1):  # gauge: the first two poses held
        graph.add(gtsam.PriorFactorPose3(X(i), poses[i], gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)))
    return graph, values


def optimize(graph, values) -> None:
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(10)
    gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()


def python_work(n: int) -> float:
    """Seconds of a pure-Python loop of ``n`` steps."""
    t0 = time.perf_counter()
    s = 0
    for i in range(n):
        s += i * i
    return time.perf_counter() - t0


def _optimize_for(seconds: float, n_poses: int, n_points: int, ready=None) -> None:
    graph, values = ba_problem(n_poses, n_points)
    if ready is not None:
        ready.set()
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        optimize(graph, values)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=30)
    ap.add_argument("--points", type=int, default=3000)
    ap.add_argument("--loop", type=int, default=15_000_000, help="steps of the Python loop")
    args = ap.parse_args(argv)
    graph, values = ba_problem(args.poses, args.points)
    t0 = time.perf_counter()
    optimize(graph, values)
    ba_s = time.perf_counter() - t0
    alone = python_work(args.loop)
    span = 2 * alone + 5

    th = threading.Thread(target=_optimize_for, args=(span, args.poses, args.points), daemon=True)
    th.start()
    time.sleep(1.0)
    with_thread = python_work(args.loop)
    th.join()

    ctx = multiprocessing.get_context("spawn")
    ready = ctx.Event()
    proc = ctx.Process(target=_optimize_for, args=(span, args.poses, args.points, ready))
    proc.start()
    ready.wait(120)
    time.sleep(0.5)
    with_process = python_work(args.loop)
    proc.join()
    report = {"benchmark": "backend_gil", "factors": graph.size(), "ba_seconds": round(ba_s, 3),
              "python_loop_alone_s": round(alone, 3), "beside_ba_thread_s": round(with_thread, 3),
              "beside_ba_process_s": round(with_process, 3),
              "slowdown_thread": round(with_thread / alone, 2), "slowdown_process": round(with_process / alone, 2),
              "gil_released": bool(with_thread / alone < 1.2 * with_process / alone)}
    json.dump(report, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
