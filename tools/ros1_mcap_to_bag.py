#!/usr/bin/env python3
"""Convert a ros1-profile MCAP (what `annotate` makes of a ROS 1 .bag) into a ROS 1 .bag.

rosbags, rosbags-convert and evo read MCAP only as ROS 2 ("Profile is not ros2"); rosbag,
rosbags and evo read the .bag this writes. Every message keeps its bytes, topic and log time;
every channel its type, definition (the MCAP schema) and md5sum (channel metadata):

    python tools/ros1_mcap_to_bag.py drive_loops.annotated.mcap drive_loops.annotated.bag

The .bag appears only when complete (written beside it, then renamed); an existing one is
not replaced.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

from mcap.reader import make_reader
from rosbags.rosbag1 import Writer

ROS1 = ("ros1", "ros1msg")  # (message encoding, schema encoding) of a ROS 1 channel


def convert(mcap_path: Path, bag_path: Path) -> int:
    """Writes `bag_path`; returns the message count. Raises ValueError for a log that is not
    ROS 1 throughout, FileExistsError when `bag_path` exists."""
    if bag_path.exists():
        raise FileExistsError(f"{bag_path} exists")
    handle, temporary = tempfile.mkstemp(suffix=".bag", dir=bag_path.parent)
    os.close(handle)
    os.unlink(temporary)  # rosbags' Writer refuses an existing file
    try:
        count = _write(mcap_path, Path(temporary))
        os.link(temporary, bag_path)  # fails instead of replacing a file made meanwhile
    finally:
        Path(temporary).unlink(missing_ok=True)
    return count


def _write(mcap_path: Path, bag_path: Path) -> int:
    connections = {}
    count = 0
    with mcap_path.open("rb") as stream, Writer(bag_path) as writer:
        reader = make_reader(stream)
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            if channel.id not in connections:
                if schema is None or (channel.message_encoding, schema.encoding) != ROS1:
                    raise ValueError(f"{channel.topic}: not a ROS 1 channel")
                connections[channel.id] = writer.add_connection(
                    channel.topic,
                    _msgtype(schema.name),
                    msgdef=schema.data.decode(),
                    md5sum=channel.metadata["md5sum"],
                )
            writer.write(connections[channel.id], message.log_time, message.data)
            count += 1
    return count


def _msgtype(ros1_name: str) -> str:
    """rosbags names types the ROS 2 way: sensor_msgs/Image -> sensor_msgs/msg/Image."""
    package, _, name = ros1_name.rpartition("/")
    return f"{package}/msg/{name}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("mcap", type=Path, help="a ros1-profile MCAP")
    parser.add_argument("bag", type=Path, help="the .bag to write (must not exist)")
    args = parser.parse_args(argv)
    try:
        count = convert(args.mcap, args.bag)
    except (OSError, ValueError, KeyError) as exc:
        print(f"ros1_mcap_to_bag: error: {exc}", file=sys.stderr)
        return 1
    print(f"{args.bag}: {count} messages")
    return 0


if __name__ == "__main__":
    sys.exit(main())
