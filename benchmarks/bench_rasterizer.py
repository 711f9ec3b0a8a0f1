"""Benchmark of the Gaussian rasterizer backends on a synthetic room; prints JSON to stdout.

Scene: a 4 x 3 x 2.5 m box room (z up). N Gaussians are spread uniformly over its six faces, flattened
onto them (tangential std = 0.7 x mean spacing, normal std = 0.05 x spacing, random in-plane rotation),
opacity uniform in [0.5, 1.0], smooth random colours. The camera stands near a corner at (-1.8, -1.3, 1.2)
looking across the room at (2.0, 1.5, 1.2), fx = fy = 0.7 W (71 deg horizontal field of view), so about
43 % of the Gaussians are in view (PERF_NOTES' "100k (40k visible)").

Measured per (backend, resolution, N): ``fwd_ms`` = median time of a render under ``torch.no_grad``;
``fwd_bwd_ms`` = median of render + ``backward`` of a loss on colour, normalised depth and alpha, with
gradients w.r.t. means, quats, scales, opacities, colours and the pose tangent ``xi``. Also reported:
visible Gaussians, (tile, Gaussian) pairs, the first-call time in a fresh process (numba cache load or
cold compile, measured in a subprocess), and the peak RSS of this process.

Usage: ``python benchmarks/bench_rasterizer.py [--quick] [--repeats 7] [--threads 2] [--backends cpu,reference]``
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time

import ggfslam  # noqa: F401  (first: its numba and OpenMP settings, ggfslam/numba_setup.py, precede torch's threads)
import numpy as np
import torch

from ggfslam.render.scenes import room_camera, room_scene


def _busy_seconds() -> float:
    """CPU seconds spent by the whole machine so far (all cores, /proc/stat), or nan where unavailable."""
    try:
        with open("/proc/stat") as f:
            vals = [float(x) for x in f.readline().split()[1:]]
        idle = vals[3] + (vals[4] if len(vals) > 4 else 0.0)
        return (sum(vals[:8]) - idle) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return float("nan")


def _own_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def wait_for_idle(max_wait_s: float, other_cores: float = 0.15) -> float:
    """Wait (up to ``max_wait_s``) until other processes use less than ``other_cores`` cores over 2 s."""
    t_end = time.time() + max_wait_s
    while True:
        b0, o0, t0 = _busy_seconds(), _own_seconds(), time.perf_counter()
        time.sleep(2.0)
        others = ((_busy_seconds() - b0) - (_own_seconds() - o0)) / (time.perf_counter() - t0)
        if not (others > other_cores) or time.time() > t_end:  # nan (no /proc/stat) counts as idle
            return others


def _median_ms(fn, repeats: int, warmup: int = 3) -> tuple[float, list[float], float]:
    """Median and all times (ms) of ``fn``; also the cores used by *other* processes meanwhile."""
    for _ in range(warmup):
        fn()
    ts = []
    b0, o0, t0 = _busy_seconds(), _own_seconds(), time.perf_counter()
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t) * 1e3)
    others = ((_busy_seconds() - b0) - (_own_seconds() - o0)) / (time.perf_counter() - t0)
    return float(np.median(ts)), ts, others


def bench_one(backend: str, width: int, height: int, n: int, repeats: int) -> dict:
    from ggfslam.render import rasterize

    sc = room_scene(n)
    cam, T_cw = room_camera(width, height)
    T = torch.from_numpy(T_cw)
    params = {k: torch.from_numpy(sc[k]) for k in ("means", "quats", "scales", "opacities", "colors")}
    g = torch.Generator().manual_seed(1)
    wc = torch.rand(height, width, 3, generator=g)
    wd = torch.rand(height, width, generator=g)
    wa = torch.rand(height, width, generator=g)

    def fwd():
        with torch.no_grad():
            return rasterize(**params, camera=cam, T_cw=T, backend=backend)

    leaves = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)

    def fwd_bwd():
        for v in list(leaves.values()) + [xi]:
            v.grad = None
        out = rasterize(**leaves, camera=cam, T_cw=T, pose_xi=xi, backend=backend)
        loss = (out.color * wc).sum() + (out.depth * wd).sum() + (out.alpha * wa).sum()
        loss.backward()
        return out

    out = fwd()
    res = {"backend": backend, "width": width, "height": height, "n_gaussians": n,
           "n_visible": int(out.visible.sum())}
    if backend == "cpu":
        from ggfslam.render.cpu import rasterize_cpu
        from ggfslam.render.types import Intrinsics, RenderSettings

        with torch.no_grad():
            *_, info = rasterize_cpu(*(params[k] for k in ("means", "quats", "scales", "opacities", "colors")),
                                       None, T, Intrinsics.of(cam), RenderSettings(), torch.zeros(3), None)
        res["n_tile_pairs"] = info.n_pairs
    res["fwd_ms"], ts, o1 = _median_ms(fwd, repeats)
    res["fwd_bwd_ms"], ts2, o2 = _median_ms(fwd_bwd, repeats)
    res["repeats"] = repeats
    res["fwd_min_ms"], res["fwd_bwd_min_ms"] = min(ts), min(ts2)
    res["fwd_max_ms"], res["fwd_bwd_max_ms"] = max(ts), max(ts2)
    res["other_processes_cores"] = round(max(o1, o2), 2)  # CPU load of other processes while measuring
    for k in ("fwd_ms", "fwd_bwd_ms", "fwd_min_ms", "fwd_bwd_min_ms", "fwd_max_ms", "fwd_bwd_max_ms"):
        res[k] = round(res[k], 2)
    return res


def first_call_seconds(threads: int) -> dict:
    """Time of the first render + backward in a fresh process: with an empty numba cache (cold compile, in a
    temporary cache directory) and again with that cache filled (what every later process pays)."""
    import tempfile

    code = (
        "import time; t0 = time.perf_counter(); import torch, numba; numba.set_num_threads(%d);\n"
        "from ggfslam.render import rasterize; from ggfslam.render.scenes import room_scene, room_camera;\n"
        "sc = room_scene(2000); cam, T = room_camera(160, 120);\n"
        "p = {k: torch.from_numpy(sc[k]).requires_grad_(True) for k in ('means','quats','scales','opacities','colors')};\n"
        "t1 = time.perf_counter(); o = rasterize(**p, camera=cam, T_cw=torch.from_numpy(T), backend='cpu');\n"
        "(o.color.sum() + o.depth.sum()).backward(); t2 = time.perf_counter();\n"
        "print(t2 - t1, t1 - t0)" % threads
    )
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    out = {}
    with tempfile.TemporaryDirectory(prefix="ggfslam-numba-") as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for label in ("cold_compile", "cached"):
            r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root, env=env)
            if r.returncode != 0:
                out[label] = {"error": (r.stderr.strip().splitlines() or ["failed"])[-1]}
                continue
            first, imp = (float(x) for x in r.stdout.split())
            out[label] = {"first_render_fwd_bwd_s": round(first, 3), "import_s": round(imp, 3)}
    out["note"] = "numba cache: NUMBA_CACHE_DIR, default ~/.cache/ggfslam/numba (set on import ggfslam)"
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small subset: 160x120 and 320x240 at 20k and 100k")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--ref-repeats", type=int, default=2, help="repeats for the (slow) reference backend")
    ap.add_argument("--threads", type=int, default=None, help="numba and torch threads (default: leave as is)")
    ap.add_argument("--backends", default="cpu,reference")
    ap.add_argument("--wait-idle", type=float, default=0.0,
                    help="before each configuration wait up to this many seconds for other processes to go idle")
    ap.add_argument("--ref-max-pairs", type=float, default=1.5e5,
                    help="skip the reference where (tile, Gaussian) pairs exceed this (memory: ~256 floats each)")
    ap.add_argument("--configs", default=None,
                    help="only these configurations, comma-separated WxHxN (e.g. 320x240x100000,640x480x100000)")
    ap.add_argument("--no-compile", action="store_true", help="skip the first-call (cold compile) measurement")
    args = ap.parse_args(argv)
    import numba

    if args.threads:
        numba.set_num_threads(args.threads)
        torch.set_num_threads(args.threads)
    res_list = [(160, 120), (320, 240), (640, 480)]
    n_list = [20_000, 100_000, 300_000]
    if args.quick:
        res_list, n_list = [(160, 120), (320, 240)], [20_000, 100_000]
    configs = None
    if args.configs:
        configs = [tuple(int(v) for v in c.lower().split("x")) for c in args.configs.split(",") if c]
    backends = [b for b in args.backends.split(",") if b]
    report = {
        "machine": {"cpus": os.cpu_count(), "numba_threads": numba.get_num_threads(),
                    "torch_threads": torch.get_num_threads(), "python": platform.python_version(),
                    "torch": torch.__version__, "numba": numba.__version__,
                    "threading_layer": None},
        "scene": "synthetic room 4x3x2.5 m, Gaussians on the faces, tangential std 0.7 x spacing, opacity U(0.5, 1)",
        "loss": "sum(color*w1) + sum(depth*w2) + sum(alpha*w3); grads: means, quats, scales, opacities, colors, pose xi",
    }
    if "cpu" in backends and not args.no_compile:
        report["compile"] = first_call_seconds(numba.get_num_threads())
    results = []
    cpu_pairs = {}
    for backend in backends:
        for (w, h) in res_list:
            for n in n_list:
                key = (w, h, n)
                if configs is not None and key not in configs:
                    continue
                if backend == "reference":
                    pairs = cpu_pairs.get(key)
                    if pairs is not None and pairs > args.ref_max_pairs:
                        results.append({"backend": backend, "width": w, "height": h, "n_gaussians": n,
                                        "skipped": f"{pairs} tile pairs > --ref-max-pairs {args.ref_max_pairs:.0f}"
                                                   " (autograd memory / minutes per repeat)"})
                        continue
                reps = args.repeats if backend != "reference" else args.ref_repeats
                if args.wait_idle > 0:
                    wait_for_idle(args.wait_idle)
                r = bench_one(backend, w, h, n, reps)
                if backend == "cpu":
                    cpu_pairs[key] = r.get("n_tile_pairs", 0)
                results.append(r)
                print(json.dumps(r), file=sys.stderr, flush=True)
    report["results"] = results
    speedups = []
    for r in results:
        if r["backend"] != "reference" or "skipped" in r:
            continue
        c = next((x for x in results if x["backend"] == "cpu" and x["width"] == r["width"]
                  and x["n_gaussians"] == r["n_gaussians"]), None)
        if c:
            speedups.append({"width": r["width"], "height": r["height"], "n_gaussians": r["n_gaussians"],
                             "fwd_x": round(r["fwd_ms"] / c["fwd_ms"], 1),
                             "fwd_bwd_x": round(r["fwd_bwd_ms"] / c["fwd_bwd_ms"], 1)})
    report["cpu_speedup_over_reference"] = speedups
    try:
        report["machine"]["threading_layer"] = numba.threading_layer()
    except Exception:
        pass
    from ggfslam.render import cpu as render_cpu

    report["machine"]["malloc_tuning"] = render_cpu._ALLOCATOR_TUNED  # see ggfslam.render.cpu.tune_allocator
    report["machine"]["GOMP_SPINCOUNT"] = os.environ.get("GOMP_SPINCOUNT")
    report["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
