"""The camera intrinsics a log records: the first CameraInfo of the camera
(sensor_msgs/CameraInfo, or Foxglove's CameraCalibration, which has the same K, width, height).

Geometric verification fits an essential matrix (and recovers the relative pose) when the
intrinsics are known. The CameraInfo topic chosen is the one sharing the longest topic prefix
with the image topic (/camera/image/compressed -> /camera/camera_info).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.reader import make_reader

from ..errors import SourceError
from .base import MCAP_MAGIC
from .mcap_source import DESERIALIZERS

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


def read_camera_info(path: str | os.PathLike[str], image_topic: str) -> CameraInfo | None:
    """The first CameraInfo of the camera of `image_topic`, or None when the log has none
    (or only ones without a focal length, e.g. an uncalibrated camera: K all zero).

    Raises SourceError when the log cannot be read.
    """
    path = Path(path)
    try:
        if path.is_file() and _head(path) == MCAP_MAGIC:
            found = _from_mcap(path, image_topic)
        else:
            found = _from_bag(path, image_topic)
    except (OSError, McapError, ValueError, KeyError) as exc:
        raise SourceError(f"{path}: cannot read the camera info ({exc})") from exc
    if found is None:
        return None
    topic, message = found
    return _camera_info(topic, message)


def _head(path: Path) -> bytes:
    with path.open("rb") as stream:
        return stream.read(len(MCAP_MAGIC))


def _closest(topics: list[str], image_topic: str) -> str | None:
    """The topic sharing the longest '/'-separated prefix with the image topic."""

    def shared(topic: str) -> int:
        common = 0
        for a, b in zip(topic.split("/"), image_topic.split("/"), strict=False):
            if a != b:
                break
            common += 1
        return common

    return max(sorted(topics), key=shared, default=None)


def _from_mcap(path: Path, image_topic: str) -> tuple[str, Any] | None:
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        if summary is None:
            return None
        channels = {
            channel.topic: channel
            for channel in summary.channels.values()
            if (schema := summary.schemas.get(channel.schema_id)) is not None
            and schema.name in CAMERA_INFO_TYPES
        }
        topic = _closest(list(channels), image_topic)
        if topic is None:
            return None
        for schema, channel, message in reader.iter_messages(topics=[topic]):
            if schema is None:
                return None
            make = DESERIALIZERS.get((channel.message_encoding, schema.encoding))
            if make is None:
                return None
            return topic, make(schema)(message.data)
    return None


def _from_bag(path: Path, image_topic: str) -> tuple[str, Any] | None:
    from rosbags.highlevel import AnyReader

    with AnyReader([path]) as reader:
        connections = [c for c in reader.connections if c.msgtype in CAMERA_INFO_TYPES]
        topic = _closest([c.topic for c in connections], image_topic)
        chosen = [c for c in connections if c.topic == topic]
        for connection, _, raw in reader.messages(connections=chosen):
            return topic or "", reader.deserialize(raw, connection.msgtype)
    return None


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
