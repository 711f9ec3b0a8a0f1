"""The first-order model of one keyframe's GCGR residuals and the GTSAM factors that read it.

Between renders a GCGR factor (``factors.gcgr``, conventions there) is the model ``r0 + J Log(T0^-1 T)``: rows
r0 [N] and Jacobian J [N, 6] at the pose T0 [4, 4] (camera-to-world) of the last render, one isotropic noise
``sigma * sqrt(N / effective_pixels)`` per row under a per-row Huber kernel. ``LinearGCGR`` is that model as plain
arrays, without a renderer, and pickles: the solver process (``ggfslam.backend.solver_process``) builds GCGR
factors from it without torch or the map, so a bundle adjustment with GCGR does not hold this process's GIL
while it optimizes. ``factors.gcgr.GCGRModel`` extends it with the renders that make and refresh it.
"""
from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from ggfslam.config import GCGRConfig

KINDS = ("depth", "normal")
MIN_PIXELS = 16  # fewer usable pixels than this make no factor (a few pixels cannot hold a pose)


def moved_past(xi: np.ndarray, cfg: GCGRConfig) -> bool:
    """Whether a tangent step [6] leaves the region where the first-order model is trusted."""
    return bool(np.degrees(np.linalg.norm(xi[:3])) > cfg.relinearize_rotation
                or np.linalg.norm(xi[3:]) > cfg.relinearize_translation)


class LinearGCGR:
    """One keyframe's GCGR rows as a first-order model around T0; ``factors()`` are the GTSAM factors reading it."""

    relinearizes = False  # no renderer: the first-order model holds wherever it is linearized

    def __init__(self, key: int, T0: np.ndarray, rows0: dict[str, np.ndarray], jacobians: dict[str, np.ndarray],
                 cfg: GCGRConfig):
        self.key, self.cfg = key, cfg
        self.T0 = gtsam.Pose3(np.asarray(T0, np.float64))  # linearization point, T_wc
        self.rows0 = rows0  # kind -> [N] rows at T0
        self.jacobians = jacobians  # kind -> [N, 6] d rows / d xi at T0

    def __len__(self) -> int:
        return len(self.rows0["depth"])

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["T0"] = self.T0.matrix()
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.T0 = gtsam.Pose3(np.asarray(state["T0"], np.float64))

    def moved_past(self, T_wc: np.ndarray) -> bool:
        """Whether the pose T_wc [4, 4] is past the relinearization threshold from T0."""
        return moved_past(self.T0.localCoordinates(gtsam.Pose3(np.asarray(T_wc, np.float64))), self.cfg)

    def evaluate(self, kind: str, pose: gtsam.Pose3, H: list | None = None) -> np.ndarray:
        """Rows [N] of ``kind`` at ``pose`` from the first-order model; fills ``H[0]`` with the Jacobian [N, 6]."""
        J = self.jacobians[kind]
        if H is not None:
            H[0] = J
        return self.rows0[kind] + J @ self.T0.localCoordinates(pose)

    @property
    def row_sigma(self) -> float:
        """Noise of one row: ``sigma * sqrt(N / effective_pixels)`` (never below sigma)."""
        return self.cfg.sigma * float(np.sqrt(max(len(self) / self.cfg.effective_pixels, 1.0)))

    def noise(self) -> gtsam.noiseModel.Base:
        """Isotropic ``row_sigma`` per row under a per-row (scalar-reweighted) Huber kernel."""
        huber = gtsam.noiseModel.mEstimator.Huber.Create(
            self.cfg.huber, gtsam.noiseModel.mEstimator.Base.ReweightScheme.Scalar)
        return gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(len(self), self.row_sigma))

    def factor(self, kind: str) -> gtsam.CustomFactor:
        """The ``kind`` ('depth' or 'normal') GCGR factor on ``X(key)``."""
        if kind not in KINDS:
            raise ValueError(f"GCGR factor kind must be one of {KINDS}, got {kind!r}")

        def evaluate(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
            return self.evaluate(kind, values.atPose3(this.keys()[0]), H)

        return gtsam.CustomFactor(self.noise(), [X(self.key)], evaluate)

    def factors(self) -> dict[str, gtsam.CustomFactor]:
        """The factors by kind (``KINDS``: depth, normal); none when fewer than ``MIN_PIXELS`` pixels are usable."""
        if len(self) < MIN_PIXELS:
            return {}
        return {k: self.factor(k) for k in KINDS}

    def frozen(self) -> LinearGCGR:
        """This model as it stands (arrays copied), without anything that renders: picklable."""
        return LinearGCGR(self.key, self.T0.matrix(), {k: v.copy() for k, v in self.rows0.items()},
                          {k: v.copy() for k, v in self.jacobians.items()}, self.cfg)


def labelled_factors(models: list[LinearGCGR]) -> list[tuple[int, str, gtsam.CustomFactor]]:
    """(keyframe, kind, factor) of every factor of ``models``, in their order: what a BA graph adds and labels."""
    return [(m.key, kind, f) for m in models for kind, f in m.factors().items()]


__all__ = ["LinearGCGR", "labelled_factors", "moved_past", "KINDS", "MIN_PIXELS"]
