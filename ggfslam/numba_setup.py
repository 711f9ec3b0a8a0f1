"""numba and OpenMP settings for every compiled module of ggfslam, applied when the package is imported.

- Cache: compiled code goes to ``~/.cache/ggfslam/numba`` (outside the repository) unless
  ``NUMBA_CACHE_DIR`` is set.
- Threading layer: OpenMP first. numba's default order tries TBB first and, where the installed TBB is
  too old, warns on every run before falling back to OpenMP anyway. ``NUMBA_THREADING_LAYER`` or
  ``NUMBA_THREADING_LAYER_PRIORITY`` set by the user win.
- OpenMP's idle threads spin ``GOMP_SPINCOUNT = 10000`` times before they sleep (libgomp's default: 300000),
  unless ``GOMP_SPINCOUNT`` or ``OMP_WAIT_POLICY`` is set. torch's bundled libgomp reads it at ``import torch``
  and numba's OpenMP layer (the system's libgomp) at its first parallel call: importing ggfslam before torch is
  what makes it hold for torch's threads too.
  With the default, threads waiting at a parallel region's barrier keep their cores busy, so a run sharing the
  cores with anything else starves its own working threads. Measured on the 2-core VM (2026-12-06,
  ``benchmarks/bench_mapping.py --throughput``, whole-image step at 320x240, medians): alone 56-60 ms either way
  (six runs each, interleaved); beside a process that keeps one core busy 322-380 ms with the default,
  141-143 ms with 10000 (1000: 106-111 ms beside it, but 64-68 ms alone).

Set through the environment, because numba reads its configuration from it when imported and re-reads it
later; when numba was imported before ggfslam, its config attributes are set as well.
"""
from __future__ import annotations

import os
import sys

CACHE_DIR = os.path.join(os.path.expanduser("~"), ".cache", "ggfslam", "numba")
LAYER_PRIORITY = ("omp", "tbb", "workqueue")
GOMP_SPINCOUNT = "10000"  # spins of an idle OpenMP thread before it sleeps (module docstring)


def configure() -> None:
    """Apply the cache location, threading-layer order and OpenMP spinning (idempotent; the user's environment
    wins)."""
    if not os.environ.get("GOMP_SPINCOUNT") and not os.environ.get("OMP_WAIT_POLICY"):
        os.environ["GOMP_SPINCOUNT"] = GOMP_SPINCOUNT
    if not os.environ.get("NUMBA_CACHE_DIR"):
        os.environ["NUMBA_CACHE_DIR"] = CACHE_DIR
    own_priority = not os.environ.get("NUMBA_THREADING_LAYER_PRIORITY") and not os.environ.get("NUMBA_THREADING_LAYER")
    if own_priority:
        os.environ["NUMBA_THREADING_LAYER_PRIORITY"] = " ".join(LAYER_PRIORITY)
    numba = sys.modules.get("numba")
    if numba is not None:  # imported before us: its config was read without these values
        if not numba.config.CACHE_DIR:
            numba.config.CACHE_DIR = os.environ["NUMBA_CACHE_DIR"]
        if own_priority:
            numba.config.THREADING_LAYER_PRIORITY = list(LAYER_PRIORITY)
