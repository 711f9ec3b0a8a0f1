"""Compiled statistics of the closed-form exposure fit (``Mapper._fit_exposure``): one pass over the pixels.

In torch the fit's masks, products and five reductions over an [H, W, 3] image were ~12 ops and 3.8 ms a mapping
step at 640x480; here each row's sums are formed in one loop (in float64) and the rows summed in order, so the
result does not depend on the number of threads.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, parallel=True)
def _row_moments(x, y, alpha, min_alpha, r2, v0, v1, rows):
    """rows [H, 13] = per row: covered pixels, then per channel the sums of x, y, x y, x x over them, with x times
    the vignetting gain ``1 + v0 r2 + v1 r2^2`` where r2 [H, W] is given (else [0, 0]: x as it is). The gain and the
    product are formed in x's type, in the order ``Mapper._vignetted`` forms them in torch, so the sums are those of
    its image to the bit."""
    H, W, C = x.shape
    vig = r2.shape[0] > 0
    one = x.dtype.type(1.0)
    for h in prange(H):
        s = np.zeros(13)
        for w in range(W):
            if alpha[h, w] > min_alpha:
                s[0] += 1.0
                gain = one
                if vig:
                    r = r2[h, w]
                    gain = (one + v0 * r) + (v1 * r) * r
                for c in range(C):
                    xv = x[h, w, c] * gain if vig else x[h, w, c]
                    a, b = np.float64(xv), np.float64(y[h, w, c])
                    s[1 + c] += a
                    s[4 + c] += b
                    s[7 + c] += a * b
                    s[10 + c] += a * a
        rows[h] = s


def covered_moments(x: np.ndarray, y: np.ndarray, alpha: np.ndarray, min_alpha: float, r2: np.ndarray | None = None,
                    vignette: tuple[float, float] = (0.0, 0.0)) -> tuple[float, np.ndarray]:
    """Over the pixels with ``alpha`` [H, W] > min_alpha: their count and the sums [4, 3] (per channel) of x, y,
    x y and x x, for a render x and an image y [H, W, 3] (float32 or float64); with r2 [H, W] (squared ray
    radius) x is first vignetted by the gain ``1 + vignette[0] r2 + vignette[1] r2^2``."""
    if x.shape != y.shape or x.ndim != 3 or x.shape[2] != 3 or alpha.shape != x.shape[:2]:
        raise ValueError(f"covered_moments: expected images [H, W, 3] and alpha [H, W], got {x.shape}, {y.shape} "
                         f"and {alpha.shape}")
    if r2 is not None and r2.shape != alpha.shape:
        raise ValueError(f"covered_moments: expected r2 {alpha.shape}, got {r2.shape}")
    rows = np.empty((x.shape[0], 13))
    f = x.dtype.type
    r2 = np.zeros((0, 0), x.dtype) if r2 is None else np.ascontiguousarray(r2, x.dtype)
    _row_moments(x, y, alpha, float(min_alpha), r2, f(vignette[0]), f(vignette[1]), rows)
    total = rows.sum(axis=0)
    return float(total[0]), total[1:].reshape(4, 3)
