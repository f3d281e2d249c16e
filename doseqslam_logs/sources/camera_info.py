"""The camera intrinsics a log records: the first CameraInfo of the camera
(sensor_msgs/CameraInfo, or Foxglove's CameraCalibration, which has the same K, width, height).

Geometric verification fits an essential matrix (and recovers the relative pose) when the
intrinsics are known. The CameraInfo topic chosen is the one sharing the longest topic prefix
with the image topic (/camera/image/compressed -> /camera/camera_info).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from . import Log, opened

CAMERA_INFO_TYPES = (
    "sensor_msgs/msg/CameraInfo",
    "sensor_msgs/CameraInfo",
    "foxglove.CameraCalibration",
    "foxglove_msgs/msg/CameraCalibration",
)


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


def read_camera_info(log: Log, image_topic: str) -> CameraInfo | None:
    """The first CameraInfo of the camera of `image_topic`, or None when the log has none
    (or only ones without a focal length, e.g. an uncalibrated camera: K all zero). The
    camera's CameraInfo topic is the one sharing the longest prefix with the image topic.

    Raises SourceError when the log cannot be read.
    """
    with opened(log) as source:
        topics = [c.topic for c in source.channels() if _is_camera_info(c.message_type)]
        topic = _closest(topics, image_topic)
        if topic is None:
            return None
        first = next(iter(source.messages(topic)), None)
    return None if first is None else _camera_info(topic, first.message)


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


def _camera_info(topic: str, message: Any) -> CameraInfo | None:
    k = getattr(message, "k", None)
    if k is None:
        k = getattr(message, "K", None)
    if k is None or len(k) != 9:
        return None
    fx, fy, cx, cy = float(k[0]), float(k[4]), float(k[2]), float(k[5])
    if not (fx > 0 and fy > 0):
        return None
    return CameraInfo(topic, int(message.width), int(message.height), fx, fy, cx, cy)
