"""Ground truth from poses: which frames revisit the place (and heading) of an earlier one.

Frame i and an earlier frame j form a loop cell GT[i, j] when, with the poses interpolated at
the frames' times,
* their positions are within `radius_m` (3-D Euclidean distance),
* with `max_heading_deg`, their yaws differ by at most that many degrees,
* frame j is at least `min_age_s` older (the run's kappa, so that the ground truth asks only
  what the detector could find), and
* with `min_travel_m`, the camera moved at least that far between them (the summed distance
  between consecutive frames), so that a parked camera does not revisit itself.

Pairs come from a KD-tree (scipy cKDTree.query_ball_point), queried in batches whose neighbour
count is bounded, so memory grows with the frames and the loop cells, never with N x N.
Frames outside the pose track's time span have no pose and so no loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from ..errors import UsageError
from ..sources.poses import PoseTrack
from .groundtruth import GroundTruth

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

# Neighbours gathered per KD-tree batch: bounds the temporary lists (a parked camera has every
# parked frame as a neighbour of every other).
BATCH_NEIGHBOURS = 1 << 21


@dataclass(frozen=True)
class LoopCriteria:
    """When two frames' poses make a loop (module docstring)."""

    radius_m: float
    min_age_s: float
    max_heading_deg: float | None = None
    min_travel_m: float | None = None

    def __post_init__(self) -> None:
        if not self.radius_m > 0 or math.isinf(self.radius_m):
            raise UsageError(f"--radius must be a positive number of metres, got {self.radius_m}")
        if self.max_heading_deg is not None and not 0 <= self.max_heading_deg <= 180:
            raise UsageError(f"--max-heading must be 0..180 degrees, got {self.max_heading_deg}")
        if self.min_travel_m is not None and not self.min_travel_m >= 0:
            raise UsageError(f"--min-travel must be >= 0 metres, got {self.min_travel_m}")
        if not self.min_age_s >= 0:
            raise UsageError(f"kappa_s must be >= 0 seconds, got {self.min_age_s}")

    def describe(self) -> str:
        parts = [f"within {self.radius_m:g} m"]
        if self.max_heading_deg is not None:
            parts.append(f"{self.max_heading_deg:g} deg")
        parts.append(f">= {self.min_age_s:g} s apart")
        if self.min_travel_m is not None:
            parts.append(f">= {self.min_travel_m:g} m driven")
        return ", ".join(parts)


@dataclass(frozen=True)
class FramePoses:
    """The pose of every frame of a run (rows of frames without a pose are NaN)."""

    times_ns: IntArray  # the time each frame's pose was taken at
    positions: FloatArray  # N x 3
    yaw: FloatArray  # N, radians
    has_pose: BoolArray  # N: inside the pose track's time span


def yaw_from_quaternions(quaternions_xyzw: npt.ArrayLike) -> FloatArray:
    """Heading about z (radians, -pi..pi) of each x, y, z, w quaternion (any norm)."""
    q = np.asarray(quaternions_xyzw, dtype=np.float64).reshape(-1, 4)
    x, y, z, w = q.T
    yaw: FloatArray = np.arctan2(2 * (w * z + x * y), w * w + x * x - y * y - z * z)
    return yaw


def frame_poses(track: PoseTrack, times_ns: IntArray) -> FramePoses:
    """`track` interpolated at `times_ns` (any order); times outside its span get no pose."""
    times = np.asarray(times_ns, dtype=np.int64)
    n = times.shape[0]
    positions = np.full((n, 3), np.nan)
    yaw = np.full(n, np.nan)
    has_pose = np.zeros(n, dtype=bool)
    if track.times_ns.size:
        has_pose = (times >= track.times_ns[0]) & (times <= track.times_ns[-1])
    if has_pose.any():
        # Sorted: interpolation wants non-decreasing times (a bridged clock jump can break it).
        index = np.flatnonzero(has_pose)
        index = index[np.argsort(times[index], kind="stable")]
        inside = track.interpolate(times[index])
        positions[index] = inside.positions
        yaw[index] = yaw_from_quaternions(inside.quaternions_xyzw)
    return FramePoses(times, positions, yaw, has_pose)


def _wrapped(angle: FloatArray) -> FloatArray:
    wrapped: FloatArray = np.abs((angle + np.pi) % (2 * np.pi) - np.pi)
    return wrapped


def _batches(counts: IntArray, limit: int) -> list[tuple[int, int]]:
    """[start, stop) ranges of consecutive queries with at most `limit` neighbours each
    (a single query with more forms its own batch)."""
    ranges = []
    start, total = 0, 0
    for index, count in enumerate(counts.tolist()):
        if total and total + count > limit:
            ranges.append((start, index))
            start, total = index, 0
        total += count
    if start < counts.size:
        ranges.append((start, int(counts.size)))
    return ranges


def loop_cells(
    times_ns: npt.ArrayLike,
    positions: npt.ArrayLike,
    criteria: LoopCriteria,
    yaw: npt.ArrayLike | None = None,
    batch_neighbours: int = BATCH_NEIGHBOURS,
) -> tuple[IntArray, IntArray]:
    """(rows, cols) of the loop cells, rows = later frame, sorted by row then column.

    Frames whose position is NaN take no part. Times must not decrease with the index.

    Raises:
        UsageError: `yaw` is missing while the criteria limit the heading.
    """
    times = np.asarray(times_ns, dtype=np.int64)
    if criteria.max_heading_deg is not None and yaw is None:
        raise UsageError("a heading limit needs the poses' orientations")
    if times.size < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    xyz = np.asarray(positions, dtype=np.float64).reshape(times.size, -1)
    valid = np.flatnonzero(np.all(np.isfinite(xyz), axis=1))
    if valid.size < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    points = xyz[valid]
    tree = cKDTree(points)
    counts = np.asarray(tree.query_ball_point(points, criteria.radius_m, return_length=True))
    travelled = np.zeros(times.size)
    travelled[valid] = np.concatenate(
        [[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
    )
    rows: list[IntArray] = [np.zeros(0, np.int64)]
    cols: list[IntArray] = [np.zeros(0, np.int64)]
    for start, stop in _batches(counts.astype(np.int64), batch_neighbours):
        neighbours = tree.query_ball_point(points[start:stop], criteria.radius_m)
        sizes = np.fromiter((len(n) for n in neighbours), np.int64, stop - start)
        i = valid[np.repeat(np.arange(start, stop), sizes)]
        flat = [k for n in neighbours for k in n]
        j = valid[np.asarray(flat, dtype=np.int64)]
        keep = _keep(i, j, times, travelled, criteria, yaw)
        rows.append(i[keep])
        cols.append(j[keep])
    i_all, j_all = np.concatenate(rows), np.concatenate(cols)
    order = np.lexsort((j_all, i_all))
    return i_all[order], j_all[order]


def _keep(
    i: IntArray,
    j: IntArray,
    times: IntArray,
    travelled: FloatArray,
    criteria: LoopCriteria,
    yaw: npt.ArrayLike | None,
) -> BoolArray:
    """Which neighbour pairs (i later than j) pass the age, heading and travel conditions."""
    keep: BoolArray = (j < i) & (times[i] - times[j] >= round(criteria.min_age_s * 1e9))
    if criteria.max_heading_deg is not None and yaw is not None:
        yaws = np.asarray(yaw, dtype=np.float64)
        keep &= _wrapped(yaws[i] - yaws[j]) <= math.radians(criteria.max_heading_deg)
    if criteria.min_travel_m is not None:
        keep &= travelled[i] - travelled[j] >= criteria.min_travel_m
    return keep


def pose_ground_truth(
    poses: FramePoses, criteria: LoopCriteria, source: str = "<poses>"
) -> GroundTruth:
    """The sparse N x N ground truth of the frames whose poses are given."""
    rows, cols = loop_cells(poses.times_ns, poses.positions, criteria, poses.yaw)
    return GroundTruth(poses.times_ns.size, rows, cols, source=source)
