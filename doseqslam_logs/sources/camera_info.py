"""The camera intrinsics a log records: the first CameraInfo of the camera
(sensor_msgs/CameraInfo, or Foxglove's CameraCalibration, which has the same K, width, height).

Geometric verification fits an essential matrix (and recovers the relative pose) when the
intrinsics are known. The CameraInfo topic chosen is the one sharing the longest topic prefix
with the image topic (/camera/image/compressed -> /camera/camera_info).

A CameraInfo whose K cannot be a camera (all zero, as ROS writes for an uncalibrated camera,
NaN, a focal length that is not positive) is skipped and counted by reason; the first usable
one of the topic's first MAX_CAMERA_INFOS messages is the camera's (`find_camera_info`).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from . import Log, opened
from .base import DecodedMessage, SideTopicReader, Source

CAMERA_INFO_TYPES = (
    "sensor_msgs/msg/CameraInfo",
    "sensor_msgs/CameraInfo",
    "foxglove.CameraCalibration",
    "foxglove_msgs/msg/CameraCalibration",
)
# CameraInfo messages looked at for a usable K: a camera calibrated after the log started
# publishes zeros first; a topic of zeros is not read to its end.
MAX_CAMERA_INFOS = 100


@dataclass(frozen=True)
class CameraInfo:
    """Pinhole intrinsics (pixels) for images of width x height, and where they came from."""

    topic: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float


@dataclass
class CameraInfoSearch:
    """What the log says of the camera's intrinsics: the first usable CameraInfo (None if
    there is none), its topic ("" without one), and the unusable messages seen, by reason."""

    topic: str = ""
    info: CameraInfo | None = None
    unusable: Counter[str] = field(default_factory=Counter)

    def describe_unusable(self) -> str:
        """E.g. "12 CameraInfo of /camera/camera_info with a K that is not a camera (K all
        zero: 12)"; "" when every message seen was usable."""
        total = sum(self.unusable.values())
        if not total:
            return ""
        reasons = ", ".join(f"{why}: {n}" for why, n in sorted(self.unusable.items()))
        return f"{total} CameraInfo of {self.topic} with a K that is not a camera ({reasons})"


def find_camera_info(log: Log, image_topic: str) -> CameraInfoSearch:
    """The camera of `image_topic`'s CameraInfo topic (the one sharing the longest prefix
    with the image topic) and its first usable message among the first MAX_CAMERA_INFOS.

    Raises SourceError when the log cannot be read.
    """
    with opened(log) as source:
        reader = CameraInfoReader(source, image_topic)
        if reader.search.topic:
            for item in source.messages(reader.search.topic):
                reader.add(item)
                if not reader.wants_more:
                    break
    return reader.found()


class CameraInfoReader(SideTopicReader):
    """The camera's CameraInfo messages in, a CameraInfoSearch out: `find_camera_info` feeds
    it the topic, a run the messages its replay's pass meets (`add_side`)."""

    def __init__(self, source: Source, image_topic: str) -> None:
        topics = [c.topic for c in source.channels() if _is_camera_info(c.message_type)]
        self.search = CameraInfoSearch(_closest(topics, image_topic) or "")
        self.seen = 0

    @property
    def wants_more(self) -> bool:
        """Whether a later message could still change the search."""
        search = self.search
        return self.error is None and search.info is None and self.seen < MAX_CAMERA_INFOS

    def add(self, item: DecodedMessage) -> None:
        """The topic's next message."""
        if not self.wants_more:
            return
        self.seen += 1
        search = self.search
        if item.decode_error is not None:
            search.unusable["undecodable"] += 1
            return
        info = _camera_info(search.topic, item.message)
        if isinstance(info, CameraInfo):
            search.info = info
        else:
            search.unusable[info] += 1

    def found(self) -> CameraInfoSearch:
        """The search; SourceError when the topic could not be decoded."""
        if self.error is not None:
            raise self.error
        return self.search


def read_camera_info(log: Log, image_topic: str) -> CameraInfo | None:
    """The first usable CameraInfo of the camera of `image_topic`, or None (`find_camera_info`).

    Raises SourceError when the log cannot be read.
    """
    return find_camera_info(log, image_topic).info


def _is_camera_info(message_type: str) -> bool:
    """A channel's type names (a topic may list several, comma-separated)."""
    return any(name in CAMERA_INFO_TYPES for name in message_type.split(", "))


def _closest(topics: list[str], image_topic: str) -> str | None:
    """The topic sharing the longest '/'-separated prefix with the image topic."""
    return max(sorted(topics), key=lambda t: shared_prefix(t, image_topic), default=None)


def shared_prefix(topic: str, other: str) -> int:
    """How many leading '/'-separated parts two topic names share (the empty part before a
    leading '/' counts: "/a/b" and "/a/c" share 2)."""
    common = 0
    for a, b in zip(topic.split("/"), other.split("/"), strict=False):
        if a != b:
            break
        common += 1
    return common


def _camera_info(topic: str, message: Any) -> CameraInfo | str:
    """The message's intrinsics, or why they cannot be a camera's."""
    k: Any = getattr(message, "k", None)
    if k is None:
        k = getattr(message, "K", None)
    try:
        values = [float(v) for v in k]
    except (TypeError, ValueError):
        return "no K"
    if len(values) != 9:
        return f"K of {len(values)} values"
    if not all(map(math.isfinite, values)):
        return "K not finite"
    if not any(values):
        return "K all zero"
    fx, fy, cx, cy = values[0], values[4], values[2], values[5]
    if not (fx > 0 and fy > 0):
        return "focal length not positive"
    try:
        width, height = int(message.width), int(message.height)
    except (AttributeError, TypeError, ValueError, OverflowError):
        width = height = 0
    return CameraInfo(topic, width, height, fx, fy, cx, cy)
