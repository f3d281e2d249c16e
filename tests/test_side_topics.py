"""Issue #40, item 1: a side topic's unusable message is skipped and counted by reason, never
the whole topic for one message. Here /odom of drive_loops with single bad samples: the
pose track keeps the rest, the run's metric poses still come from the odometry and the
summaries (annotate, export, optimize) say how many messages were skipped and why."""

from __future__ import annotations

import contextlib
import io
import math
import struct
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
from mcap_ros2.decoder import DecoderFactory

from doseqslam_logs.annotations.records import FrameTimes
from doseqslam_logs.cli.main import main
from doseqslam_logs.pipeline.metric_edges import read_odometry
from doseqslam_logs.sources.poses import read_poses

REPO = Path(__file__).resolve().parents[1]
LOOPS = REPO / "sample_logs" / "drive_loops.ros2.mcap"
ODOM = "/odom"


def _damaged(data: bytes, decoded: object, damage: str) -> bytes:
    pose = decoded.pose.pose  # type: ignore[attr-defined]
    if damage == "undecodable":
        return data[:24]
    if damage == "nan covariance":  # kept: the exports use the default information
        covariance = struct.pack("<36d", *decoded.pose.covariance)  # type: ignore[attr-defined]
        at = data.find(covariance)
        assert at > 0
        return data[:at] + struct.pack("<36d", *[math.nan] * 36) + data[at + 288 :]
    p, q = pose.position, pose.orientation
    # The whole pose (7 doubles) locates it: a zero position alone may match padding.
    old = struct.pack("<7d", p.x, p.y, p.z, q.x, q.y, q.z, q.w)
    if damage == "nan position":
        new = struct.pack("<7d", math.nan, p.y, p.z, q.x, q.y, q.z, q.w)
    else:  # "zero quaternion"
        new = struct.pack("<7d", p.x, p.y, p.z, 0, 0, 0, 0)
    at = data.find(old)
    assert at > 0
    return data[:at] + new + data[at + len(old) :]


# change(topic, index of the message in its topic, data, decode) -> the data written instead
Change = Callable[[str, int, bytes, Callable[[bytes], object]], bytes]


def rewrite_messages(source: Path, out: Path, change: Change) -> Path:
    """The ROS 2 MCAP `source` written again with each message's data as `change` says."""
    factory = DecoderFactory()
    decoders: dict[int, Callable[[bytes], object]] = {}  # by channel id, made when asked for
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    counts: Counter[str] = Counter()

    def decoder(schema: Any, channel: Any) -> Callable[[bytes], object]:
        def decode(data: bytes) -> object:
            if channel.id not in decoders:
                made = factory.decoder_for(channel.message_encoding, schema)
                assert made is not None
                decoders[channel.id] = made
            return decoders[channel.id](data)

        return decode

    with source.open("rb") as stream, out.open("wb") as sink:
        writer = Writer(sink, compression=CompressionType.ZSTD)
        writer.start(profile="ros2")
        for schema, channel, message in make_reader(stream).iter_messages():
            assert schema is not None
            decode = decoder(schema, channel)
            data = change(channel.topic, counts[channel.topic], message.data, decode)
            counts[channel.topic] += 1
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id]
                )
            writer.add_message(channels[channel.id], message.log_time, data, message.publish_time)
        writer.finish()
    return out


def copy_with_bad_odometry(out: Path, damage_of: dict[int, str]) -> Path:
    """drive_loops with the i-th /odom message damaged as damage_of[i] says."""

    def change(topic: str, index: int, data: bytes, decode: Callable[[bytes], object]) -> bytes:
        if topic != ODOM or index not in damage_of:
            return data
        return _damaged(data, decode(data), damage_of[index])

    return rewrite_messages(LOOPS, out, change)


def test_each_bad_odometry_message_is_skipped_and_counted(tmp_path: Path) -> None:
    damage = {10: "nan position", 50: "zero quaternion", 90: "undecodable"}
    log = copy_with_bad_odometry(tmp_path / "bad_odom.mcap", damage)
    track = read_poses(log, ODOM)
    assert len(track) == len(read_poses(LOOPS, ODOM)) - 3
    assert dict(track.skipped) == {
        "position not finite": 1,
        "zero quaternion": 1,
        "undecodable": 1,
    }


@pytest.mark.slow
def test_one_nan_odometry_sample_costs_no_metric_pose_and_is_reported(tmp_path: Path) -> None:
    """Before: one NaN position in 240 messages dropped /odom silently, and all pairs fell
    back to rotation only, each with the false reason "no odometry topic"."""
    damage = {100: "nan position", 150: "nan covariance"}
    log = copy_with_bad_odometry(tmp_path / "nan_odom.mcap", damage)
    out = tmp_path / "out.mcap"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["annotate", str(log), "-o", str(out)]) == 0
    summary = printed.getvalue()
    assert "(odometry /odom, 1 message skipped (1 position not finite))" in summary
    fitted = int(summary.split(" odometry_pnp")[0].rsplit(" ", 1)[-1])
    assert fitted >= 40  # the sample gives 59 with every sample usable
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
        assert main(["export", str(out), "--format", "g2o", "-o", str(tmp_path / "g.g2o")]) == 0
    exported = printed.getvalue()
    assert "odometry: 1 message skipped (1 position not finite)" in exported
    assert "without a covariance use the default information" in exported
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["optimize", str(out), "-o", str(tmp_path / "opt.mcap")]) == 0
    optimized = printed.getvalue()  # optimize says what export says
    assert "odometry: 1 message skipped (1 position not finite)" in optimized
    assert "without a covariance use the default information" in optimized


def test_a_default_pose_topic_with_no_usable_message_is_named_as_the_reason(
    tmp_path: Path,
) -> None:
    """Every /odom sample bad: the metric stage goes on without odometry, and says that /odom
    was unusable and why, not that the log has no odometry topic."""
    log = copy_with_bad_odometry(
        tmp_path / "all_bad.mcap", dict.fromkeys(range(240), "nan position")
    )
    frame_times = FrameTimes.from_pairs([(t, t) for t in range(1, 241)])
    odometry = read_odometry(log, frame_times, "log", None)
    assert odometry.frames is None
    assert odometry.missing_reason == (
        "odometry_pnp: odometry /odom unusable (topic '/odom' holds no usable pose "
        "(240 messages skipped (240 position not finite)))"
    )
