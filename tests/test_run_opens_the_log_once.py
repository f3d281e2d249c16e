"""The run owns the log (issue #36, item 1): `annotate` opens its input once as a Source and
every stage reads through it, so the input file is opened at most 6 times (the format's probe,
the reader, the sha256, the writer's probe and its copy pass; 86 to 102 before), the odometry
and the CameraInfo are read in the replay's own pass over the camera topic (no pass of their
own), and the sources lend each read a handle of its own (two at once: two handles)."""

from __future__ import annotations

import sys
import threading
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.cli.main import main
from doseqslam_logs.sources import open_source, opened
from doseqslam_logs.sources.base import ChannelInfo
from doseqslam_logs.sources.handles import HandlePool
from doseqslam_logs.sources.mcap_source import McapSource
from doseqslam_logs.sources.poses import default_pose_topic, run_pose_topic
from doseqslam_logs.sources.rosbags_source import RosbagsSource

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
TOPIC = "/camera/image/compressed"
MAX_OPENS = 6

_watched: list[str] = []  # the path whose opens are counted ("" none)
_opens: Counter[str] = Counter()


def _count_opens(event: str, args: tuple[Any, ...]) -> None:
    watched = event == "open" and _watched and isinstance(args[0], (str, Path))
    if watched and str(Path(args[0]).resolve()) == _watched[0]:
        _opens[_watched[0]] += 1


sys.addaudithook(_count_opens)  # for the whole process: cheap while nothing is watched


def opens_of(path: Path, argv: list[str]) -> int:
    _watched[:] = [str(path.resolve())]
    _opens.clear()
    try:
        assert main(argv) == 0
    finally:
        _watched.clear()
    return _opens[str(path.resolve())]


@pytest.fixture
def topic_reads(monkeypatch: pytest.MonkeyPatch) -> Counter[tuple[str, ...]]:
    """(method, topic[, side topics...]) -> calls of the sources' readers."""
    calls: Counter[tuple[str, ...]] = Counter()
    for cls in (McapSource, RosbagsSource):
        passes = cls.image_and_side_messages

        def with_side(self: Any, topic: str, side: Any, *a: Any, _o: Any = passes) -> Any:
            calls[("image_and_side_messages", topic, *side)] += 1
            return _o(self, topic, side, *a)

        monkeypatch.setattr(cls, "image_and_side_messages", with_side)
        for name in ("messages", "raw_messages", "image_messages"):
            original = getattr(cls, name)

            def counted(self: Any, topic: str, *a: Any, _o: Any = original, _n: str = name) -> Any:
                calls[(_n, topic)] += 1
                return _o(self, topic, *a)

            monkeypatch.setattr(cls, name, counted)
    return calls


@pytest.mark.slow
@pytest.mark.parametrize("name", ["drive_loops.ros2.mcap", "drive_varrate.bag"])
def test_annotate_opens_its_input_at_most_six_times_and_reads_the_side_topics_in_the_replay(
    name: str, tmp_path: Path, topic_reads: Counter[tuple[str, ...]]
) -> None:
    log = SAMPLES / name
    opens = opens_of(log, ["annotate", str(log), "-o", str(tmp_path / "out.mcap")])
    assert 0 < opens <= MAX_OPENS
    # One pass reads the frames, the odometry and the CameraInfo; none has a pass of its own.
    replay = ("image_and_side_messages", TOPIC, "/odom", "/camera/camera_info")
    assert topic_reads[replay] == 1
    assert not [key for key in topic_reads if key[0] == "messages"], topic_reads


@pytest.mark.slow
def test_a_run_over_a_time_window_reads_its_side_topics_whole(
    tmp_path: Path, topic_reads: Counter[tuple[str, ...]]
) -> None:
    # The pass reads the window only; the odometry is read whole (poses before and after the
    # window bracket its first and last frames).
    log = SAMPLES / "drive_loops.ros2.mcap"
    out = tmp_path / "out.mcap"
    start, end = str(1_700_000_010 * 10**9), str(1_700_000_060 * 10**9)
    assert main(["annotate", str(log), "-o", str(out), "--start", start, "--end", end]) == 0
    assert topic_reads[("messages", "/odom")] == 1
    assert not [key for key in topic_reads if key[0] == "image_and_side_messages"]


def test_a_rosbag2_folder_is_opened_once_by_its_source(tmp_path: Path) -> None:
    folder = SAMPLES / "drive_loops.rosbag2"
    with open_source(folder) as source:
        assert isinstance(source, RosbagsSource)
        for _ in range(3):
            assert sum(1 for _ in source.image_messages(TOPIC)) == 240
        assert source.handles_opened == 1


def test_reads_one_after_another_share_one_handle_and_reads_at_once_get_their_own() -> None:
    with open_source(SAMPLES / "drive_loops.ros2.mcap") as source:
        assert isinstance(source, McapSource)
        one = [m.log_time_ns for m in source.image_messages(TOPIC)]
        again = [m.log_time_ns for m in source.image_messages(TOPIC)]
        assert one == again and source.handles_opened == 1
        # Interleaved: the second iteration must not seek the first one's handle.
        first, second = source.image_messages(TOPIC), source.image_messages(TOPIC)
        interleaved = [(a.log_time_ns, b.log_time_ns) for a, b in zip(first, second, strict=True)]
        assert interleaved == list(zip(one, one, strict=True))
        assert source.handles_opened == 2
        # Threads: each reads the whole topic through the one source, all get it whole.
        results: list[list[int]] = []

        def read() -> None:
            results.append([m.log_time_ns for m in source.image_messages(TOPIC)])

        threads = [threading.Thread(target=read) for _ in range(4)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        assert results == [one] * 4
        assert source.handles_opened <= 2 + 4


def test_the_pool_closes_a_handle_given_back_after_it_closed() -> None:
    made: list[list[str]] = []
    closed: list[list[str]] = []
    pool: HandlePool[list[str]] = HandlePool(lambda: made.append([]) or made[-1], closed.append)

    def borrow() -> Iterator[list[str]]:
        with pool.borrowed() as handle:
            yield handle

    lent = borrow()
    handle = next(lent)
    with pool.borrowed() as other:
        assert other is not handle  # lent: a second one is made
    pool.close()
    assert closed == [other]  # the idle one closes now
    next(lent, None)  # the lent one is given back after the close
    assert closed == [other, handle] and pool.opened == 2


def test_opened_leaves_an_open_source_open_and_closes_what_it_opened() -> None:
    log = SAMPLES / "drive_loops.ros2.mcap"
    with open_source(log) as source:
        with opened(source) as same:
            assert same is source
        assert sum(1 for _ in source.image_messages(TOPIC)) == 240  # still open
    with opened(log) as mine:
        assert mine.path == log


class _Listed:
    """A source that only lists channels (what `default_pose_topic` looks at)."""

    def __init__(self, *channels: tuple[str, str]) -> None:
        self._channels = [ChannelInfo(t, kind, "cdr", 1) for t, kind in channels]

    def channels(self) -> list[ChannelInfo]:
        return self._channels


def test_one_rule_picks_the_default_pose_topic() -> None:
    truth = ("/ground_truth/pose", "geometry_msgs/msg/PoseStamped")
    odom = ("/odom", "nav_msgs/msg/Odometry")
    image = ("/camera", "sensor_msgs/msg/Image")
    assert default_pose_topic(_Listed(image, truth, odom)) == "/odom"  # Odometry first
    assert default_pose_topic(_Listed(image, truth)) == "/ground_truth/pose"  # else any pose
    assert default_pose_topic(_Listed(image)) is None
    # Every pose type is a candidate, in either ROS spelling, Odometry before the others.
    for kind in (
        "geometry_msgs/msg/PoseWithCovarianceStamped",
        "geometry_msgs/PoseWithCovarianceStamped",
        "geometry_msgs/PoseStamped",
        "foxglove.PoseInFrame",
    ):
        assert default_pose_topic(_Listed(image, ("/pose", kind))) == "/pose"
        assert default_pose_topic(_Listed(("/pose", kind), ("/odom", "nav_msgs/Odometry"))) == (
            "/odom"
        )
    # Never our own topics (the optimized pose of a log optimized before).
    assert default_pose_topic(_Listed(("/doseqslam/optimized_pose", truth[1]))) is None
    # A run's odometry: the topic asked for ("" none), else the rule's.
    assert run_pose_topic(_Listed(image, truth, odom), None) == "/odom"
    assert run_pose_topic(_Listed(image, truth, odom), "/ground_truth/pose") == "/ground_truth/pose"
    assert run_pose_topic(_Listed(image, truth, odom), "") == ""
    assert run_pose_topic(_Listed(image), None) == ""


@pytest.mark.slow
def test_a_foxglove_pose_topic_gives_the_metric_poses_as_odometry_does(
    annotated_sample: Callable[..., Path],
) -> None:
    # drive_loops.foxglove.mcap's /odom is a foxglove.PoseInFrame: the motion rule and the
    # metric poses use it, as they use the ROS 2 sample's nav_msgs/Odometry (59 odometry_pnp,
    # 5 rotation_only each; the pose rule used to look for nav_msgs/Odometry only: 64
    # rotation_only), and the same pairs are accepted.
    def methods(name: str) -> list[tuple[int, int, str]]:
        log = read_annotations(annotated_sample(name))
        return [
            (c.query.index, c.matched.index, c.metric_method) for c in log.reported_loop_closures
        ]

    foxglove = methods("drive_loops.foxglove.mcap")
    assert Counter(method for *_, method in foxglove)["odometry_pnp"] > 0
    assert foxglove == methods("drive_loops.ros2.mcap")
