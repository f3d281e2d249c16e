"""Trajectory scores over enhanced difference rows and their normalization (paper eq. 3-7)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float32]
IntArray = npt.NDArray[np.int64]


def offsets(velocity: float, length: int) -> IntArray:
    """Database offsets round(v * z) for z = 0 .. length-1, rounding halves up.

    The small epsilon makes e.g. 0.7 * 5 = 3.4999999999999996 round to 4 as intended.
    """
    z = np.arange(length, dtype=np.float64)
    return np.floor(velocity * z + 0.5 + 1e-9).astype(np.int64)


def distinct_velocities(velocities: Sequence[float], length: int) -> list[tuple[float, IntArray]]:
    """Velocities whose offsets differ, each group represented by the velocity nearest 1.0.

    Short sequences give identical offsets for several velocities (for one frame, all of them);
    scoring each only once saves work and makes the reported best velocity well defined.
    """
    seen: set[bytes] = set()
    out = []
    for v in sorted(velocities, key=lambda v: (abs(v - 1.0), v)):
        off = offsets(v, length)
        if off.tobytes() not in seen:
            seen.add(off.tobytes())
            out.append((v, off))
    return out


@dataclass(frozen=True)
class TrajectoryScores:
    """S_do[j] (mean enhanced difference of the best trajectory starting at database frame j)."""

    scores: FloatArray  # +inf where no trajectory fits wholly inside the database
    velocity_index: IntArray  # index into `velocities` of the best trajectory at each j
    velocities: tuple[tuple[float, IntArray], ...]

    def best_offsets(self, start: int) -> IntArray:
        return self.velocities[int(self.velocity_index[start])][1]

    def best_velocity(self, start: int) -> float:
        return self.velocities[int(self.velocity_index[start])][0]


def trajectory_scores(enhanced: FloatArray, velocities: Sequence[float]) -> TrajectoryScores:
    """Score every start j: min over velocities of the mean of enhanced[z, j + round(v z)].

    `enhanced` is (length, database) for the query frames z = 0 .. length-1. Trajectories that
    leave the database are not scored. Memory is O(velocities x database).
    """
    length, database = enhanced.shape
    groups = distinct_velocities(velocities, length)
    per_velocity = np.full((len(groups), database), np.inf, np.float64)
    for g, (_, off) in enumerate(groups):
        starts = database - int(off[-1])
        if starts <= 0:
            continue
        acc = np.zeros(starts, np.float64)
        for z in range(length):
            acc += enhanced[z, off[z] : off[z] + starts]
        per_velocity[g, :starts] = acc / length
    best = np.argmin(per_velocity, axis=0) if database else np.zeros(0, np.int64)
    scores = per_velocity[best, np.arange(database)].astype(np.float32)
    return TrajectoryScores(scores, best.astype(np.int64), tuple(groups))


def next_best_starts(scores: FloatArray, best_start: int, count: int, separation: int) -> list[int]:
    """Up to `count` further starts, lowest S_do first, each more than `separation` frames from
    every start chosen before it (best_start included): the runner-up trajectories. O(count x
    database)."""
    remaining = scores.copy()
    starts: list[int] = []
    chosen = best_start
    for _ in range(count):
        remaining[max(chosen - separation, 0) : chosen + separation + 1] = np.inf
        if not np.isfinite(remaining).any():
            break
        chosen = int(np.argmin(remaining))
        starts.append(chosen)
    return starts


@dataclass(frozen=True)
class Normalized:
    """The best start j*, its score, the second-lowest score outside the window, and gamma."""

    best_start: int
    best_score: float
    second_score: float | None
    gamma: float


def normalize(scores: FloatArray, before: int, after: int) -> Normalized | None:
    """gamma = S[j*] / min S outside [j* - before, j* + after] (paper eq. 7).

    Returns None when no trajectory fits the database. gamma is 1.0 (no confidence) when
    nothing lies outside the window or the second-lowest score is 0.
    """
    finite = np.isfinite(scores)
    if not finite.any():
        return None
    best = int(np.argmin(scores))
    outside = finite.copy()
    outside[max(best - before, 0) : best + after + 1] = False
    best_score = float(scores[best])
    if not outside.any():
        return Normalized(best, best_score, None, 1.0)
    second = float(scores[outside].min())
    gamma = best_score / second if second > 0 else 1.0
    return Normalized(best, best_score, second, min(gamma, 1.0) if math.isfinite(gamma) else 1.0)
