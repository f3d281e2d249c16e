"""The motion rule: a loop closure means the camera left the place and came back.

A camera that stands still (a parked robot, a train at a station) sees the same scene for
minutes; once kappa seconds have passed, the detector takes its frames as a revisit and the
geometric check passes them with hundreds of inliers. Nothing in the images of the pair
tells that apart from a true revisit: what does is the camera's path between the two frames.

Two kinds of evidence, the first that covers the pair decides:

* **A pose topic** (odometry): the camera left if, at some frame between the match and the
  query, it was at least `leave_distance_m` from where it was at the match (`CameraPath`).
  Leaving the place's neighbourhood, not distance driven: a parked robot's odometry that
  jitters in place adds up distance but never leaves.
* **The images** (no pose topic, or poses that do not cover the pair): `leave_samples` frames
  evenly spaced strictly between the match and the query are checked with the same check as
  the pair, against the query and, where that is hopeless, against the match; the camera left
  if at least a third of them are hopeless against both (under half of `min_inliers`: they see
  neither end's place). A still camera's frames between keep seeing it, though on small,
  noisy frames not always both ends of it; one that drove away sees other places for most of
  the time between.

A pair that passes the check but not the rule is rejected with the reason STATIONARY.

With a pose topic that gives headings, the pair must also agree with it (`CameraPath.turn`,
VINS-Mono's check of a loop's yaw drift): a look-alike facade seen facing another way passes
the essential fit with a small rotation where the odometry turned 90 degrees. The odometry's
own heading drifts with the path driven, so the turn it may exceed the fit's rotation by
grows with the path between the two frames. A pair beyond it is rejected with the reason
ODOMETRY_DISAGREES.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

STATIONARY = "stationary"
ODOMETRY_DISAGREES = "odometry disagrees"
# Frames of the path scanned at a time from the match on: a camera that left is usually found
# gone within the first block, so a check costs a block, not the whole span (hours at 10 Hz).
_SCAN_BLOCK = 256


@dataclass(frozen=True)
class CameraPath:
    """The camera's positions at the frames (metres, by frame index) from a pose topic;
    `valid[i]` False where the topic does not cover frame i's time."""

    topic: str
    positions: npt.NDArray[np.float64]  # (N, 3)
    valid: npt.NDArray[np.bool_]  # (N,)
    # The camera's orientation at each frame, unit quaternions (N, 4), or None: no headings.
    orientations: npt.NDArray[np.float64] | None = None
    # frames without a pose before frame i, so that a span's coverage costs O(1)
    _invalid_before: npt.NDArray[np.int64] = field(init=False, repr=False, compare=False)
    # metres driven from frame 0 to frame i (steps into or out of a frame without a pose: 0)
    _driven: npt.NDArray[np.float64] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        counts = np.concatenate([[0], np.cumsum(~self.valid, dtype=np.int64)])
        object.__setattr__(self, "_invalid_before", counts)
        steps = np.linalg.norm(np.diff(self.positions, axis=0), axis=1)
        steps[~(self.valid[1:] & self.valid[:-1])] = 0.0
        object.__setattr__(self, "_driven", np.concatenate([[0.0], np.cumsum(steps)]))

    def covers(self, first: int, last: int) -> bool:
        """Every frame from `first` to `last` (inclusive) has a pose."""
        if first < 0 or last >= len(self.valid) or first > last:
            return False
        return bool(self._invalid_before[last + 1] == self._invalid_before[first])

    def left(self, match: int, query: int, distance_m: float) -> bool | None:
        """Whether the camera was at least `distance_m` from its position at `match` at some
        frame up to `query`; None when the poses do not cover the frames between."""
        first, last = min(match, query), max(match, query)
        if not self.covers(first, last):
            return None
        origin = self.positions[first]
        for start in range(first + 1, last + 1, _SCAN_BLOCK):
            block = self.positions[start : min(start + _SCAN_BLOCK, last + 1)]
            if float(np.max(np.sum((block - origin) ** 2, axis=1))) >= distance_m**2:
                return True
        return False

    def turn(self, match: int, query: int) -> tuple[float, float] | None:
        """(degrees the camera turned from `match` to `query`, metres driven between them) by
        the poses; None without headings or when the poses do not cover the frames between."""
        first, last = min(match, query), max(match, query)
        if self.orientations is None or not self.covers(first, last):
            return None
        a, b = self.orientations[match], self.orientations[query]
        b = b if float(np.dot(a, b)) >= 0 else -b  # q and -q: one rotation
        # The quaternions are half the rotation's angle apart, and atan2(|a - b|, |a + b|) is
        # half that angle: well conditioned near 0, where the arc cosine of a . b is not.
        half = math.atan2(float(np.linalg.norm(a - b)), float(np.linalg.norm(a + b)))
        return math.degrees(4.0 * half), float(self._driven[last] - self._driven[first])


def agrees_with_odometry(
    fit_rotation_deg: float, turn: tuple[float, float], drift_deg: float, drift_deg_per_m: float
) -> bool:
    """Whether the essential fit's rotation and the odometry's `turn` (degrees, metres driven)
    agree: the odometry turned at most drift_deg + drift_deg_per_m x metres more (the fit's
    angle is a lower bound of the drift it leaves: the two rotations' axes are not compared)."""
    turned, driven = turn
    return turned - fit_rotation_deg <= drift_deg + drift_deg_per_m * driven


def frames_between(match: int, query: int, samples: int) -> list[int]:
    """Up to `samples` frame indices evenly spaced strictly between `match` and `query`
    (all of them when there are fewer), in increasing order."""
    first, last = min(match, query), max(match, query)
    inside = last - first - 1
    if inside <= 0 or samples <= 0:
        return []
    if inside <= samples:
        return list(range(first + 1, last))
    # The k-th of `samples` interior points of the span, in integers (the same on every machine).
    return [first + ((k + 1) * (last - first)) // (samples + 1) for k in range(samples)]


def left_by_images(away: list[bool]) -> bool:
    """The image evidence's verdict from the frames between (True: the frame sees neither the
    query's place nor the match's): at least a third of them, and one at the least. Not one:
    on small noisy frames a standing camera's frame now and then fails both checks; not half:
    a long stop at the place before leaving fills most of the span with frames that see it."""
    return bool(away) and 3 * sum(away) >= len(away)
