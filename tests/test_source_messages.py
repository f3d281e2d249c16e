"""Every container reads its non-image topics through one interface (`Source.messages`),
which poses and camera info use: the same decoded values from MCAP and from a ROS 1 bag."""

from __future__ import annotations

from pathlib import Path

import pytest

from doseqslam_logs.errors import SourceError
from doseqslam_logs.sources import is_mcap_file, open_source
from doseqslam_logs.sources.camera_info import read_camera_info
from doseqslam_logs.sources.poses import read_poses

SAMPLES = Path(__file__).resolve().parent.parent / "sample_logs"
MCAP, BAG = SAMPLES / "drive_loops.ros2.mcap", SAMPLES / "drive_loops.bag"


@pytest.mark.parametrize("log", [MCAP, BAG], ids=["mcap", "ros1-bag"])
def test_messages_of_a_pose_topic_come_decoded_in_log_time_order(log: Path) -> None:
    with open_source(log) as source:
        count = next(c.message_count for c in source.channels() if c.topic == "/odom")
        messages = list(source.messages("/odom"))
    assert len(messages) == count > 100
    times = [m.log_time_ns for m in messages]
    assert times == sorted(times)
    assert all(m.message_type.replace("/msg/", "/") == "nav_msgs/Odometry" for m in messages)
    assert hasattr(messages[0].message, "pose")


def test_both_containers_give_the_same_poses_and_intrinsics() -> None:
    mcap, bag = read_poses(MCAP, "/odom"), read_poses(BAG, "/odom")
    assert (mcap.times_ns == bag.times_ns).all() and (mcap.positions == bag.positions).all()
    k_mcap = read_camera_info(MCAP, "/camera/image/compressed")
    k_bag = read_camera_info(BAG, "/camera/image/compressed")
    assert k_mcap is not None and k_bag is not None
    assert (k_mcap.fx, k_mcap.cy) == (k_bag.fx, k_bag.cy) and k_mcap.fx > 0


def test_a_topic_the_log_lacks_has_no_messages_and_no_poses() -> None:
    with open_source(BAG) as source:
        assert list(source.messages("/nothing")) == []
    with pytest.raises(SourceError, match="not in the log"):
        read_poses(MCAP, "/nothing")


def test_is_mcap_file_looks_at_the_content(tmp_path: Path) -> None:
    renamed = tmp_path / "log.bag"
    renamed.write_bytes(MCAP.read_bytes()[:64])
    assert is_mcap_file(renamed) and not is_mcap_file(BAG) and not is_mcap_file(tmp_path)
    assert not is_mcap_file(tmp_path / "missing.mcap")
