"""Speed and memory: per-stage timers (frames per second) and peak resident memory."""
from __future__ import annotations

import resource
import sys
import time
from collections import defaultdict
from contextlib import contextmanager


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, in MiB."""
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024.0 if sys.platform != "darwin" else kb / 2**20


def current_rss_mb() -> float:
    """Resident set size of this process now, in MiB (Linux /proc; else the peak)."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
        return pages * resource.getpagesize() / 2**20
    except OSError:
        return peak_rss_mb()


class StageTimer:
    """Wall-clock time per named stage; ``fps(stage)`` = calls per second spent in that stage."""

    def __init__(self) -> None:
        self.total: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)

    @contextmanager
    def __call__(self, stage: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.total[stage] += time.perf_counter() - t0
            self.calls[stage] += 1

    def fps(self, stage: str) -> float:
        """Calls per second of a stage (0 when never called)."""
        t = self.total.get(stage, 0.0)
        return self.calls.get(stage, 0) / t if t > 0 else 0.0

    def summary(self) -> dict[str, dict[str, float]]:
        """{stage: {seconds, calls, fps, ms_per_call}}."""
        return {
            s: {
                "seconds": self.total[s],
                "calls": self.calls[s],
                "fps": self.fps(s),
                "ms_per_call": 1000 * self.total[s] / max(self.calls[s], 1),
            }
            for s in self.total
        }
