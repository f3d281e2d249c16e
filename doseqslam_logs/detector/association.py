"""Image-to-image association inside a sequence (paper III-C, last paragraph)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .trajectory import TrajectoryScores

FloatArray = npt.NDArray[np.float32]
IntArray = npt.NDArray[np.int64]


def trajectory_matches(scores: TrajectoryScores, best_start: int) -> IntArray:
    """Each query frame z gets the frame on the best trajectory: j* + round(v* z)."""
    matches: IntArray = best_start + scores.best_offsets(best_start)
    return matches


def greedy_matches(enhanced: FloatArray, best_start: int, velocity_max: float) -> IntArray:
    """The paper's greedy search: each query row's lowest enhanced difference among the
    columns j* .. j* + round(v_max * length), clipped to the database."""
    length, database = enhanced.shape
    stop = min(best_start + int(np.floor(velocity_max * length + 0.5)), database - 1) + 1
    window = enhanced[:, best_start:stop]
    matches: IntArray = best_start + np.argmin(window, axis=1).astype(np.int64)
    return matches


def pair_differences(enhanced: FloatArray, matches: IntArray) -> FloatArray:
    """The enhanced difference of each (query row, matched column) pair."""
    return np.asarray(enhanced[np.arange(len(matches)), matches], dtype=np.float32)
