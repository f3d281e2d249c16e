"""Contrast enhancement of difference rows along the database axis (paper eq. 2)."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float32]

# A window whose population std is below this is flat and its z-scores are 0.
FLAT_WINDOW_STD = 1e-9


def enhance(rows: FloatArray, epsilon: int) -> FloatArray:
    """Local z-score of every element over the window j - eps/2 .. j + eps/2, made non-negative.

    The window is clipped at the ends of the row. A z-score over m samples is at most sqrt(m - 1)
    in magnitude, so adding the constant sqrt(epsilon) makes every value >= 0 (the gamma ratio
    needs non-negative scores) without shifting rows by their own minimum.
    """
    rows64 = np.asarray(rows, dtype=np.float64)
    if rows64.ndim != 2:
        raise ValueError("enhance expects a 2-D array of rows")
    n = rows64.shape[1]
    if n == 0:
        return np.zeros(rows64.shape, np.float32)
    half = epsilon // 2
    index = np.arange(n)
    lo = np.maximum(index - half, 0)
    hi = np.minimum(index + half, n - 1) + 1
    count = (hi - lo).astype(np.float64)
    zero = np.zeros((rows64.shape[0], 1))
    csum = np.concatenate([zero, np.cumsum(rows64, axis=1)], axis=1)
    # Second moments about the row mean keep the cumulative sums well conditioned.
    centred = rows64 - rows64.mean(axis=1, keepdims=True)
    csq = np.concatenate([zero, np.cumsum(centred * centred, axis=1)], axis=1)
    ccen = np.concatenate([zero, np.cumsum(centred, axis=1)], axis=1)
    mean = (csum[:, hi] - csum[:, lo]) / count
    mean_c = (ccen[:, hi] - ccen[:, lo]) / count
    var = (csq[:, hi] - csq[:, lo]) / count - mean_c * mean_c
    std = np.sqrt(np.maximum(var, 0.0))
    flat = std < FLAT_WINDOW_STD
    z = np.where(flat, 0.0, (rows64 - mean) / np.where(flat, 1.0, std))
    return (z + math.sqrt(epsilon)).astype(np.float32)
