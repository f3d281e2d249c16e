"""A ROS 1-profile MCAP (what `annotate` makes of a ROS 1 .bag) as a ROS 1 .bag: `to-bag`, and
`annotate LOG.bag -o OUT.bag`.

rosbags, rosbags-convert and evo read MCAP only as ROS 2 ("Profile is not ros2"); rosbag,
rosbags and evo read the .bag this writes. Every message keeps its bytes, topic and log time
(written in log-time order); every channel its type, definition (the MCAP schema) and md5sum
(channel metadata). The .bag is written atomically (`sinks.atomic`), never over the input.

A log that is not a ROS 1 MCAP throughout is refused (UsageError) before anything is written,
naming the tool that converts it when there is one: `rosbags-convert` writes a ROS 2 MCAP or a
rosbag2 bag as a .bag (it re-serializes CDR as ROS 1).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import UsageError
from ..sources import chunk_limits  # noqa: F401 - the input's chunks are read within the cap
from ..sources.copying import guarded_reads, reading_errors
from ..sources.formats import format_of
from .atomic import atomic_path
from .mcap_writer import refuse_same_file

ROS1 = ("ros1", "ros1msg")  # (message encoding, schema encoding) of a ROS 1 channel


@dataclass(frozen=True)
class BagResult:
    """What `mcap_to_bag` wrote."""

    messages: int
    topics: int

    @property
    def summary(self) -> str:
        return f"{self.messages} messages on {self.topics} topics"


def mcap_to_bag(mcap_path: str | Path, bag_path: str | Path) -> BagResult:
    """Write the ROS 1-profile MCAP `mcap_path` as the ROS 1 bag `bag_path`, atomically.

    Raises SourceError (exit 3) for an input that is missing or cannot be read, UsageError
    (exit 2) for a log that is not a ROS 1 MCAP throughout (or lacks a channel's md5sum),
    OutputError (exit 6) when the .bag cannot be written or would replace the input."""
    from mcap.reader import make_reader

    source, target = Path(mcap_path), Path(bag_path)
    kind = format_of(source).name
    if kind != "mcap":
        raise UsageError(_not_an_mcap(source, kind))
    refuse_same_file(source, target)
    with reading_errors(source):
        stream = source.open("rb")
    with stream:
        reader = make_reader(stream)
        with reading_errors(source):
            profile = reader.get_header().profile
            summary = reader.get_summary()
        _check_ros1(source, profile, summary)
        messages = guarded_reads(source, reader.iter_messages(log_time_order=True))
        with atomic_path(target) as temporary:
            return _write(source, messages, temporary)


def _not_an_mcap(source: Path, kind: str) -> str:
    if kind == "ros1-bag":
        return f"{source}: a ROS 1 .bag already, not an MCAP"
    return (
        f"{source}: a rosbag2 bag, not a ROS 1 MCAP: `rosbags-convert --src {source} "
        "--dst OUT.bag` writes it as a ROS 1 .bag"
    )


def _check_ros1(source: Path, profile: str, summary: Any) -> None:
    """UsageError, naming the tool that converts it, for an MCAP that is not ROS 1."""
    channels = []
    if summary is not None:
        channels = [(c, summary.schemas.get(c.schema_id)) for c in summary.channels.values()]
    if profile == "ros2" or any(c.message_encoding == "cdr" for c, _ in channels):
        raise UsageError(
            f"{source}: a ROS 2 MCAP, not ROS 1: rosbags and evo read it as it is; "
            f"`rosbags-convert --src {source} --dst OUT.bag` writes it as a ROS 1 .bag"
        )
    if profile != "ros1":
        raise UsageError(
            f"{source}: MCAP profile {profile!r}, not 'ros1': only a ROS 1-profile MCAP "
            "(annotate's output of a ROS 1 .bag) becomes a .bag"
        )
    for channel, schema in channels:
        _check_channel(source, channel, schema)


def _check_channel(source: Path, channel: Any, schema: Any) -> None:
    encodings = (channel.message_encoding, schema.encoding if schema is not None else "")
    if encodings != ROS1:
        raise UsageError(
            f"{source}: channel {channel.topic} is not ROS 1 (message encoding "
            f"{channel.message_encoding!r}): a .bag holds only ROS 1 messages"
        )
    if "md5sum" not in channel.metadata:
        raise UsageError(
            f"{source}: channel {channel.topic} has no md5sum in its metadata, which a .bag "
            "connection needs"
        )


def _write(source: Path, messages: Any, bag_path: Path) -> BagResult:
    from rosbags.rosbag1 import Writer

    connections: dict[int, Any] = {}
    count = 0
    with Writer(bag_path) as writer:
        for schema, channel, message in messages:
            if channel.id not in connections:
                _check_channel(source, channel, schema)  # also in an MCAP without a summary
                connections[channel.id] = writer.add_connection(
                    channel.topic,
                    _msgtype(schema.name),
                    msgdef=schema.data.decode(),
                    md5sum=channel.metadata["md5sum"],
                )
            writer.write(connections[channel.id], message.log_time, message.data)
            count += 1
    return BagResult(count, len({channel.topic for channel in connections.values()}))


def _msgtype(ros1_name: str) -> str:
    """rosbags names types the ROS 2 way: sensor_msgs/Image -> sensor_msgs/msg/Image."""
    package, _, name = ros1_name.rpartition("/")
    return f"{package}/msg/{name}"
