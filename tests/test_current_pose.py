"""The current pose (`/doseqslam/current_pose`): the trajectory's pose at each camera frame,
logged at the frame's log time, stamped and interpolated at the frame's time, in the
trajectory's frame, in each output profile's pose type (Foxglove's 3-D panel draws it as an
arrow; it draws no nav_msgs/Odometry)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from unittest.mock import patch

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.sinks.visualization import CURRENT_POSE_TOPIC, Trajectory
from doseqslam_logs.sources.poses import PoseTrack, read_poses

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


@settings(max_examples=200, deadline=None)
@given(
    steps=st.lists(st.integers(1, 10**9), min_size=1, max_size=40),
    start=st.integers(0, 2**62),
    coordinates=st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=3 * 41, max_size=3 * 41),
    offsets=st.lists(st.integers(-(10**9), 41 * 10**9), min_size=1, max_size=20),
)
def test_a_position_is_np_interp_of_the_track_and_reads_no_copy_of_it(
    steps: list[int], start: int, coordinates: list[float], offsets: list[int]
) -> None:
    """The drawn position is np.interp over the track, bit for bit, as it was when each call
    converted the whole track (int64 times, a strided column) to contiguous float64: that
    conversion, once per frame, made the write's cost per frame grow with the log. The arrays
    np.interp reads are now made once, so each call passes the same contiguous float64
    arrays."""
    times = start + np.cumsum(np.array([0, *steps], np.int64))
    positions = np.array(coordinates[: 3 * len(times)], np.float64).reshape(-1, 3)
    quaternions = np.tile([0.0, 0.0, 0.0, 1.0], (len(times), 1))
    track = PoseTrack("/odom", times, positions, quaternions, None)
    trajectory = Trajectory("/odom", "odom", track)
    for offset in offsets:
        at = int(times[0]) + offset
        expected = tuple(float(np.interp(at, times, positions[:, k])) for k in range(3))
        with patch.object(np, "interp", wraps=np.interp) as spy:
            assert trajectory.position(at) == expected
        for call in spy.call_args_list:
            _, xp, fp = call.args
            assert xp.dtype == fp.dtype == np.float64
            assert xp.flags.c_contiguous and fp.flags.c_contiguous
    # The same arrays at every call (made once): one pair per axis, whatever the calls.
    with patch.object(np, "interp", wraps=np.interp) as spy:
        trajectory.position(int(times[0]))
        trajectory.position(int(times[-1]))
    assert len({(id(c.args[1]), id(c.args[2])) for c in spy.call_args_list}) == 3
