"""Pose tracks from a log: odometry or ground truth, and interpolation at other times.

`read_poses(path, topic)` reads one pose topic of an MCAP file (any profile: ROS 2, ROS 1,
Foxglove protobuf or JSON) or a ROS 1 / rosbag2 bag. Supported message types:
nav_msgs/Odometry, geometry_msgs/PoseStamped, geometry_msgs/PoseWithCovarianceStamped (ROS 1
and ROS 2 spellings) and foxglove.PoseInFrame (what the Foxglove sample logs carry).

Each pose is timed by its header stamp (Foxglove: its `timestamp`); a stamp of 0 (unset) falls
back to the message's log time, as the detector's clock does. Poses are sorted by that time and
a pose whose time repeats an earlier one is dropped (keeping the first), so times are strictly
ascending and interpolation is well defined.

A message that cannot be a pose (undecodable, a position or orientation not finite, a zero
quaternion, a covariance that is not 6 x 6) is skipped and counted by reason in
`PoseTrack.skipped`, like an unusable image: one bad sample never costs the topic.
"""

from __future__ import annotations

import math
from array import array
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ..errors import SourceError
from . import Log, opened
from .base import DecodedMessage, SideTopicReader, Source

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

# Canonical names (ROS 1 spelling); ROS 2 inserts "/msg/".
ODOMETRY = "nav_msgs/Odometry"
POSE_STAMPED = "geometry_msgs/PoseStamped"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/PoseWithCovarianceStamped"
FOXGLOVE_POSE_IN_FRAME = "foxglove.PoseInFrame"
POSE_TYPES = (ODOMETRY, POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED, FOXGLOVE_POSE_IN_FRAME)
_WITH_COVARIANCE = (ODOMETRY, POSE_WITH_COVARIANCE_STAMPED)

# Below this angle between two quaternions slerp is numerically lerp.
SLERP_LINEAR_BELOW_RAD = 1e-6


@dataclass(frozen=True)
class PoseTrack:
    """Timed poses of one topic; the arrays share their first dimension N."""

    topic: str
    times_ns: I64  # strictly ascending (header stamp; log time when none)
    positions: F64  # (N, 3)
    quaternions_xyzw: F64  # (N, 4), unit
    covariances: F64 | None  # (N, 6, 6) in ROS order (x, y, z, rot x, rot y, rot z), or None
    frame_id: str = ""  # the first message's frame (header.frame_id), "" without one
    # Messages of the topic that gave no pose, by reason (`skipped_summary`).
    skipped: Mapping[str, int] = field(default_factory=dict)

    def skipped_summary(self) -> str:
        """e.g. '2 messages skipped (1 position not finite, 1 zero quaternion)', '' for none."""
        return describe_skipped(self.skipped)

    def __len__(self) -> int:
        return int(self.times_ns.shape[0])

    def interpolate(self, times_ns: npt.ArrayLike) -> PoseTrack:
        """The poses at `times_ns` (non-decreasing): positions (and covariances) linearly
        interpolated, orientations by slerp along the shorter arc.

        Raises ValueError when a time lies outside [first, last] of the track (the message says
        how many and the range) or the times decrease.
        """
        query = np.asarray(times_ns, dtype=np.int64).reshape(-1)
        if query.size > 1 and (np.diff(query) < 0).any():
            raise ValueError(f"{self.topic}: interpolation times must be non-decreasing")
        self._check_range(query)
        lower = np.clip(np.searchsorted(self.times_ns, query, side="right") - 1, 0, len(self) - 1)
        upper = np.minimum(lower + 1, len(self) - 1)
        span = (self.times_ns[upper] - self.times_ns[lower]).astype(np.float64)
        offset = (query - self.times_ns[lower]).astype(np.float64)
        fraction = np.divide(offset, span, out=np.zeros_like(offset), where=span > 0)
        weight = fraction[:, None]
        positions = (1 - weight) * self.positions[lower] + weight * self.positions[upper]
        quaternions = slerp(self.quaternions_xyzw[lower], self.quaternions_xyzw[upper], fraction)
        covariances = None
        if self.covariances is not None:
            w3 = fraction[:, None, None]
            covariances = (1 - w3) * self.covariances[lower] + w3 * self.covariances[upper]
        return PoseTrack(self.topic, query, positions, quaternions, covariances, self.frame_id)

    def _check_range(self, query: I64) -> None:
        if len(self) == 0:
            if query.size:
                raise ValueError(f"{self.topic}: no poses to interpolate {query.size} times")
            return
        first, last = int(self.times_ns[0]), int(self.times_ns[-1])
        outside = int(np.count_nonzero((query < first) | (query > last)))
        if outside:
            raise ValueError(
                f"{self.topic}: {outside} of {query.size} times lie outside the poses' range "
                f"[{first}, {last}] ns ({(last - first) / 1e9:.3f} s)"
            )


def slerp(q0: F64, q1: F64, fraction: F64) -> F64:
    """Row-wise spherical interpolation between unit quaternions (..., 4) along the shorter
    arc; fraction 0 gives q0, 1 gives q1 (or -q1: the same rotation). Rows come out unit."""
    q1 = np.where((np.sum(q0 * q1, axis=-1) < 0)[..., None], -q1, q1)
    cosine = np.clip(np.sum(q0 * q1, axis=-1), -1.0, 1.0)
    angle = np.arccos(cosine)
    small = angle < SLERP_LINEAR_BELOW_RAD
    sine = np.where(small, 1.0, np.sin(angle))
    w0 = np.where(small, 1 - fraction, np.sin((1 - fraction) * angle) / sine)
    w1 = np.where(small, fraction, np.sin(fraction * angle) / sine)
    result = w0[..., None] * q0 + w1[..., None] * q1
    normalized: F64 = result / np.linalg.norm(result, axis=-1, keepdims=True)
    return normalized


# ---------------------------------------------------------------------------------------------
# Reading


@dataclass
class _Pose:
    time_ns: int
    position: list[float]  # x, y, z
    quaternion: list[float]  # x, y, z, w
    covariance: list[float] | None


def describe_skipped(skipped: Mapping[str, int]) -> str:
    total = sum(skipped.values())
    if not total:
        return ""
    reasons = ", ".join(f"{n} {reason}" for reason, n in sorted(skipped.items()))
    return f"{total} message{'s' if total > 1 else ''} skipped ({reasons})"


def canonical_type(name: str) -> str:
    """ROS 2 names to ROS 1 ones: nav_msgs/msg/Odometry -> nav_msgs/Odometry."""
    return name.replace("/msg/", "/")


def default_pose_topic(source: Source) -> str | None:
    """The pose topic a run uses when none is asked for (the motion rule, the metric poses
    and the trajectory drawn, all of them): the log's first nav_msgs/Odometry topic (what a
    robot itself estimates), else its first topic of another pose type (PoseStamped,
    PoseWithCovarianceStamped, foxglove.PoseInFrame); None without one. 'First' is the order
    of the log's channels; our own topics (/doseqslam/..., e.g. the optimized pose) are never
    picked."""
    channels = [c for c in source.channels() if not c.topic.startswith("/doseqslam/")]
    topics = [(c.topic, canonical_type(c.message_type)) for c in channels]
    poses = [(topic, kind) for topic, kind in topics if kind in POSE_TYPES]
    odometry = [topic for topic, kind in poses if kind == ODOMETRY]
    candidates = odometry or [topic for topic, _ in poses]
    return candidates[0] if candidates else None


def run_pose_topic(source: Source, asked: str | None) -> str:
    """The one rule for a run's odometry: the topic asked for (`--odometry-topic`; "" none),
    else `default_pose_topic` ("" when the log has none)."""
    if asked is not None:
        return asked
    return default_pose_topic(source) or ""


def read_poses(log: Log, topic: str) -> PoseTrack:
    """Every pose of `topic` in the log (an open Source, or the path of an MCAP, ROS 1 .bag,
    rosbag2 folder or .db3), with the first message's frame id.

    Raises SourceError (one line naming the file and the topic) when the log cannot be read,
    the topic is missing, its message type is not a supported pose type, or it holds no
    usable pose. Unusable messages are skipped and counted (`PoseTrack.skipped`).
    """
    with opened(log) as source:
        poses = PoseReader(source, topic)
        for message in source.messages(topic):
            poses.add(message)
    return poses.track()


class PoseReader(SideTopicReader):
    """A pose topic's messages in, its PoseTrack out: `read_poses` feeds it a whole topic,
    a run the messages its replay's pass meets (`add_side`).

    Raises SourceError (constructor) when the topic is missing or not a supported pose type.
    """

    def __init__(self, source: Source, topic: str) -> None:
        self.topic, self.path = topic, source.path
        types = [c.message_type for c in source.channels() if c.topic == topic]
        self.kind = _check_type(self.path, topic, [n for t in types for n in t.split(", ")])
        self.columns = _Columns(self.path, topic, with_covariance=self.kind in _WITH_COVARIANCE)

    def add(self, message: DecodedMessage) -> None:
        """One message of the topic, in log-time order: a pose kept, or why not counted."""
        columns = self.columns
        if message.decode_error is not None:
            columns.skipped["undecodable"] += 1
            return
        try:
            pose = _pose(self.kind, message.message, message.log_time_ns)
        except (TypeError, ValueError, AttributeError, OverflowError):
            columns.skipped["fields missing or not numbers"] += 1
            return
        if columns.add(pose) and len(columns.times) == 1:
            columns.frame_id = frame_id_of(message.message)

    def track(self) -> PoseTrack:
        """The poses read; SourceError when the topic holds no usable pose or could not be
        decoded."""
        if self.error is not None:
            raise self.error
        columns = self.columns
        if not columns.times:
            if columns.skipped:
                raise SourceError(
                    f"{self.path}: topic {self.topic!r} holds no usable pose "
                    f"({describe_skipped(columns.skipped)})"
                )
            raise SourceError(f"{self.path}: topic {self.topic!r} holds no messages")
        return _track(columns)


def frame_id_of(message: Any) -> str:
    """header.frame_id (ROS) or frame_id (foxglove.PoseInFrame, protobuf or JSON dict)."""
    header = _get(message, "header")
    value = _get(header, "frame_id") if header is not None else _get(message, "frame_id")
    return value if isinstance(value, str) else ""


def _get(value: Any, name: str) -> Any:
    return value.get(name) if isinstance(value, dict) else getattr(value, name, None)


def _check_type(path: Path, topic: str, type_names: list[str]) -> str:
    """The topic's canonical pose type; SourceError for a missing topic or another type."""
    if not type_names:
        raise SourceError(f"{path}: topic {topic!r} is not in the log")
    kinds = {canonical_type(name) for name in type_names}
    if len(kinds) != 1 or next(iter(kinds)) not in POSE_TYPES:
        raise SourceError(
            f"{path}: topic {topic!r} is {', '.join(sorted(set(type_names)))}, not a supported "
            f"pose type ({', '.join(POSE_TYPES)})"
        )
    return kinds.pop()


# ---------------------------------------------------------------------------------------------
# Message fields (ROS objects, protobuf objects, or dicts from Foxglove JSON)


def _field(value: Any, *names: str) -> Any:
    for name in names:
        if isinstance(value, dict) and name in value:
            return value[name]
        if not isinstance(value, dict) and hasattr(value, name):
            return getattr(value, name)
    return None


def _stamp_ns(stamp: Any) -> int:
    """ROS Time (sec, nanosec / nsec) or protobuf Timestamp (seconds, nanos); 0 when absent."""
    if stamp is None:
        return 0
    seconds = _field(stamp, "sec", "seconds", "secs") or 0
    nanos = _field(stamp, "nanosec", "nsec", "nanos", "nsecs") or 0
    return int(seconds) * 1_000_000_000 + int(nanos)


def _pose(kind: str, message: Any, log_time_ns: int) -> _Pose:
    if kind == FOXGLOVE_POSE_IN_FRAME:
        stamp = _stamp_ns(_field(message, "timestamp"))
        pose, covariance = _field(message, "pose"), None
    else:
        stamp = _stamp_ns(_field(_field(message, "header"), "stamp"))
        pose = _field(message, "pose")
        covariance = None
        if kind in _WITH_COVARIANCE:  # PoseWithCovariance: the pose and its covariance
            covariance = [float(v) for v in _field(pose, "covariance")]
            pose = _field(pose, "pose")
    position = _components(_field(pose, "position"), "xyz")
    quaternion = _components(_field(pose, "orientation"), "xyzw")
    return _Pose(stamp if stamp > 0 else log_time_ns, position, quaternion, covariance)


def _components(value: Any, axes: str) -> list[float]:
    # Protobuf and JSON leave zero components out.
    return [float(_field(value, axis) or 0.0) for axis in axes]


class _Columns:
    """Pose messages as flat arrays, filled as they are read (8 bytes a value): kept as one
    Python object each, with lists of floats, the Odometry messages of a log of a few hours
    would take hundreds of MB."""

    def __init__(self, path: Path, topic: str, with_covariance: bool) -> None:
        self.path, self.topic = path, topic  # for errors
        self.times = array("q")
        self.poses = array("d")  # x, y, z, qx, qy, qz, qw per message
        self.covariances = array("d")  # 36 per message, when the type has a covariance
        self.with_covariance = with_covariance
        self.frame_id = ""
        self.skipped: Counter[str] = Counter()

    def add(self, pose: _Pose) -> bool:
        """Keep `pose`, or count why it cannot be one; whether it was kept."""
        reason = _unusable(pose)
        if reason:
            self.skipped[reason] += 1
            return False
        self.times.append(pose.time_ns)
        self.poses.extend(pose.position + pose.quaternion)
        if pose.covariance is not None:  # every message of the topic's type has one
            self.covariances.extend(pose.covariance)
        return True


def _unusable(pose: _Pose) -> str:
    """Why a message cannot be a pose, "" when it can. A covariance that is not finite keeps
    its pose: the exports then give that edge the default information and say so."""
    if pose.covariance is not None and len(pose.covariance) != 36:
        return f"covariance of {len(pose.covariance)} values"
    if not all(math.isfinite(v) for v in pose.position):
        return "position not finite"
    if not all(math.isfinite(v) for v in pose.quaternion):
        return "orientation not finite"
    if math.fsum(v * v for v in pose.quaternion) < 1e-18:
        return "zero quaternion"
    if not -(2**63) <= pose.time_ns < 2**63:
        return "stamp out of range"
    return ""


def _track(columns: _Columns) -> PoseTrack:
    topic = columns.topic
    # Stable: the first of equal times comes first.
    unsorted = np.frombuffer(columns.times, dtype=np.int64)
    order = np.argsort(unsorted, kind="stable")
    times = unsorted[order]
    keep = np.concatenate([[True], np.diff(times) > 0])
    values = np.frombuffer(columns.poses, dtype=np.float64).reshape(-1, 7)[order][keep]
    positions, quaternions = values[:, :3].copy(), values[:, 3:].copy()
    norms = np.linalg.norm(quaternions, axis=1)  # finite and > 0: `_unusable`
    skipped = Counter(columns.skipped)
    if repeated := int(np.count_nonzero(~keep)):
        skipped["stamp repeated"] = repeated
    covariances = None
    if columns.with_covariance:
        matrices = np.frombuffer(columns.covariances, dtype=np.float64).reshape(-1, 6, 6)
        covariances = matrices[order][keep]
    unit = quaternions / norms[:, None]
    return PoseTrack(topic, times[keep], positions, unit, covariances, columns.frame_id, skipped)
