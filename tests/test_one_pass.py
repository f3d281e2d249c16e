"""One pass over the camera topic and its side topics (`Source.image_and_side_messages`): the
same image messages as `image_messages`, the same side messages as `messages` of each topic,
in log-time order, for every container; the pose and CameraInfo readers fed by that pass give
what reading their topics whole gives."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from doseqslam_logs.sources import open_source
from doseqslam_logs.sources.base import ImageMessage, SideMessage, merged_passes
from doseqslam_logs.sources.camera_info import CameraInfoReader, find_camera_info
from doseqslam_logs.sources.poses import PoseReader, read_poses

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
CAMERA = "/camera/image/compressed"
SIDE = ["/odom", "/camera/camera_info"]
LOGS = [
    "drive_loops.ros2.mcap",
    "drive_loops.bag",
    "drive_loops.rosbag2",
    "drive_loops.foxglove.mcap",
    "drive_varrate.bag",
]


def _image_key(m: ImageMessage) -> tuple[Any, ...]:
    return (m.topic, m.log_time_ns, m.header_stamp_ns, m.data)


def _side_key(m: SideMessage) -> tuple[int, str]:
    decoded = m.decode()
    assert decoded.decode_error is None
    return decoded.log_time_ns, repr(decoded.message)


@pytest.mark.parametrize("name", LOGS)
def test_one_pass_yields_what_the_passes_of_each_topic_yield(name: str) -> None:
    with open_source(SAMPLES / name) as source:
        both = list(source.image_and_side_messages(CAMERA, SIDE))
        times = [m.log_time_ns for m in both]
        assert times == sorted(times)
        images = [_image_key(m) for m in both if isinstance(m, ImageMessage)]
        assert images == [_image_key(m) for m in source.image_messages(CAMERA)]
        for topic in SIDE:
            side = [m for m in both if isinstance(m, SideMessage) and m.topic == topic]
            whole = [(m.log_time_ns, repr(m.message)) for m in source.messages(topic)]
            assert [_side_key(m) for m in side] == whole and len(whole) > 200


@pytest.mark.parametrize("name", ["drive_loops.ros2.mcap", "drive_varrate.bag"])
def test_a_time_window_and_no_side_topic(name: str) -> None:
    with open_source(SAMPLES / name) as source:
        times = [m.log_time_ns for m in source.image_messages(CAMERA)]
        start, end = times[10], times[50]
        window = list(source.image_and_side_messages(CAMERA, SIDE, start, end))
        assert all(start <= m.log_time_ns < end for m in window)
        assert [m.log_time_ns for m in window if isinstance(m, ImageMessage)] == times[10:50]
        assert any(isinstance(m, SideMessage) for m in window)
        alone = list(source.image_and_side_messages(CAMERA, []))
        assert [m.log_time_ns for m in alone] == times


def test_the_merged_passes_of_a_one_topic_source_are_the_one_pass() -> None:
    # What a source that reads one topic at a time (an image folder, a toy format) inherits.
    with open_source(SAMPLES / "drive_loops.ros2.mcap") as source:
        one = [
            (type(m).__name__, m.log_time_ns) for m in source.image_and_side_messages(CAMERA, SIDE)
        ]
        merged = [(type(m).__name__, m.log_time_ns) for m in merged_passes(source, CAMERA, SIDE)]
        assert sorted(one) == sorted(merged)
        assert [t for _, t in merged] == sorted(t for _, t in merged)


@pytest.mark.parametrize("name", ["drive_loops.ros2.mcap", "drive_loops.bag"])
def test_readers_fed_by_the_pass_find_what_reading_the_topic_finds(name: str) -> None:
    with open_source(SAMPLES / name) as source:
        poses, camera = PoseReader(source, "/odom"), CameraInfoReader(source, CAMERA)
        for m in source.image_and_side_messages(CAMERA, SIDE):
            if isinstance(m, SideMessage):
                (poses.add_side if m.topic == "/odom" else camera.add_side)(m)
        track, whole = poses.track(), read_poses(source, "/odom")
        assert track.times_ns.tolist() == whole.times_ns.tolist()
        assert track.positions.tolist() == whole.positions.tolist()
        assert track.frame_id == whole.frame_id
        assert camera.found() == find_camera_info(source, CAMERA)
        assert camera.seen == 1  # the first CameraInfo is usable: the rest are not decoded
