"""The current pose (`/doseqslam/current_pose`): the trajectory's pose at each camera frame,
logged at the frame's log time, stamped and interpolated at the frame's time, in the
trajectory's frame, in each output profile's pose type (Foxglove's 3-D panel draws it as an
arrow; it draws no nav_msgs/Odometry)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.sinks.visualization import CURRENT_POSE_TOPIC
from doseqslam_logs.sources.poses import read_poses

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
# Each sample, the schema its output's current pose has.
PROFILES = {
    "drive_loops.ros2.mcap": "geometry_msgs/msg/PoseStamped",
    "drive_loops.bag": "geometry_msgs/PoseStamped",
    "drive_loops.foxglove.mcap": "foxglove.PoseInFrame",
}
FRAMES = 240  # the drive's camera frames


def log_times_and_schema(path: Path, topic: str) -> tuple[list[int], str]:
    with path.open("rb") as stream:
        reader = make_reader(stream)
        found = [(s.name, m.log_time) for s, _, m in reader.iter_messages(topics=[topic])]
    return [time for _, time in found], found[0][0]


@pytest.mark.parametrize("sample", list(PROFILES))
def test_one_pose_per_frame_at_its_log_time_interpolated_from_the_odometry(
    sample: str, annotated_sample: Callable[..., Path]
) -> None:
    output = annotated_sample(sample, "--no-verify")
    log_times, schema = log_times_and_schema(output, CURRENT_POSE_TOPIC)
    assert schema == PROFILES[sample]
    annotated = read_annotations(output)
    frame_times = annotated.frame_times
    assert frame_times is not None and len(frame_times) == FRAMES
    assert log_times == frame_times.log_times_ns.tolist()
    # Decoded by the pose reader (every profile), stamped at the frames' times.
    current = read_poses(output, CURRENT_POSE_TOPIC)
    times = annotated.detector_times_ns()
    assert times is not None
    assert current.times_ns.tolist() == times.tolist()
    odometry = read_poses(SAMPLES / sample, "/odom")
    assert current.frame_id == odometry.frame_id == "odom"
    expected = odometry.interpolate(np.clip(times, odometry.times_ns[0], odometry.times_ns[-1]))
    assert np.allclose(current.positions, expected.positions, atol=1e-9)
    same_rotation = np.abs(np.sum(current.quaternions_xyzw * expected.quaternions_xyzw, axis=1))
    assert np.allclose(same_rotation, 1.0, atol=1e-9)


def test_the_pose_follows_the_odometry_asked_for_in_its_frame(
    annotated_sample: Callable[..., Path],
) -> None:
    sample = "drive_loops.ros2.mcap"
    output = annotated_sample(sample, "--no-verify", "--odometry-topic", "/ground_truth/pose")
    current = read_poses(output, CURRENT_POSE_TOPIC)
    truth = read_poses(SAMPLES / sample, "/ground_truth/pose")
    assert current.frame_id == truth.frame_id == "map"
    expected = truth.interpolate(np.clip(current.times_ns, truth.times_ns[0], truth.times_ns[-1]))
    assert np.allclose(current.positions, expected.positions, atol=1e-9)
    odometry = read_poses(SAMPLES / sample, "/odom")
    assert not np.allclose(current.positions, odometry.positions[: len(current)], atol=1e-3)
