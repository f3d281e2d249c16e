"""`doseqslam-logs info LOG`: the camera channels of a log and a summary of the rest."""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass
from itertools import islice
from pathlib import Path
from typing import Any

from ..annotations.records import OUR_TOPIC_PREFIX, RunMetadata
from ..errors import ImageDecodeError
from ..sources import open_source
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


def run_summary(run: RunMetadata) -> dict[str, Any]:
    """What an annotated log says of the run that wrote it."""
    return {
        "tool_version": run.tool_version,
        "method": run.method,
        "parameters_hash": run.parameters_hash,
        "verification": run.verification,
        "verification_hash": run.verification_hash or None,
        "loop_closures": run.loop_closures,
        "candidate_pairs": run.verified_pairs if run.verification == "on" else None,
        "sequences": run.sequences,
        "frames_used": run.frames_used,
        "image_topic": run.image_topic,
        "odometry_topic": run.odometry_topic or None,
        "source_file": run.source_file,
        "source_sha256": run.source_sha256,
    }


def _run_line(run: RunMetadata) -> str:
    verified = (
        f"verification {run.verification_hash}, {run.loop_closures} loop closures of "
        f"{run.verified_pairs} candidate pairs"
        if run.verification == "on"
        else f"no verification, {run.loop_closures} loop closures"
    )
    return (
        f"  annotated by doseqslam-logs {run.tool_version}: {run.method}, parameters "
        f"{run.parameters_hash}, {verified}, {run.sequences} sequences over {run.frames_used} "
        f"frames of {run.image_topic} from {run.source_file}"
        + (f", odometry {run.odometry_topic}" if run.odometry_topic else "")
    )


def run(args: argparse.Namespace) -> int:
    from ..annotations.reader import read_run_metadata

    with open_source(args.log) as source:
        channels = source.channels()
        # Our match images are a picture of the run, not a camera of the log.
        ours = [c for c in channels if c.is_image and c.topic.startswith(OUR_TOPIC_PREFIX)]
        cameras = [camera_summary(source, c) for c in channels if c.is_image and c not in ours]
    others = [c for c in channels if not c.is_image or c in ours]
    annotated = read_run_metadata(args.log) if Path(args.log).is_file() else None
    if args.json:
        doc: dict[str, Any] = {
            "log": str(args.log),
            "cameras": [asdict(c) for c in cameras],
            "other_channels": [asdict(c) for c in others],
            "doseqslam_run": None if annotated is None else run_summary(annotated),
        }
        print(json.dumps(doc, indent=2))
        return 0
    print(f"{args.log}: {len(channels)} channels, {len(cameras)} camera channel(s)")
    if annotated is not None:
        print(_run_line(annotated))
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
