"""`doseqslam-logs info LOG`: the camera channels of a log and a summary of the rest."""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass
from itertools import islice
from pathlib import Path
from typing import Any

from ..errors import ImageDecodeError
from ..sources import image_channels, open_source
from ..sources.base import ChannelInfo, Source
from ..sources.images import decode_gray

OTHERS_SHOWN = 8  # the summary of non-camera channels stays one readable line


@dataclass(frozen=True)
class CameraSummary:
    topic: str
    message_type: str
    encoding: str  # raw encoding, or compressed format as the first message states it
    resolution: str  # "WxH" of the first decodable message, or "?"
    count: int
    rate_hz: float | None
    start_ns: int | None
    end_ns: int | None


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "info", help="list the camera channels of a log", description=__doc__
    )
    parser.add_argument("log", type=Path, help="MCAP file, ROS 1 .bag, rosbag2 folder or .db3")
    parser.add_argument("--json", action="store_true", help="print as JSON")
    parser.set_defaults(run=run)


def camera_summary(source: Source, channel: ChannelInfo) -> CameraSummary:
    """Encoding and resolution come from the first message that decodes (up to five tried)."""
    encoding, resolution = "?", "?"
    for msg in islice(source.image_messages(channel.topic), 5):
        encoding = msg.encoding or ("compressed" if msg.kind == "compressed" else "?")
        try:
            height, width = decode_gray(msg).shape
        except ImageDecodeError:
            continue
        resolution = f"{width}x{height}"
        break
    start, end = channel.first_log_time_ns, channel.last_log_time_ns
    rate = None
    if start is not None and end is not None and end > start and channel.message_count > 1:
        rate = (channel.message_count - 1) / ((end - start) / 1e9)
    return CameraSummary(
        channel.topic,
        channel.message_type,
        encoding,
        resolution,
        channel.message_count,
        rate,
        start,
        end,
    )


def _span(start: int | None, end: int | None) -> str:
    if start is None or end is None:
        return "?"
    return f"{(end - start) / 1e9:.1f} s from {start / 1e9:.3f}"


def run(args: argparse.Namespace) -> int:
    with open_source(args.log) as source:
        channels = source.channels()
        cameras = [camera_summary(source, c) for c in image_channels(source)]
    others = [c for c in channels if not c.is_image]
    if args.json:
        doc: dict[str, Any] = {
            "log": str(args.log),
            "cameras": [asdict(c) for c in cameras],
            "other_channels": [asdict(c) for c in others],
        }
        print(json.dumps(doc, indent=2))
        return 0
    print(f"{args.log}: {len(channels)} channels, {len(cameras)} camera channel(s)")
    for cam in cameras:
        rate = f"{cam.rate_hz:.2f} Hz" if cam.rate_hz else "? Hz"
        print(
            f"  camera {cam.topic}  {cam.message_type}  {cam.encoding}  {cam.resolution}  "
            f"{cam.count} msgs  {rate}  {_span(cam.start_ns, cam.end_ns)}"
        )
    if not cameras:
        print("  no camera channel (sensor_msgs Image/CompressedImage, foxglove images)")
    if others:
        shown = ", ".join(f"{c.topic} ({c.message_count})" for c in others[:OTHERS_SHOWN])
        more = f", +{len(others) - OTHERS_SHOWN} more" if len(others) > OTHERS_SHOWN else ""
        total = sum(c.message_count for c in others)
        print(f"  other channels: {len(others)} with {total} msgs: {shown}{more}")
    return 0
