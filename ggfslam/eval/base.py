"""The small interface every ggfslam metric shares (modelled on evo's): feed data, then ask for statistics."""
from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

STATISTICS = ("rmse", "mean", "median", "std", "min", "max", "sse")


class Metric(ABC):
    """A metric accumulates per-sample errors with ``process_data`` and reports ``get_statistic``."""

    name: str = "metric"
    unit: str = ""

    def __init__(self) -> None:
        self.values: list[float] = []

    @abstractmethod
    def process_data(self, data) -> None:
        """Compute per-sample errors from ``data`` and append them to ``self.values``."""

    def get_statistic(self, statistic: str = "mean") -> float:
        """One statistic of the accumulated values (rmse, mean, median, std, min, max, sse)."""
        if statistic not in STATISTICS:
            raise ValueError(f"unknown statistic {statistic!r}; choose from {', '.join(STATISTICS)}")
        v = np.asarray(self.values, dtype=np.float64)
        if v.size == 0:
            return float("nan")
        return float({
            "rmse": lambda: np.sqrt(np.mean(v ** 2)),
            "mean": v.mean, "median": lambda: np.median(v), "std": v.std,
            "min": v.min, "max": v.max, "sse": lambda: np.sum(v ** 2),
        }[statistic]())

    def get_all_statistics(self) -> dict[str, float]:
        """Every statistic as a dict."""
        return {s: self.get_statistic(s) for s in STATISTICS}
