"""Compiled statistics of the closed-form exposure fit (``Mapper._fit_exposure``): one pass over the pixels.

In torch the fit's masks, products and five reductions over an [H, W, 3] image were ~12 ops and 3.8 ms a mapping
step at 640x480; here each row's sums are formed in one loop (in float64) and the rows summed in order, so the
result does not depend on the number of threads.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, parallel=True)
def _row_moments(x, y, alpha, min_alpha, rows):
    """rows [H, 13] = per row: covered pixels, then per channel the sums of x, y, x y, x x over them."""
    H, W, C = x.shape
    for h in prange(H):
        s = np.zeros(13)
        for w in range(W):
            if alpha[h, w] > min_alpha:
                s[0] += 1.0
                for c in range(C):
                    a, b = np.float64(x[h, w, c]), np.float64(y[h, w, c])
                    s[1 + c] += a
                    s[4 + c] += b
                    s[7 + c] += a * b
                    s[10 + c] += a * a
        rows[h] = s


def covered_moments(x: np.ndarray, y: np.ndarray, alpha: np.ndarray, min_alpha: float) -> tuple[float, np.ndarray]:
    """Over the pixels with ``alpha`` [H, W] > min_alpha: their count and the sums [4, 3] (per channel) of x, y,
    x y and x x, for a render x and an image y [H, W, 3] (float32 or float64)."""
    if x.shape != y.shape or x.ndim != 3 or x.shape[2] != 3 or alpha.shape != x.shape[:2]:
        raise ValueError(f"covered_moments: expected images [H, W, 3] and alpha [H, W], got {x.shape}, {y.shape} "
                         f"and {alpha.shape}")
    rows = np.empty((x.shape[0], 13))
    _row_moments(x, y, alpha, float(min_alpha), rows)
    total = rows.sum(axis=0)
    return float(total[0]), total[1:].reshape(4, 3)
