"""Pose tracks: reading odometry and ground truth from every container, and interpolation."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import Writer as McapWriter
from mcap_ros2.writer import Writer as Ros2Writer

from doseqslam_logs.errors import SourceError
from doseqslam_logs.sources import open_source
from doseqslam_logs.sources.poses import PoseTrack, read_poses, slerp

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
DRIVE_LOOPS = {
    "ros2 mcap": SAMPLES / "drive_loops.ros2.mcap",
    "foxglove protobuf mcap": SAMPLES / "drive_loops.foxglove.mcap",
    "ros1 bag": SAMPLES / "drive_loops.bag",
    "rosbag2 sqlite3": SAMPLES / "drive_loops.rosbag2",
}
ODOM_POSE_VARIANCES = [0.05, 0.05, 1e6, 1e6, 1e6, 0.01]  # tools/loggen/camera_log_writers.py


def _true_poses() -> dict[str, np.ndarray]:
    with (SAMPLES / "drive_loops.poses.csv").open() as file:
        rows = list(csv.DictReader(file))
    return {
        "stamp_ns": np.array([int(r["stamp_ns"]) for r in rows], dtype=np.int64),
        "x": np.array([float(r["x"]) for r in rows]),
        "y": np.array([float(r["y"]) for r in rows]),
        "yaw": np.array([float(r["yaw"]) for r in rows]),
    }


def _yaw(quaternions: np.ndarray) -> np.ndarray:
    x, y, z, w = quaternions.T
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def _angle_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(np.mod(a - b + np.pi, 2 * np.pi) - np.pi)


# ---------------------------------------------------------------------------------------------
# Real logs


@pytest.mark.parametrize("container", DRIVE_LOOPS)
def test_ground_truth_matches_the_poses_csv_in_every_container(container: str) -> None:
    track = read_poses(DRIVE_LOOPS[container], "/ground_truth/pose")
    truth = _true_poses()
    assert track.topic == "/ground_truth/pose"
    np.testing.assert_array_equal(track.times_ns, truth["stamp_ns"])
    np.testing.assert_allclose(track.positions[:, 0], truth["x"], atol=1e-4)
    np.testing.assert_allclose(track.positions[:, 1], truth["y"], atol=1e-4)
    np.testing.assert_allclose(track.positions[:, 2], 1.6)  # camera height
    assert _angle_difference(_yaw(track.quaternions_xyzw), truth["yaw"]).max() < 1e-5
    np.testing.assert_allclose(np.linalg.norm(track.quaternions_xyzw, axis=1), 1.0)
    assert track.covariances is None  # PoseStamped / PoseInFrame carry none


@pytest.mark.parametrize("container", DRIVE_LOOPS)
def test_odometry_is_the_same_in_every_container_and_drifts(container: str) -> None:
    reference = read_poses(DRIVE_LOOPS["ros2 mcap"], "/odom")
    track = read_poses(DRIVE_LOOPS[container], "/odom")
    np.testing.assert_array_equal(track.times_ns, reference.times_ns)
    np.testing.assert_allclose(track.positions, reference.positions, atol=1e-9)
    np.testing.assert_allclose(track.quaternions_xyzw, reference.quaternions_xyzw, atol=1e-9)
    if container == "foxglove protobuf mcap":
        assert track.covariances is None  # PoseInFrame has no covariance
    else:
        assert track.covariances is not None and track.covariances.shape == (240, 6, 6)
        np.testing.assert_allclose(
            np.diagonal(track.covariances, axis1=1, axis2=2)[0], ODOM_POSE_VARIANCES
        )
    # The odometry frame starts at the first pose; the true path seen from its first pose
    # differs from it by a drift of tens of centimetres, not by metres and not by nothing.
    truth = _true_poses()
    yaw0 = truth["yaw"][0]
    dx, dy = truth["x"] - truth["x"][0], truth["y"] - truth["y"][0]
    local = np.column_stack(
        [np.cos(yaw0) * dx + np.sin(yaw0) * dy, -np.sin(yaw0) * dx + np.cos(yaw0) * dy]
    )
    drift = np.hypot(*(track.positions[:, :2] - local).T)
    assert drift[0] == pytest.approx(0.0, abs=1e-9)
    assert 0.3 < drift.max() < 2.0


def test_interpolating_ground_truth_between_frames_follows_the_csv() -> None:
    track = read_poses(DRIVE_LOOPS["ros2 mcap"], "/ground_truth/pose")
    truth = _true_poses()
    midpoints = (truth["stamp_ns"][:-1] + truth["stamp_ns"][1:]) // 2
    between = track.interpolate(midpoints)
    np.testing.assert_array_equal(between.times_ns, midpoints)
    expected_x = (truth["x"][:-1] + truth["x"][1:]) / 2
    np.testing.assert_allclose(between.positions[:, 0], expected_x, atol=1e-4)
    turn = np.mod(truth["yaw"][1:] - truth["yaw"][:-1] + np.pi, 2 * np.pi) - np.pi
    expected_yaw = truth["yaw"][:-1] + turn / 2
    assert _angle_difference(_yaw(between.quaternions_xyzw), expected_yaw).max() < 1e-5


# ---------------------------------------------------------------------------------------------
# Errors


def test_a_missing_topic_is_a_one_line_source_error_naming_file_and_topic() -> None:
    path = DRIVE_LOOPS["ros2 mcap"]
    with pytest.raises(SourceError, match=r"drive_loops\.ros2\.mcap: topic '/nope' is not in"):
        read_poses(path, "/nope")
    with pytest.raises(SourceError, match=r"drive_loops\.bag: topic '/nope' is not in"):
        read_poses(DRIVE_LOOPS["ros1 bag"], "/nope")


@pytest.mark.parametrize("container", ["ros2 mcap", "ros1 bag", "foxglove protobuf mcap"])
def test_a_topic_of_another_type_is_refused(container: str) -> None:
    pattern = r"'/camera/camera_info' is .*Camera(Info|Calibration), not a supported"
    with pytest.raises(SourceError, match=pattern):
        read_poses(DRIVE_LOOPS[container], "/camera/camera_info")


def test_missing_and_non_log_files_are_source_errors(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="no such file"):
        read_poses(tmp_path / "absent.mcap", "/odom")
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    with pytest.raises(SourceError, match=r"notes\.txt"):
        read_poses(text, "/odom")


def _pose_stamped_schema_text() -> str:
    with (SAMPLES / "drive_loops.ros2.mcap").open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    schema = next(s for s in summary.schemas.values() if s.name.endswith("PoseStamped"))
    return str(schema.data.decode())


def _pose_stamped(stamp_ns: int, x: float, quaternion: tuple[float, ...]) -> dict[str, Any]:
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    qx, qy, qz, qw = quaternion
    return {
        "header": {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": "map"},
        "pose": {
            "position": {"x": x, "y": 0.0, "z": 0.0},
            "orientation": {"x": qx, "y": qy, "z": qz, "w": qw},
        },
    }


def _write_pose_log(path: Path, messages: list[tuple[int, dict[str, Any]]]) -> Path:
    with path.open("wb") as stream:
        writer = Ros2Writer(stream)
        schema = writer.register_msgdef(
            "geometry_msgs/msg/PoseStamped", _pose_stamped_schema_text()
        )
        for log_time, message in messages:
            writer.write_message("/pose", schema, message, log_time=log_time)
        writer.finish()
    return path


def test_a_topic_without_messages_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "empty.mcap"
    with path.open("wb") as stream:
        writer = McapWriter(stream)
        writer.start()
        schema = writer.register_schema(
            "geometry_msgs/msg/PoseStamped", "ros2msg", _pose_stamped_schema_text().encode()
        )
        writer.register_channel("/pose", "cdr", schema)
        writer.finish()
    with pytest.raises(SourceError, match=r"empty\.mcap: topic '/pose' holds no messages"):
        read_poses(path, "/pose")


UNIT = (0.0, 0.0, 0.0, 1.0)


@pytest.mark.parametrize(
    ("x", "quaternion", "reason"),
    [
        (math.nan, UNIT, "position not finite"),
        (math.inf, UNIT, "position not finite"),
        (0.5, (0.0, math.nan, 0.0, 1.0), "orientation not finite"),
        (0.5, (0.0, 0.0, 0.0, 0.0), "zero quaternion"),
    ],
)
def test_one_unusable_pose_is_skipped_and_counted_not_the_topic(
    tmp_path: Path, x: float, quaternion: tuple[float, float, float, float], reason: str
) -> None:
    # One bad sample among good ones used to drop the whole topic (issue #40, item 1).
    messages = [(t, _pose_stamped(t, float(t), UNIT)) for t in (1_000, 2_000, 4_000)]
    messages.insert(2, (3_000, _pose_stamped(3_000, x, quaternion)))
    track = read_poses(_write_pose_log(tmp_path / "poses.mcap", messages), "/pose")
    assert track.times_ns.tolist() == [1_000, 2_000, 4_000]
    assert dict(track.skipped) == {reason: 1}
    assert track.skipped_summary() == f"1 message skipped (1 {reason})"
    only_bad = _write_pose_log(tmp_path / "bad.mcap", [(5, _pose_stamped(5, x, quaternion))])
    with pytest.raises(
        SourceError, match=rf"holds no usable pose \(1 message skipped \(1 {reason}"
    ):
        read_poses(only_bad, "/pose")


def test_an_undecodable_pose_message_is_skipped_and_counted(tmp_path: Path) -> None:
    path = tmp_path / "cut.mcap"
    with path.open("wb") as stream:
        writer = McapWriter(stream)
        writer.start()
        schema = writer.register_schema(
            "geometry_msgs/msg/PoseStamped", "ros2msg", _pose_stamped_schema_text().encode()
        )
        channel = writer.register_channel("/pose", "cdr", schema)
        good = _write_pose_log(tmp_path / "one.mcap", [(1, _pose_stamped(1, 1.0, UNIT))])
        with open_source(good) as source:
            [(_, data)] = list(source.raw_messages("/pose"))
        for t, payload in [(1_000, data), (2_000, data[:20]), (3_000, data)]:
            writer.add_message(channel, log_time=t, data=payload, publish_time=t)
        writer.finish()
    track = read_poses(path, "/pose")
    # The two good messages carry the same stamp: the second is counted as a repeat.
    assert dict(track.skipped) == {"undecodable": 1, "stamp repeated": 1}


def test_unset_stamps_fall_back_to_log_time_and_repeated_times_keep_the_first(
    tmp_path: Path,
) -> None:
    unit = (0.0, 0.0, 0.0, 2.0)  # not normalized: read_poses normalizes
    messages = [
        (3_000, _pose_stamped(0, 3.0, unit)),  # no stamp: log time 3000
        (1_000, _pose_stamped(1_000, 1.0, unit)),
        (1_500, _pose_stamped(1_000, 9.0, unit)),  # repeats stamp 1000: dropped
        (2_000, _pose_stamped(2_000, 2.0, unit)),
    ]
    track = read_poses(_write_pose_log(tmp_path / "poses.mcap", messages), "/pose")
    np.testing.assert_array_equal(track.times_ns, [1_000, 2_000, 3_000])
    np.testing.assert_array_equal(track.positions[:, 0], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(track.quaternions_xyzw, [[0, 0, 0, 1]] * 3)


def test_foxglove_json_pose_in_frame(tmp_path: Path) -> None:
    path = tmp_path / "fox.mcap"
    with path.open("wb") as stream:
        writer = McapWriter(stream)
        writer.start()
        schema = writer.register_schema("foxglove.PoseInFrame", "jsonschema", b"{}")
        channel = writer.register_channel("/gt", "json", schema)
        for k in range(3):
            # JSON leaves zero fields out, as Foxglove writers may.
            document = {
                "timestamp": {"sec": 10 + k, "nsec": 5},
                "frame_id": "map",
                "pose": {"position": {"x": float(k)}, "orientation": {"z": 0.0, "w": 1.0}},
            }
            data = json.dumps(document).encode()
            writer.add_message(channel, log_time=k, data=data, publish_time=k)
        writer.finish()
    track = read_poses(path, "/gt")
    np.testing.assert_array_equal(track.times_ns, [10_000_000_005, 11_000_000_005, 12_000_000_005])
    np.testing.assert_array_equal(track.positions, [[0, 0, 0], [1, 0, 0], [2, 0, 0]])
    assert track.covariances is None


# ---------------------------------------------------------------------------------------------
# Interpolation (hypothesis)

unit_quaternions = (
    st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4)
    .filter(lambda q: float(np.linalg.norm(q)) > 0.1)
    .map(lambda q: np.asarray(q) / np.linalg.norm(q))
)


def _rotation_angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(2 * np.arccos(np.clip(abs(float(np.dot(a, b))), 0.0, 1.0)))


@settings(max_examples=200, deadline=None)
@given(unit_quaternions, unit_quaternions, st.floats(0, 1))
def test_slerp_is_unit_and_moves_at_constant_angular_speed(
    q0: np.ndarray, q1: np.ndarray, fraction: float
) -> None:
    result = slerp(q0[None], q1[None], np.array([fraction]))[0]
    assert np.linalg.norm(result) == pytest.approx(1.0, abs=1e-12)
    total = _rotation_angle(q0, q1)  # along the shorter arc: at most pi
    assert _rotation_angle(q0, result) == pytest.approx(fraction * total, abs=1e-6)
    assert _rotation_angle(result, q1) == pytest.approx((1 - fraction) * total, abs=1e-6)


@settings(max_examples=100, deadline=None)
@given(unit_quaternions, unit_quaternions)
def test_slerp_endpoints_are_the_given_rotations(q0: np.ndarray, q1: np.ndarray) -> None:
    ends = slerp(np.stack([q0, q0]), np.stack([q1, q1]), np.array([0.0, 1.0]))
    np.testing.assert_allclose(ends[0], q0, atol=1e-9)
    assert _rotation_angle(ends[1], q1) == pytest.approx(0.0, abs=1e-6)  # q1 or -q1


@st.composite
def tracks(draw: st.DrawFn) -> PoseTrack:
    n = draw(st.integers(1, 8))
    gaps = draw(st.lists(st.integers(1, 10**10), min_size=n - 1, max_size=n - 1))
    start = draw(st.integers(0, 2 * 10**18))
    times = np.cumsum([start, *gaps]).astype(np.int64)
    coords = st.floats(-1e3, 1e3, allow_nan=False)
    positions = np.array(draw(st.lists(st.tuples(coords, coords, coords), min_size=n, max_size=n)))
    quaternions = np.array(draw(st.lists(unit_quaternions, min_size=n, max_size=n)))
    covariances = np.stack([np.eye(6) * (k + 1) for k in range(n)])
    return PoseTrack("/t", times, positions, quaternions, covariances)


@settings(max_examples=150, deadline=None)
@given(tracks(), st.lists(st.floats(0, 1), max_size=12))
def test_interpolation_stays_between_neighbours_with_unit_quaternions(
    track: PoseTrack, fractions: list[float]
) -> None:
    first, last = int(track.times_ns[0]), int(track.times_ns[-1])
    query = np.sort(np.array([first + round(u * (last - first)) for u in fractions], np.int64))
    result = track.interpolate(query)
    np.testing.assert_array_equal(result.times_ns, query)
    assert np.all(np.diff(result.times_ns) >= 0)
    np.testing.assert_allclose(np.linalg.norm(result.quaternions_xyzw, axis=1), 1.0, atol=1e-12)
    upper = np.searchsorted(track.times_ns, query, side="left")
    lower = np.searchsorted(track.times_ns, query, side="right") - 1
    upper = np.minimum(upper, len(track) - 1)
    low = np.minimum(track.positions[lower], track.positions[upper]) - 1e-9
    high = np.maximum(track.positions[lower], track.positions[upper]) + 1e-9
    assert np.all((result.positions >= low) & (result.positions <= high))
    assert result.covariances is not None
    assert np.all(result.covariances[:, 0, 0] >= lower + 1 - 1e-9)
    assert np.all(result.covariances[:, 0, 0] <= upper + 1 + 1e-9)


@settings(max_examples=100, deadline=None)
@given(tracks())
def test_interpolating_at_the_track_times_gives_the_track(track: PoseTrack) -> None:
    same = track.interpolate(track.times_ns)
    np.testing.assert_allclose(same.positions, track.positions, rtol=0, atol=1e-9)
    dots = np.abs(np.sum(same.quaternions_xyzw * track.quaternions_xyzw, axis=1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(tracks(), st.integers(1, 10**9), st.integers(0, 3))
def test_times_outside_the_track_raise_naming_how_many_and_the_range(
    track: PoseTrack, overshoot: int, inside: int
) -> None:
    first, last = int(track.times_ns[0]), int(track.times_ns[-1])
    query = [first - overshoot] + [first] * inside + [last + overshoot, last + 2 * overshoot]
    with pytest.raises(ValueError, match=rf"3 of {3 + inside} times .*\[{first}, {last}\]"):
        track.interpolate(query)


def test_decreasing_times_are_refused() -> None:
    track = PoseTrack(
        "/t", np.array([0, 10]), np.zeros((2, 3)), np.array([[0, 0, 0, 1.0]] * 2), None
    )
    with pytest.raises(ValueError, match="non-decreasing"):
        track.interpolate([5, 4])
    assert len(track.interpolate([])) == 0


def test_poses_are_kept_as_arrays_and_a_short_covariance_is_one_clear_error() -> None:
    """Poses go into flat arrays as they are read (a Python object per message took 2.6 kB:
    docs/performance.md); a covariance that is not 36 values would shift every later
    message's, so its message is skipped before anything of it is kept."""
    from doseqslam_logs.sources import poses

    columns = poses._Columns(Path("x.mcap"), "/odom", with_covariance=False)
    columns.add(poses._Pose(2, [1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 2.0], None))
    columns.add(poses._Pose(1, [4.0, 5.0, 6.0], [0.0, 0.0, 0.0, 1.0], None))
    track = poses._track(columns)
    assert track.times_ns.tolist() == [1, 2]
    assert track.positions.tolist() == [[4.0, 5.0, 6.0], [1.0, 2.0, 3.0]]
    assert track.quaternions_xyzw.tolist() == [[0.0, 0.0, 0.0, 1.0]] * 2
    assert track.covariances is None
    with_covariance = poses._Columns(Path("x.mcap"), "/odom", with_covariance=True)
    with_covariance.add(poses._Pose(1, [0.0] * 3, [0.0] * 3 + [1.0], [0.5] * 36))
    assert not with_covariance.add(poses._Pose(2, [0.0] * 3, [0.0] * 3 + [1.0], [0.5] * 35))
    assert with_covariance.add(poses._Pose(3, [0.0] * 3, [0.0] * 3 + [1.0], [0.5] * 36))
    track = poses._track(with_covariance)  # the short one skipped: no covariance shifted
    assert track.times_ns.tolist() == [1, 3] and (track.covariances == 0.5).all()
    assert dict(track.skipped) == {"covariance of 35 values": 1}
