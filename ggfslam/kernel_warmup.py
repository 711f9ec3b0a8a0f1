"""The compiled kernels: compiled on every core at once on a fresh install, loaded before a live input starts.

numba compiles a kernel the first time it is called, one kernel at a time, in the process that calls it, and keeps
the machine code in its cache (``ggfslam/numba_setup.py``; entries are per host CPU and per source file version).
On a fresh install a run therefore first spends a minute and a half compiling on one core: on the 2-core VM
(2026-12-07, an empty cache) 89 s, of which the rasterizer's kernels 52 s (135 s and 88 s before the compositing
kernels' bodies became worker functions, ``render/kernels_cpu.py: _WorkerPipeline``); the first `ggfslam demo` took
4 min 6 s then against 1 min 34 s with the cache filled. ``compile_kernels`` splits them
into ``PARTS`` of similar compile time and compiles them in worker processes side by side, one part after another
per worker; ``slam.run`` starts it when the cache is not known to be complete, overlapping its dataset's opening
(the demo renders its sequence meanwhile), and waits for it before the first frame. A marker file in numba's cache
directory, keyed by the numba / llvmlite / Python versions, the host CPU and the kernel modules' source stamps,
records a complete compile, so later runs skip this after one check. A part that fails only costs time: the run
compiles what is missing as before, and the failure is logged."""
from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import re
import sys
import time
from pathlib import Path

import numpy as np

log = logging.getLogger("ggfslam.kernels")

PARTS = ("mapping", "projection", "composite_backward", "composite_forward", "tracking")
"""Longest first (compile seconds beside another worker on the 2-core VM, 2026-12-07: 38, 27, 14, 12, 5): workers
claim them in this order, which on two workers gives {mapping, composite_forward} and {projection, composite_backward,
tracking}, 50 and 46 s (54 s wall with the processes' start)."""
MARKER_PREFIX = "ggfslam-kernels-"
_PACKAGE = Path(__file__).resolve().parent


@functools.lru_cache(maxsize=1)
def _kernel_sources() -> list[Path]:
    """The package's source files with numba kernels numba caches (their stamps key the marker). Scanned once per
    process (~20 ms; a run checks the marker two or three times); their stamps are read at every check."""
    cached = re.compile(r"@(numba\.)?njit\([^)]*cache=True")
    return sorted(p for p in _PACKAGE.rglob("*.py") if cached.search(p.read_text(encoding="utf-8", errors="ignore")))


def cache_key() -> str:
    """What a complete compile is valid for: numba, llvmlite and Python versions, host CPU, kernel source stamps."""
    import llvmlite
    import llvmlite.binding as llvm
    import numba

    stamps = [(str(p.relative_to(_PACKAGE)), p.stat().st_mtime_ns, p.stat().st_size) for p in _kernel_sources()]
    ident = [numba.__version__, llvmlite.__version__, sys.version, llvm.get_host_cpu_name(),
             llvm.get_host_cpu_features().flatten(), stamps]
    return hashlib.sha256(json.dumps(ident).encode()).hexdigest()[:20]


def _cache_dir() -> Path | None:
    """numba's cache directory, or None where caching is off (``NUMBA_DISABLE_JIT``)."""
    if os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0"):
        return None
    import numba

    d = numba.config.CACHE_DIR or os.environ.get("NUMBA_CACHE_DIR")
    return Path(d) if d else None


def _marker(cache: Path) -> Path:
    return cache / f"{MARKER_PREFIX}{cache_key()}.json"


def kernels_compiled() -> bool:
    """Whether every part was compiled into the cache for this install and host (or there is no cache to fill)."""
    cache = _cache_dir()
    return cache is None or _marker(cache).exists()


# --------------------------------------------------------------------------------------------------
# the parts (each compiles its kernels on a few elements; run in a worker process)
# --------------------------------------------------------------------------------------------------
def _default_config():
    from ggfslam.config import config_from_dict

    return config_from_dict({"dataset": {"kind": "synthetic"}})


def _tiny_camera():
    from ggfslam.data.types import Camera

    return Camera(40.0, 40.0, 31.5, 23.5, 64, 48, 1000.0)


def load_kernels(config, camera, mapping: bool, backend: str | None = None, tracking: bool = True) -> None:
    """Run tracking's compiled kernels (projection matching, pose refinement; unless not ``tracking``) and, with
    ``mapping``, the mapper's (seeding, training steps with their losses, the field) once on a throwaway keyframe of
    ``camera``'s size, with ``backend`` (default: the config's) rendering: compiles them, or loads them from the
    cache."""
    import tempfile

    rng = np.random.default_rng(0)
    if tracking:
        from ggfslam.frontend.matching import match_projected
        from ggfslam.frontend.pose_refine import refine_pose

        pts = rng.uniform([-1, -1, 2], [1, 1, 3], (16, 3))  # [16, 3] in front of the camera
        uv = np.column_stack([camera.fx * pts[:, 0] / pts[:, 2] + camera.cx,
                              camera.fy * pts[:, 1] / pts[:, 2] + camera.cy])
        desc = rng.integers(0, 256, (16, 32), dtype=np.uint8)
        level = np.zeros(16, np.int64)
        match_projected(uv, desc, level, uv, desc, level, 5.0, np.ones(1), 50, 0.9)
        refine_pose(np.eye(4), pts, uv, pts[:, 2], np.ones(16), camera, config.tracking.virtual_baseline)
    if mapping:
        from ggfslam.mapping.mapper import Mapper
        from ggfslam.render.types import RenderSettings

        h, w = camera.height, camera.width
        rgb = rng.random((h, w, 3), dtype=np.float32)  # [H, W, 3]
        # [H, W] two walls meeting in a fold: the anchors along it are curved, so the field's plane borrowing runs
        depth = np.full((h, w), 2.0, np.float32) + 0.5 * np.abs(np.linspace(-1, 1, w, dtype=np.float32))
        with tempfile.TemporaryDirectory(prefix="ggfslam-warmup-") as tmp:
            pose = np.eye(4)
            m = Mapper(config.mapping, camera, RenderSettings(backend=backend or config.render.backend),
                       lambda: {0: pose}, tmp, config.runtime.seed, ggf=config.ggf)
            m.store.add(0, 0, rgb, depth)
            m.seed_keyframe(0)
            m.train(2, focus=0)


def _part_mapping() -> None:
    """The mapper's kernels but the rasterizer's and tracking's (those are the other parts): a training step
    rendered by the plain-torch reference backend."""
    load_kernels(_default_config(), _tiny_camera(), mapping=True, backend="reference", tracking=False)


def _part_tracking() -> None:
    """Tracking's kernels and the geometry's: matching, pose refinement, depth registration and normals, ORB
    nearest neighbours for loop closure."""
    from ggfslam.backend.place_recognition import hamming_knn2
    from ggfslam.geometry.depth import normals_from_depth, register_depth

    cam = _tiny_camera()
    load_kernels(_default_config(), cam, mapping=False)
    depth = np.full((cam.height, cam.width), 1.5, np.float32)
    k = (cam.fx, cam.fy, cam.cx, cam.cy)
    register_depth(depth, k, k, np.eye(4), cam.width, cam.height)
    normals_from_depth(depth, *k)
    desc = np.random.default_rng(0).integers(0, 256, (8, 32), dtype=np.uint8)
    hamming_knn2(desc, desc)


def _run_part(name: str) -> None:
    if name not in PARTS:
        raise ValueError(f"unknown kernel part {name!r}; expected one of {', '.join(PARTS)}")
    if name == "mapping":
        _part_mapping()
    elif name == "tracking":
        _part_tracking()
    else:  # the rasterizer's groups (``render.cpu.KERNEL_STAGES``), which compile_kernels checks
        from ggfslam.render.cpu import compile_kernels

        compile_kernels(name)


def _claim(claims: Path, name: str) -> bool:
    """Take part ``name`` for this worker unless another took it (an exclusive create of its claim file)."""
    try:
        os.close(os.open(claims / name, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        return True
    except FileExistsError:
        return False


def worker_main(claims: Path) -> None:
    """A worker: compile every part of ``PARTS`` no other worker has claimed, in order; one JSON line each on stdout
    (part, seconds, error or null)."""
    import torch

    torch.set_num_threads(1)  # the workers share the cores; compiling is single-threaded anyway
    for name in PARTS:
        if not _claim(claims, name):
            continue
        t0 = time.perf_counter()
        error = None
        try:
            _run_part(name)
        except Exception as e:  # noqa: BLE001 - reported to the parent, which logs it
            error = f"{type(e).__name__}: {e}"
        print(json.dumps([name, round(time.perf_counter() - t0, 2), error]), flush=True)


# --------------------------------------------------------------------------------------------------
# running the parts side by side
# --------------------------------------------------------------------------------------------------
class KernelCompile:
    """Parts being compiled by worker processes (``compile_kernels(background=True)``). The workers are separate
    interpreters running this module (``python -m ggfslam.kernel_warmup``), not multiprocessing children, which
    would import the caller's main script again."""

    def __init__(self, cache: Path, jobs: int, lock):
        import subprocess
        import tempfile

        self.cache, self.t0, self._lock = cache, time.perf_counter(), lock
        self._claims = tempfile.TemporaryDirectory(prefix="ggfslam-kernels-")
        work = Path(self._claims.name)
        cmd = [sys.executable, "-m", "ggfslam.kernel_warmup", "--worker", str(work)]
        # this package's folder first on the path: the caller may have imported it from a source tree
        path = os.pathsep.join(x for x in (str(_PACKAGE.parent), os.environ.get("PYTHONPATH", "")) if x)
        env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "OMP_NUM_THREADS": "1", "PYTHONPATH": path}
        # output to files, not pipes: a worker that wrote more than a pipe holds would wait for a reader
        self._logs = [(work / f"worker{i}.out", work / f"worker{i}.err") for i in range(jobs)]
        self._procs = []
        for out, err in self._logs:
            with open(out, "w") as fo, open(err, "w") as fe:
                self._procs.append(subprocess.Popen(cmd, stdout=fo, stderr=fe, env=env))
        self.results: dict[str, tuple[float, str | None]] = {}

    def wait(self) -> bool:
        """Wait for every part; write the marker when all compiled. Returns whether they did."""
        try:
            for p, (out_file, err_file) in zip(self._procs, self._logs):
                p.wait()
                out, err = out_file.read_text(errors="replace"), err_file.read_text(errors="replace")
                for line in out.splitlines():
                    try:
                        name, seconds, error = json.loads(line)
                    except ValueError:
                        continue  # not a report (a library printed something)
                    self.results[name] = (seconds, error)
                    if error:
                        log.warning("compiling the %s kernels failed (%s); the run compiles what it needs itself",
                                    name, error)
                if p.returncode != 0:
                    log.warning("a kernel compile worker ended with status %s: %s", p.returncode,
                                err.strip().splitlines()[-1] if err.strip() else "no message")
            ok = len(self.results) == len(PARTS) and not any(e for _, e in self.results.values())
            wall = time.perf_counter() - self.t0
            if ok:
                try:
                    _write_marker(self.cache, {name: s for name, (s, _) in self.results.items()}, wall,
                                  len(self._procs))
                except OSError as e:  # a read-only cache: numba could not keep the code either
                    log.warning("could not record the compiled kernels in %s (%s)", self.cache, e)
                    ok = False
            log.info("kernels compiled in %.0f s by %d processes (%s)", wall, len(self._procs),
                     ", ".join(f"{n} {s:.0f} s" for n, (s, _) in self.results.items()))
            return ok
        except BaseException:  # Ctrl-C while waiting: the workers stop too
            self.cancel()
            raise
        finally:
            self._release()

    def cancel(self) -> None:
        """Stop the workers (what they finished stays in the cache)."""
        for p in self._procs:
            if p.poll() is None:
                p.terminate()
        for p in self._procs:
            p.wait()
        self._release()

    def _release(self) -> None:
        if self._claims is not None:
            self._claims.cleanup()
            self._claims = None
        if self._lock is not None:
            self._lock.close()  # closing the file releases its lock
            self._lock = None


def _lock_file(cache: Path):
    """An exclusive lock on the cache's compile (one process compiles, the others wait for it); None off POSIX."""
    try:
        import fcntl
    except ImportError:  # Windows: no lock; at worst two processes compile the same kernels
        return None
    f = open(cache / "ggfslam-kernels.lock", "a")  # noqa: SIM115 - held until the compile ends
    try:
        fcntl.flock(f, fcntl.LOCK_EX)
    except OSError:  # a file system without locks (some network mounts): go on unlocked
        f.close()
        return None
    return f


def _write_marker(cache: Path, parts: dict[str, float], wall: float, jobs: int) -> None:
    from ggfslam.atomic import write_text_atomic

    for old in cache.glob(f"{MARKER_PREFIX}*.json"):
        old.unlink(missing_ok=True)
    write_text_atomic(_marker(cache), json.dumps({"parts_seconds": parts, "wall_seconds": round(wall, 1),
                                                  "processes": jobs}, indent=1))


def compile_kernels(jobs: int | None = None, background: bool = False) -> KernelCompile | None:
    """Compile every kernel into numba's cache, ``jobs`` processes side by side (default: ``GGFSLAM_COMPILE_JOBS``,
    else one per core; at most one per part), unless the marker says it is done. With ``background`` returns the
    running compile (its ``wait()`` or ``cancel()``), else waits for it; None when there is nothing to do
    (``jobs`` 0 turns it off: runs then compile lazily, one kernel at a time)."""
    if jobs is None:
        jobs = int(os.environ.get("GGFSLAM_COMPILE_JOBS", os.cpu_count() or 1))
    cache = _cache_dir()
    if jobs <= 0 or cache is None or kernels_compiled():
        return None
    try:
        cache.mkdir(parents=True, exist_ok=True)
        lock = _lock_file(cache)
    except OSError as e:  # an unwritable cache: numba compiles in the run (and warns that it cannot cache)
        log.warning("cannot compile the kernels into %s (%s)", cache, e)
        return None
    if kernels_compiled():  # another process finished the compile while this one waited for the lock
        if lock is not None:
            lock.close()
        return None
    n = min(len(PARTS), jobs)
    log.info("compiling the kernels (first run of this install on this machine) in %d processes ...", n)
    c = KernelCompile(cache, n, lock)
    if background:
        return c
    c.wait()
    return None


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description="Compile ggfslam's numba kernels into the cache.")
    ap.add_argument("--worker", metavar="CLAIMS_DIR", help="(internal) run as a worker claiming parts in this folder")
    ap.add_argument("--jobs", type=int, default=None, help="worker processes (default: one per core)")
    a = ap.parse_args()
    if a.worker:
        worker_main(Path(a.worker))
    else:
        logging.basicConfig(level=logging.INFO, format="%(message)s")
        compile_kernels(a.jobs)
