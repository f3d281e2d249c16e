"""Visualization channels: what Foxglove and Lichtblick draw with their own panels.

For each reported loop closure, at the query image's log time:
- the matched frame's image message, its bytes unchanged, on `match_topic(camera topic)` (same
  schema as the camera topic): two Image panels show query and match side by side;
- a text on the query image (`/doseqslam/match/annotations`) naming the match, its time and
  the verification result, and with verification the inlier keypoints of the pair's accepted
  check on it; their matches on the match image on `/doseqslam/match/image_annotations`;
- with a pose topic, the line from the query's to the match's position, highlighted
  (`/doseqslam/match/marker`), and every reported loop closure's line so far
  (`/doseqslam/loop_lines`, one message replacing the previous; past EVERY_LOOP_LINES loop
  closures, only as they grow by LOOP_LINES_GROWTH, so that the bytes stay linear).
With a pose topic, `/doseqslam/markers` holds the whole trajectory, written once, at the log's
first message, and `/doseqslam/current_pose` the trajectory's pose at each camera frame (at its
log time, interpolated at the frame's time): Foxglove's 3-D panel draws no nav_msgs/Odometry,
so this arrow is where the robot is. A viewer seeking anywhere shows the latest message of
each topic: the trajectory, the loop lines up to then and the current loop closure, wherever
one scrubs (a scene built up message by message would show only its last line after a seek).

Between loop closures those topics would go on showing the last one, so the first camera frame
that is not a query, after each loop closure and at the log's start, has its own messages: a
grey "no loop" frame on the match topic (`no_loop_frame`, made once per run), an empty
ImageAnnotations on each annotations topic, and the current loop closure's line deleted. One
message there is enough for a viewer keeping the latest message, whether it plays or seeks; at
every such frame would add a message per camera frame for the same picture.

The match is older than the query, so the copy has already written both the camera channel
whose schema the match images reuse and the match's own message: the writer keeps the camera
messages at the plan's match times as they are copied, each until the last loop closure that
shows it is written. Memory stays bounded: the kept images have a byte budget
(KEPT_MATCHES_BYTES), and a match not kept (over the budget, not seen, or ambiguous) is read
again from the input, one ranged read, when its query's time comes.
"""

from __future__ import annotations

import contextlib
import functools
import math
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
from mcap.writer import Writer

from ..annotations.records import OUR_TOPIC_PREFIX, FrameTimes, LoopClosureRecord, TimedMessage
from ..errors import SourceError
from ..sources import Log, opened
from ..sources.base import Source
from ..sources.poses import (
    SLERP_LINEAR_BELOW_RAD,
    PoseTrack,
    default_pose_topic,
    read_poses,
)
from .no_loop_frame import no_loop_message
from .visual_encoders import (
    LINE_LIST,
    LINE_STRIP,
    Badge,
    Dots,
    Lines,
    SchemaInfo,
    Text,
    VisualEncoder,
)

MARKERS_TOPIC = OUR_TOPIC_PREFIX + "markers"
MATCH_MARKER_TOPIC = OUR_TOPIC_PREFIX + "match/marker"
LOOP_LINES_TOPIC = OUR_TOPIC_PREFIX + "loop_lines"
# The loop lines so far are written at every loop closure up to this many, then each time they
# have grown by this fraction (`loop_lines_due`).
EVERY_LOOP_LINES = 256
LOOP_LINES_GROWTH = 1 / 16
CURRENT_LOOP = ("doseqslam/match", 0)  # the current loop closure's line: namespace, number
ANNOTATIONS_TOPIC = OUR_TOPIC_PREFIX + "match/annotations"
CURRENT_POSE_TOPIC = OUR_TOPIC_PREFIX + "current_pose"
# The match image's annotations (its inlier keypoints), with verification only.
MATCH_ANNOTATIONS_TOPIC = OUR_TOPIC_PREFIX + "match/image_annotations"
DEFAULT_FRAME_ID = "map"  # for poses without a frame_id
TRAJECTORY_COLOR = (0.6, 0.6, 0.6, 1.0)
LOOP_COLOR = (0.1, 0.8, 0.2, 1.0)
CURRENT_LOOP_COLOR = (1.0, 0.3, 0.1, 1.0)
BADGE_PX = 20.0  # the square drawn on the query image (Foxglove 1.48 draws no texts)
TEXT_COLOR = (1.0, 1.0, 1.0, 1.0)
TEXT_BACKGROUND = (0.0, 0.0, 0.0, 0.6)
# The inlier keypoints: yellow, which neither the loop's green nor a 3-D path colour is.
INLIER_COLOR = (1.0, 1.0, 0.0, 1.0)
INLIER_RADIUS_PX = 1.5
# The match images kept from the copy at most (bytes); beyond it a match is read again.
KEPT_MATCHES_BYTES = 64 * 1024 * 1024
# Camera messages tried for the "no loop" frame (a damaged one is not understood) at most.
NO_LOOP_TRIES = 3


def match_topic(camera_topic: str) -> str:
    """Where the match images go: `.../compressed` for a compressed camera topic, as
    image_transport names it, so viewers see the same kind of image topic."""
    suffix = "/image/compressed" if camera_topic.endswith("/compressed") else "/image"
    return OUR_TOPIC_PREFIX + "match" + suffix


class PointPairs(Protocol):
    """A pair's inlier correspondences (`verification.InlierPoints`): row i of `query`, N x 2
    (x, y) in the query image's pixels, matches row i of `match` in the match image's; pixel
    centres at integers (OpenCV's keypoints)."""

    @property
    def query(self) -> npt.NDArray[np.float32]: ...

    @property
    def match(self) -> npt.NDArray[np.float32]: ...


@dataclass(frozen=True)
class VisualLoop:
    """One reported loop closure as drawn: the query, its (refined) match and a caption, and
    with verification the inlier points of its accepted check."""

    query_log_time_ns: int
    query_time_ns: int  # header stamp, else log time: what the images and poses are timed by
    match_log_time_ns: int
    match_time_ns: int
    caption: str
    points: PointPairs | None = field(default=None, compare=False)


@dataclass(frozen=True)
class Trajectory:
    """The pose topic drawn in the 3-D panel, in its messages' frame."""

    topic: str
    frame_id: str
    track: PoseTrack

    def position(self, time_ns: int) -> tuple[float, float, float]:
        """The position at `time_ns`, interpolated (the end poses outside the track)."""
        times, axes = self._interpolated
        x, y, z = (float(np.interp(time_ns, times, axis)) for axis in axes)
        return x, y, z

    @functools.cached_property
    def _interpolated(self) -> tuple[npt.NDArray[np.float64], list[npt.NDArray[np.float64]]]:
        """The times and each axis of the positions as np.interp reads them, made once: given
        int64 times and a strided column, it copies the whole track to contiguous float64 at
        every call, a cost per frame that would grow with the log."""
        times = np.ascontiguousarray(self.track.times_ns, dtype=np.float64)
        positions = self.track.positions
        return times, [np.ascontiguousarray(positions[:, k], np.float64) for k in range(3)]

    def orientation(self, time_ns: int) -> tuple[float, float, float, float]:
        """The orientation (x, y, z, w) at `time_ns`, by slerp (the end poses outside)."""
        times = self.track.times_ns
        upper = min(int(np.searchsorted(times, time_ns)), len(times) - 1)
        lower = max(upper - 1, 0)
        span = int(times[upper] - times[lower])
        fraction = min(max((time_ns - int(times[lower])) / span, 0.0), 1.0) if span else 1.0
        q0, q1 = self.track.quaternions_xyzw[lower].tolist(), self.track.quaternions_xyzw[upper]
        return _slerp(q0, q1.tolist(), fraction)


def _slerp(q0: list[float], q1: list[float], fraction: float) -> tuple[float, float, float, float]:
    """sources.poses.slerp for one pair, in floats: numpy's per-call cost on 4 numbers would
    be most of a frame's current pose."""
    cosine = sum(a * b for a, b in zip(q0, q1, strict=True))
    if cosine < 0:  # the shorter arc
        q1, cosine = [-b for b in q1], -cosine
    angle = math.acos(min(cosine, 1.0))
    if angle < SLERP_LINEAR_BELOW_RAD:
        w0, w1 = 1 - fraction, fraction
    else:
        w0 = math.sin((1 - fraction) * angle) / math.sin(angle)
        w1 = math.sin(fraction * angle) / math.sin(angle)
    q = [w0 * a + w1 * b for a, b in zip(q0, q1, strict=True)]
    norm = math.sqrt(sum(v * v for v in q))
    x, y, z, w = (v / norm for v in q)
    return x, y, z, w


@dataclass(frozen=True)
class FrameClock:
    """The camera frames by log time, and the time each was given (its header stamp, or its
    log time): what a frame's current pose is interpolated at."""

    log_times_ns: npt.NDArray[np.int64]  # ascending
    times_ns: npt.NDArray[np.int64]

    @classmethod
    def of(cls, frame_times: FrameTimes, time_source: str) -> FrameClock:
        order = np.argsort(frame_times.log_times_ns, kind="stable")
        times = frame_times.detector_times_ns(time_source)
        return cls(frame_times.log_times_ns[order], times[order])

    def time_at(self, log_time_ns: int) -> int | None:
        """The time of the frame logged at `log_time_ns`; None for a camera message that is
        no frame of the run (skipped, or outside the time range asked for)."""
        k = int(np.searchsorted(self.log_times_ns, log_time_ns))
        if k < len(self.log_times_ns) and int(self.log_times_ns[k]) == log_time_ns:
            return int(self.times_ns[k])
        return None


@dataclass(frozen=True)
class Visualization:
    """What the writer draws besides our messages (see the module's docstring)."""

    camera_topic: str
    loops: Sequence[VisualLoop]  # in query log-time order
    trajectory: Trajectory | None
    frames: FrameClock | None = None  # None: no current pose
    # The run verified its pairs: the match image gets annotations of its own (its points).
    verified: bool = False


def caption(record: LoopClosureRecord) -> str:
    """E.g. 'match: frame 88 at 1700000044.000 s, accepted (57 inliers, essential)'."""
    match = record.matched
    when = f"frame {match.index} at {match.time_ns / 1e9:.3f} s"
    if record.verification in ("off", ""):
        return f"match: {when}, not verified (--no-verify)"
    detail = f"{record.inliers} inliers, {record.verification_model}"
    return f"match: {when}, {record.verification} ({detail})"


def visual_loops(
    messages: Iterable[TimedMessage],
    points: Mapping[tuple[int, int], PointPairs] | None = None,
) -> list[VisualLoop]:
    """The reported loop closures among our messages, in query log-time order; `points`: the
    verified pairs' inlier points by (query, refined match) frame index."""
    # One at a time: the messages may be spooled (sinks.message_spool), read back as they go.
    records = (m.record for m in messages if isinstance(m.record, LoopClosureRecord))
    points = points or {}
    loops = [
        VisualLoop(
            r.query.log_time_ns,
            r.query.time_ns,
            r.matched.log_time_ns,
            r.matched.time_ns,
            caption(r),
            points.get((r.query.index, r.matched.index)),
        )
        for r in records
        if r.reported
    ]
    return sorted(loops, key=lambda loop: loop.query_log_time_ns)


def read_trajectory(
    log: Log, topic: str | None = None, track: PoseTrack | None = None
) -> Trajectory | None:
    """The pose topic (`topic`, else `default_pose_topic`) as a Trajectory: `track` when the
    run has read that topic already, else read here. None when the log has none, or its poses
    cannot be read (the 3-D lines are then left out, nothing else)."""
    try:
        with opened(log) as source:
            topic = topic or default_pose_topic(source)
            if topic is None:
                return None
            if track is None or track.topic != topic:
                track = read_poses(source, topic)
    except SourceError:
        return None
    return Trajectory(topic, track.frame_id or DEFAULT_FRAME_ID, track)


def loop_lines_due(lines: int, last_written: int, total: int) -> bool:
    """Whether the loop lines so far (`lines`, the last message held `last_written`, the run
    reports `total`) get a message: at every loop closure up to EVERY_LOOP_LINES, then each
    time they have grown by LOOP_LINES_GROWTH, and at the last one. Each message holds every
    line so far, so a message per loop closure would write loops² lines; this writes fewer than
    EVERY_LOOP_LINES² / 2 + (1 / LOOP_LINES_GROWTH + 2) * total lines in all. The current
    loop closure's own line is drawn at every one."""
    return (
        lines <= EVERY_LOOP_LINES
        or lines >= last_written * (1 + LOOP_LINES_GROWTH)
        or lines == total
    )


class VisualWriter:
    """Writes the visualization channels into the output, interleaved by log time."""

    def __init__(
        self, writer: Writer, encoder: VisualEncoder, log: Log, plan: Visualization
    ) -> None:
        self.writer, self.encoder, self.plan = writer, encoder, plan
        self.log = log  # the run's open input, or its path (opened at the first match image)
        self._opened = contextlib.ExitStack()
        self.position = 0  # next loop to draw
        self.trajectory_written = plan.trajectory is None
        self.camera: tuple[int, str, dict[str, str]] | None = None  # schema, encoding, metadata
        self.channel_ids: dict[str, int] = {}
        self.written: dict[str, int] = {}
        self._source: Source | None = None
        self._kept = _KeptMatches(plan.loops, KEPT_MATCHES_BYTES)
        self._loop_ends: list[tuple[float, float, float]] = []  # the loop lines so far
        self._loop_lines_drawn = 0  # lines in the last loop lines message
        self._no_loop_due = True  # the next camera frame that is no query says "no loop"
        self._no_loop_annotations = encoder.annotations(0, [], [])
        self._no_loop_image: bytes | None = None
        self._no_loop_tries = 0
        self._last_pose_log_time: int | None = None

    def input_channel(
        self, topic: str, encoding: str, schema_id: int, metadata: dict[str, str]
    ) -> None:
        """Called for each input channel copied: the camera's schema is the match images'."""
        if topic == self.plan.camera_topic and self.camera is None:
            self.camera = (schema_id, encoding, dict(metadata))

    def input_message(self, topic: str, log_time_ns: int, data: bytes) -> None:
        """Called after each input message copied: a camera message at a match time is kept."""
        if topic != self.plan.camera_topic:
            return
        self._kept.offer(log_time_ns, data)
        self._write_current_pose(log_time_ns)
        if self._no_loop_due and not self._is_query(log_time_ns):
            self._no_loop_due = False
            self._write_no_loop(log_time_ns, data)

    def write_until(self, log_time_ns: int | None) -> None:
        """Writes what is due at log times <= log_time_ns (everything for None)."""
        if not self.trajectory_written:
            first = self.plan.loops[0].query_log_time_ns if self.plan.loops else 0
            self._write_trajectory(first if log_time_ns is None else log_time_ns)
        loops = self.plan.loops
        while self.position < len(loops):
            loop = loops[self.position]
            if log_time_ns is not None and loop.query_log_time_ns > log_time_ns:
                return
            self._write_loop(loop)
            self.position += 1

    def finish(self) -> dict[str, int]:
        """Writes the rest; returns the messages written per topic."""
        self.write_until(None)
        self._opened.close()
        return dict(sorted(self.written.items()))

    def _write_trajectory(self, log_time_ns: int) -> None:
        self.trajectory_written = True
        trajectory = self.plan.trajectory
        assert trajectory is not None
        points = [(float(x), float(y), float(z)) for x, y, z in trajectory.track.positions]
        path = Lines("doseqslam/trajectory", 0, LINE_STRIP, points, TRAJECTORY_COLOR, 0.1)
        data = self.encoder.scene(trajectory.frame_id, log_time_ns, [path])
        self._add(MARKERS_TOPIC, self.encoder.scene_schema, log_time_ns, data)

    @staticmethod
    def _ends(trajectory: Trajectory, loop: VisualLoop) -> list[tuple[float, float, float]]:
        return [trajectory.position(loop.query_time_ns), trajectory.position(loop.match_time_ns)]

    def _write_loop(self, loop: VisualLoop) -> None:
        time = loop.query_log_time_ns
        self._write_match_image(loop)
        text = Text(BADGE_PX + 8, 4.0, loop.caption, 12.0, TEXT_COLOR, TEXT_BACKGROUND)
        badge = Badge(4.0, 4.0, BADGE_PX, LOOP_COLOR)
        query_dots, match_dots = _inlier_dots(loop.points)
        schema = self.encoder.annotations_schema
        annotations = self.encoder.annotations(loop.query_time_ns, [text], [badge], query_dots)
        self._add(ANNOTATIONS_TOPIC, schema, time, annotations)
        if self.plan.verified:
            match_side = self.encoder.annotations(loop.match_time_ns, [], [], match_dots)
            self._add(MATCH_ANNOTATIONS_TOPIC, schema, time, match_side)
        self._no_loop_due = True
        trajectory = self.plan.trajectory
        if trajectory is None:
            return
        ends = self._ends(trajectory, loop)
        lines = Lines(*CURRENT_LOOP, LINE_LIST, ends, CURRENT_LOOP_COLOR, 0.6)
        data = self.encoder.scene(trajectory.frame_id, time, [lines])
        self._add(MATCH_MARKER_TOPIC, self.encoder.scene_schema, time, data)
        # The lines so far in one message: a seek shows them all.
        self._loop_ends.extend(ends)
        drawn = len(self._loop_ends) // 2
        if not loop_lines_due(drawn, self._loop_lines_drawn, len(self.plan.loops)):
            return
        self._loop_lines_drawn = drawn
        so_far = Lines("doseqslam/loop_closures", 0, LINE_LIST, self._loop_ends, LOOP_COLOR, 0.08)
        data = self.encoder.scene(trajectory.frame_id, time, [so_far])
        self._add(LOOP_LINES_TOPIC, self.encoder.scene_schema, time, data)

    def _write_current_pose(self, log_time_ns: int) -> None:
        """The trajectory's pose at the camera frame logged at this time, once per log time."""
        trajectory, frames = self.plan.trajectory, self.plan.frames
        if trajectory is None or frames is None or log_time_ns == self._last_pose_log_time:
            return
        time_ns = frames.time_at(log_time_ns)
        if time_ns is None:
            return
        self._last_pose_log_time = log_time_ns
        position, orientation = trajectory.position(time_ns), trajectory.orientation(time_ns)
        data = self.encoder.pose(trajectory.frame_id, time_ns, position, orientation)
        self._add(CURRENT_POSE_TOPIC, self.encoder.pose_schema, log_time_ns, data)

    def _is_query(self, log_time_ns: int) -> bool:
        """Whether the camera frame at this log time is the query of the last loop written."""
        last = self.plan.loops[self.position - 1] if self.position else None
        return last is not None and last.query_log_time_ns == log_time_ns

    def _write_no_loop(self, log_time_ns: int, sample: bytes) -> None:
        """No current loop closure from this frame on (see the module's docstring)."""
        schema = self.encoder.annotations_schema
        self._add(ANNOTATIONS_TOPIC, schema, log_time_ns, self._no_loop_annotations)
        if self.plan.verified:
            self._add(MATCH_ANNOTATIONS_TOPIC, schema, log_time_ns, self._no_loop_annotations)
        trajectory = self.plan.trajectory
        if trajectory is not None:
            data = self.encoder.deletion(trajectory.frame_id, log_time_ns, *CURRENT_LOOP)
            self._add(MATCH_MARKER_TOPIC, self.encoder.scene_schema, log_time_ns, data)
        if self._no_loop_image is None and self._no_loop_tries < NO_LOOP_TRIES:
            self._no_loop_tries += 1
            self._no_loop_image = self._build_no_loop_image(log_time_ns, sample)
        if self._no_loop_image is not None:
            self._add_message(self._match_channel(), log_time_ns, self._no_loop_image)

    def _build_no_loop_image(self, log_time_ns: int, sample: bytes) -> bytes | None:
        """The "no loop" frame made from the camera message `sample` at this log time."""
        if self.camera is None:
            return None
        images = self._input().image_messages(self.plan.camera_topic, log_time_ns, log_time_ns + 1)
        image = next(iter(images), None)
        return None if image is None else no_loop_message(sample, image, self.camera[1])

    def _write_match_image(self, loop: VisualLoop) -> None:
        kept = self._kept.take(loop.match_log_time_ns)
        if self.camera is None:
            return  # the camera channel was not copied (a sidecar): no schema to reuse
        data = self._read_match(loop) if kept is None else kept
        self._add_message(self._match_channel(), loop.query_log_time_ns, data)

    def _match_channel(self) -> str:
        """The match images' topic, its channel registered with the camera's schema."""
        topic = match_topic(self.plan.camera_topic)
        if topic not in self.channel_ids:
            assert self.camera is not None
            schema_id, encoding, metadata = self.camera
            self.channel_ids[topic] = self.writer.register_channel(
                topic, encoding, schema_id, metadata
            )
        return topic

    def _input(self) -> Source:
        """The input, opened at the first read."""
        if self._source is None:
            self._source = self._opened.enter_context(opened(self.log))
        return self._source

    def _read_match(self, loop: VisualLoop) -> bytes:
        """The match frame's message: the first of the camera topic at its log time."""
        source = self._input()
        start = loop.match_log_time_ns
        for _, data in source.raw_messages(self.plan.camera_topic, start, start + 1):
            return data
        raise SourceError(
            f"{source.path}: the image of {self.plan.camera_topic} at log time {start} "
            "is not found again (the log changed under us)"
        )

    def _add(self, topic: str, schema: Any, log_time_ns: int, data: bytes) -> None:
        if topic not in self.channel_ids:
            self.channel_ids[topic] = self._register(topic, schema())
        self._add_message(topic, log_time_ns, data)

    def _register(self, topic: str, schema: SchemaInfo) -> int:
        schema_id = self.writer.register_schema(schema.name, schema.encoding, schema.data)
        encoding = self.encoder.message_encoding
        return self.writer.register_channel(topic, encoding, schema_id, schema.channel_metadata)

    def _add_message(self, topic: str, log_time_ns: int, data: bytes) -> None:
        sequence = self.written.get(topic, 0)
        channel_id = self.channel_ids[topic]
        self.writer.add_message(channel_id, log_time_ns, data, log_time_ns, sequence & 0xFFFFFFFF)
        self.written[topic] = sequence + 1


def _inlier_dots(points: PointPairs | None) -> tuple[list[Dots], list[Dots]]:
    """The query's and the match's inlier points as drawn (none without them)."""
    if points is None:
        return [], []
    return [_dots(points.query)], [_dots(points.match)]


def _dots(pixels: npt.NDArray[np.float32]) -> Dots:
    # Keypoints have pixel centres at integers; an annotation's origin is the top left pixel's
    # corner: half a pixel on. Hundredths of a pixel are more than a viewer can show.
    # tolist: Python floats at once (float32 to float64 is exact), not a NumPy scalar each.
    drawn = [(round(x + 0.5, 2), round(y + 0.5, 2)) for x, y in np.asarray(pixels).tolist()]
    return Dots(drawn, INLIER_COLOR, INLIER_RADIUS_PX)


class _KeptMatches:
    """The camera messages at the loops' match times, kept from the copy until the last loop
    closure that shows each is written, within a byte budget."""

    def __init__(self, loops: Sequence[VisualLoop], budget_bytes: int) -> None:
        self.budget_bytes = budget_bytes
        self.uses = Counter(loop.match_log_time_ns for loop in loops)  # loops still to write
        self.images: dict[int, bytes] = {}
        self.seen: set[int] = set()  # match times whose first camera message has gone by
        self.kept_bytes = 0

    def offer(self, log_time_ns: int, data: bytes) -> None:
        """A copied camera message: kept when it is the first at a match time still needed."""
        if self.uses[log_time_ns] <= 0:
            return
        if log_time_ns in self.seen:
            # Two images at one log time: the ranged read settles which one is the match.
            self._drop(log_time_ns)
            return
        self.seen.add(log_time_ns)
        if self.kept_bytes + len(data) <= self.budget_bytes:
            self.images[log_time_ns] = data
            self.kept_bytes += len(data)

    def take(self, log_time_ns: int) -> bytes | None:
        """The kept image of one loop closure's match (None: read it again), dropped once no
        loop closure still to write shows it."""
        data = self.images.get(log_time_ns)
        self.uses[log_time_ns] -= 1
        if self.uses[log_time_ns] <= 0:
            del self.uses[log_time_ns]
            self.seen.discard(log_time_ns)
            self._drop(log_time_ns)
        return data

    def _drop(self, log_time_ns: int) -> None:
        data = self.images.pop(log_time_ns, None)
        if data is not None:
            self.kept_bytes -= len(data)
