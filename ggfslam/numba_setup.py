"""numba settings for every compiled module of ggfslam, applied when the package is imported.

- Cache: compiled code goes to ``~/.cache/ggfslam/numba`` (outside the repository) unless
  ``NUMBA_CACHE_DIR`` is set.
- Threading layer: OpenMP first. numba's default order tries TBB first and, where the installed TBB is
  too old, warns on every run before falling back to OpenMP anyway. ``NUMBA_THREADING_LAYER`` or
  ``NUMBA_THREADING_LAYER_PRIORITY`` set by the user win.

Set through the environment, because numba reads its configuration from it when imported and re-reads it
later; when numba was imported before ggfslam, its config attributes are set as well.
"""
from __future__ import annotations

import os
import sys

CACHE_DIR = os.path.join(os.path.expanduser("~"), ".cache", "ggfslam", "numba")
LAYER_PRIORITY = ("omp", "tbb", "workqueue")


def configure() -> None:
    """Apply the cache location and threading-layer order (idempotent; the user's environment wins)."""
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
