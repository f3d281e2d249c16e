"""Ground truth from poses: which frames revisit the place (and heading) of an earlier one.

Frame i and an earlier frame j form a loop cell GT[i, j] when, with the poses interpolated at
the frames' times,
* their positions are within `radius_m` (3-D Euclidean distance),
* with `max_heading_deg`, their yaws differ by at most that many degrees,
* frame j is at least `min_age_s` older (the run's kappa, so that the ground truth asks only
  what the detector could find), and
* with `min_travel_m`, the camera moved at least that far between them (the summed distance
  between consecutive frames), so that a parked camera does not revisit itself.

Cells come from a KD-tree (scipy cKDTree.query_ball_point), queried in batches whose neighbour
count is bounded. `PoseGroundTruth` keeps none of them (memory grows with the frames only: a
route driven lap after lap for 8 hours has 240 million cells); `loop_cells` lists them all.
Frames outside the pose track's time span have no pose and so no loop.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from ..errors import UsageError
from ..sources.poses import PoseTrack
from .groundtruth import GroundTruth, checked_pairs

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


class _Frames:
    """The frames' times, positions, headings and distance driven, and the loop condition
    between two of them: one definition for the cells listed and the pairs looked up."""

    def __init__(
        self,
        times_ns: npt.ArrayLike,
        positions: npt.ArrayLike,
        criteria: LoopCriteria,
        yaw: npt.ArrayLike | None,
    ) -> None:
        """Raises UsageError when `yaw` is missing while the criteria limit the heading."""
        if criteria.max_heading_deg is not None and yaw is None:
            raise UsageError("a heading limit needs the poses' orientations")
        self.criteria = criteria
        self.times: IntArray = np.asarray(times_ns, dtype=np.int64).ravel()
        n = self.times.size
        xyz = np.asarray(positions, dtype=np.float64)
        self.xyz: FloatArray = xyz.reshape(n, -1) if n else np.zeros((0, 3))
        self.yaw = None if yaw is None else np.asarray(yaw, dtype=np.float64).ravel()
        self.valid: IntArray = np.flatnonzero(np.all(np.isfinite(self.xyz), axis=1))
        # Driven distance, summed over the frames with a pose (a frame without one is skipped).
        self.travelled: FloatArray = np.zeros(n)
        if self.valid.size:
            steps = np.linalg.norm(np.diff(self.xyz[self.valid], axis=0), axis=1)
            self.travelled[self.valid] = np.concatenate([[0.0], np.cumsum(steps)])
        self.has_pose: BoolArray = np.zeros(n, dtype=bool)
        self.has_pose[self.valid] = True

    def loops(self, i: IntArray, j: IntArray) -> BoolArray:
        """Whether each (later i, earlier j) is a loop (module docstring); frames without a
        pose make none."""
        keep: BoolArray = self.has_pose[i] & self.has_pose[j] & (j < i)
        distance = np.sqrt(np.sum((self.xyz[i] - self.xyz[j]) ** 2, axis=1))
        keep &= distance <= self.criteria.radius_m
        keep &= self.times[i] - self.times[j] >= round(self.criteria.min_age_s * 1e9)
        if self.criteria.max_heading_deg is not None and self.yaw is not None:
            turn = _wrapped(self.yaw[i] - self.yaw[j])
            keep &= turn <= math.radians(self.criteria.max_heading_deg)
        if self.criteria.min_travel_m is not None:
            keep &= self.travelled[i] - self.travelled[j] >= self.criteria.min_travel_m
        return keep

    def cell_batches(self, batch_neighbours: int) -> Iterator[tuple[IntArray, IntArray]]:
        """(rows, cols) of the loop cells, batch by batch of consecutive query frames (rows
        ascending; sorted by row then column within a batch); a batch's KD-tree neighbours
        are at most `batch_neighbours` (or a single frame's)."""
        if self.valid.size < 2:
            return
        points = self.xyz[self.valid]
        tree = cKDTree(points)
        # A hair wider than the radius: the exact distance test is `loops`'.
        reach = self.criteria.radius_m * (1 + 1e-9)
        counts = np.asarray(tree.query_ball_point(points, reach, return_length=True))
        for start, stop in _batches(counts.astype(np.int64), batch_neighbours):
            neighbours = tree.query_ball_point(points[start:stop], reach)
            sizes = np.fromiter((len(n) for n in neighbours), np.int64, stop - start)
            i = self.valid[np.repeat(np.arange(start, stop), sizes)]
            flat = np.fromiter(
                itertools.chain.from_iterable(neighbours), np.int64, int(sizes.sum())
            )
            j = self.valid[flat]
            keep = self.loops(i, j)
            i, j = i[keep], j[keep]
            order = np.lexsort((j, i))
            yield i[order], j[order]


def loop_cells(
    times_ns: npt.ArrayLike,
    positions: npt.ArrayLike,
    criteria: LoopCriteria,
    yaw: npt.ArrayLike | None = None,
    batch_neighbours: int = BATCH_NEIGHBOURS,
) -> tuple[IntArray, IntArray]:
    """(rows, cols) of all the loop cells, rows = later frame, sorted by row then column:
    memory grows with the cells (`PoseGroundTruth` holds none).

    Frames whose position is NaN take no part. Times must not decrease with the index.

    Raises:
        UsageError: `yaw` is missing while the criteria limit the heading.
    """
    frames = _Frames(times_ns, positions, criteria, yaw)
    rows: list[IntArray] = [np.zeros(0, np.int64)]
    cols: list[IntArray] = [np.zeros(0, np.int64)]
    for i, j in frames.cell_batches(batch_neighbours):
        rows.append(i)
        cols.append(j)
    return np.concatenate(rows), np.concatenate(cols)


class PoseGroundTruth:
    """The ground truth of poses (`LoopTruth`), answered from the frames' poses: memory grows
    with the frames, never with the loop cells (a route driven lap after lap for hours has
    hundreds of millions). The loop cells are walked once, in bounded batches, to find the
    frames that revisit a place and to count them; a pair is looked up by the condition
    itself; `cell_batches` walks them again (the plots).
    """

    def __init__(
        self,
        poses: FramePoses,
        criteria: LoopCriteria,
        source: str = "<poses>",
        batch_neighbours: int = BATCH_NEIGHBOURS,
    ) -> None:
        self.source = source
        self.transposed = False
        self._frames = _Frames(poses.times_ns, poses.positions, criteria, poses.yaw)
        self._batch = batch_neighbours
        self._revisits = np.zeros(self.n_frames, dtype=bool)
        self._nnz = 0
        for rows, _ in self.cell_batches():
            self._revisits[rows] = True
            self._nnz += int(rows.size)

    @property
    def n_frames(self) -> int:
        return int(self._frames.times.size)

    @property
    def nnz(self) -> int:
        return self._nnz

    @property
    def n_loop_events(self) -> int:
        return int(np.count_nonzero(self._revisits))

    def query_rows(self) -> IntArray:
        rows: IntArray = np.flatnonzero(self._revisits).astype(np.int64)
        return rows

    def cell_batches(self) -> Iterator[tuple[IntArray, IntArray]]:
        return self._frames.cell_batches(self._batch)

    def is_true(self, query: int, match: int, tolerance: int = 0) -> bool:
        return bool(self.are_true([query], [match], tolerance)[0])

    def are_true(
        self, queries: npt.ArrayLike, matches: npt.ArrayLike, tolerance: int = 0
    ) -> BoolArray:
        """`GroundTruth.are_true`, each pair tested by the condition: O(pairs x tolerance).

        Raises:
            GroundTruthError: an index lies outside the frames, or the arrays differ in shape.
            UsageError: tolerance is negative.
        """
        n = self.n_frames
        q, m = checked_pairs(self.source, n, queries, matches, tolerance)
        result: BoolArray = np.zeros(q.size, dtype=bool)
        for offset in range(-tolerance, tolerance + 1):
            near = m + offset
            inside = (near >= 0) & (near < n)
            result[inside] |= self._frames.loops(q[inside], near[inside])
        return result

    def materialized(self) -> GroundTruth:
        """The same truth as a `GroundTruth` holding every cell (memory grows with them)."""
        rows, cols = zip(*self.cell_batches(), strict=True) if self._nnz else ((), ())
        empty = np.zeros(0, np.int64)
        return GroundTruth(
            self.n_frames,
            np.concatenate([empty, *rows]),
            np.concatenate([empty, *cols]),
            source=self.source,
        )

    def __repr__(self) -> str:
        return (
            f"PoseGroundTruth(source={self.source!r}, n_frames={self.n_frames}, "
            f"nnz={self.nnz}, loop_events={self.n_loop_events})"
        )


def pose_ground_truth(
    poses: FramePoses, criteria: LoopCriteria, source: str = "<poses>"
) -> PoseGroundTruth:
    """The ground truth of the frames whose poses are given (`PoseGroundTruth`).

    Raises:
        UsageError: the poses have no orientation while the criteria limit the heading.
    """
    return PoseGroundTruth(poses, criteria, source)
