"""Contrast enhancement of difference rows along the database axis (paper eq. 2)."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float32]

# A window whose population std is below this is flat and its z-scores are 0.
FLAT_WINDOW_STD = 1e-9
# Rows are enhanced in chunks of about this many elements (at least one row): the float64
# temporaries of a long sequence against an hour of frames would otherwise take gigabytes, and
# the few dozen passes over each chunk run 2-3x faster while its temporaries stay in the
# CPU's cache (256 KB each) than when they spill to memory (tools/bench/sad.py).
CHUNK_ELEMENTS = 1 << 15


def enhance(rows: FloatArray, epsilon: int) -> FloatArray:
    """Local z-score of every element over the window j - eps/2 .. j + eps/2, made non-negative.

    The window is clipped at the ends of the row. A z-score over m samples is at most sqrt(m - 1)
    in magnitude, so adding the constant sqrt(epsilon) makes every value >= 0 (the gamma ratio
    needs non-negative scores) without shifting rows by their own minimum.
    """
    if rows.ndim != 2:
        raise ValueError("enhance expects a 2-D array of rows")
    out = np.empty(rows.shape, np.float32)
    step = max(1, CHUNK_ELEMENTS // max(rows.shape[1], 1))
    for first in range(0, rows.shape[0], step):
        out[first : first + step] = _enhance_chunk(rows[first : first + step], epsilon)
    return out


def _window_sum(values: npt.NDArray[np.float64], half: int) -> npt.NDArray[np.float64]:
    """Sum over the clipped window j - half .. j + half of every column, by shifted adds.

    Shifted adds (not cumulative sums) keep the variance exact: a cumulative sum over a long
    row cancels catastrophically when a window's spread is tiny next to the row's values.
    """
    n = values.shape[1]
    total: npt.NDArray[np.float64] = values.copy()
    for k in range(1, min(half, n - 1) + 1):
        total[:, : n - k] += values[:, k:]  # the element k to the right
        total[:, k:] += values[:, : n - k]  # the element k to the left
    return total


def _enhance_chunk(rows: FloatArray, epsilon: int) -> FloatArray:
    x = np.asarray(rows, dtype=np.float64)
    n = x.shape[1]
    if n == 0:
        return np.zeros(x.shape, np.float32)
    half = epsilon // 2
    index = np.arange(n)
    count = (np.minimum(index + half, n - 1) - np.maximum(index - half, 0) + 1).astype(np.float64)
    mean = _window_sum(x, half) / count
    squares = np.zeros_like(x)
    for k in range(-half, half + 1):
        lo, hi = max(0, -k), min(n, n - k)  # columns j whose neighbour j + k exists
        if lo >= hi:
            continue
        deviation = x[:, lo + k : hi + k] - mean[:, lo:hi]
        squares[:, lo:hi] += deviation * deviation
    std = np.sqrt(squares / count)
    flat = std < FLAT_WINDOW_STD
    z = np.where(flat, 0.0, (x - mean) / np.where(flat, 1.0, std))
    return (z + math.sqrt(epsilon)).astype(np.float32)
