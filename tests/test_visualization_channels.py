"""The visualization channels (issue #19 item 2): match images, image texts, 3-D lines."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from rosbags.typesys import Stores, get_typestore

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.cli.main import main
from doseqslam_logs.detector import Parameters
from doseqslam_logs.errors import SourceError
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.sinks import visualization
from doseqslam_logs.sinks.mcap_writer import _Annotator
from doseqslam_logs.sources.mcap_source import McapSource
from doseqslam_logs.sources.rosbags_source import RosbagsSource

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
ROS2 = SAMPLES / "drive_loops.ros2.mcap"
# Loop closures the `annotate` defaults report on it (README).
LOOPS = 83
MATCH = "/doseqslam/match/image/compressed"
TEXTS = "/doseqslam/match/annotations"
MARKERS = "/doseqslam/markers"
CURRENT = "/doseqslam/match/marker"
LOOP_LINES = "/doseqslam/loop_lines"
CURRENT_POSE = "/doseqslam/current_pose"
# The first camera frames that are no query, at the start and after each run of loop closures
# (the "no loop" messages, tests/test_visualization_between_loops.py): 9 since 2c99a1e (10
# before), whose pairs placed by the odometry moved where runs of loop closures start and end;
# 10 again since the homography's rotation moved its pairs (one run of loop closures more).
NO_LOOPS = 10
NO_VERIFY = AnnotateOptions(verification=None)


def channels(path: Path) -> dict[str, tuple[str, int]]:
    """topic -> (schema name, messages)."""
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics is not None
    counts = summary.statistics.channel_message_counts
    return {
        c.topic: (summary.schemas[c.schema_id].name if c.schema_id else "", counts.get(i, 0))
        for i, c in summary.channels.items()
    }


def messages(path: Path, topic: str) -> Iterator[tuple[int, bytes]]:
    with path.open("rb") as stream:
        for _, _, message in make_reader(stream).iter_messages(topics=[topic]):
            yield message.log_time, message.data


@pytest.fixture(scope="module")
def ros2_output(annotated_sample: Callable[..., Path]) -> Path:
    return annotated_sample(ROS2.name)  # the `annotate` defaults: verification on


def reported_loops(path: Path) -> int:
    return sum(r.reported for r in read_annotations(path).loop_closures)


def test_ros2_channels_have_the_viewers_schemas_and_one_message_per_loop(
    ros2_output: Path,
) -> None:
    found = channels(ros2_output)
    assert reported_loops(ros2_output) == LOOPS
    assert found[MATCH] == ("sensor_msgs/msg/CompressedImage", LOOPS + NO_LOOPS)
    assert found[TEXTS] == ("foxglove_msgs/msg/ImageAnnotations", LOOPS + NO_LOOPS)
    # The trajectory once; the current loop closure at each query, and the loop lines so far.
    assert found[MARKERS] == ("visualization_msgs/msg/MarkerArray", 1)
    assert found[CURRENT] == ("visualization_msgs/msg/MarkerArray", LOOPS + NO_LOOPS)
    assert found[LOOP_LINES] == ("visualization_msgs/msg/MarkerArray", LOOPS)


def test_match_images_are_the_input_bytes_of_the_match_at_the_query_time(
    ros2_output: Path,
) -> None:
    records = read_annotations(ros2_output).loop_closures
    by_query = {r.query.log_time_ns: r for r in records if r.reported}
    camera = dict(messages(ROS2, "/camera/image/compressed"))
    republished = [(t, data) for t, data in messages(ros2_output, MATCH) if t in by_query]
    assert [t for t, _ in republished] == sorted(by_query)
    for log_time, data in republished:
        assert data == camera[by_query[log_time].matched.log_time_ns]


def test_markers_decode_as_a_trajectory_and_loop_lines(ros2_output: Path) -> None:
    store = get_typestore(Stores.ROS2_HUMBLE)
    typename = "visualization_msgs/msg/MarkerArray"
    [(first_time, scene)] = list(messages(ros2_output, MARKERS))
    [trajectory] = store.deserialize_cdr(scene, typename).markers
    *_, (_, so_far) = messages(ros2_output, LOOP_LINES)
    [loops] = store.deserialize_cdr(so_far, typename).markers
    assert first_time == next(messages(ROS2, "/camera/camera_info"))[0]  # the log's first
    assert (trajectory.type, len(trajectory.points)) == (4, 240)  # LINE_STRIP, every pose
    assert trajectory.header.frame_id == loops.header.frame_id == "odom"  # /odom's frame
    assert (loops.type, len(loops.points)) == (5, 2 * LOOPS)  # LINE_LIST: a line per loop
    scenes = [store.deserialize_cdr(d, typename).markers for _, d in messages(ros2_output, CURRENT)]
    current = [m for [m] in scenes if m.action == 0]  # ADD; DELETE between loop closures
    assert {(m.type, m.id, len(m.points)) for m in current} == {(5, 0, 2)}  # replaced each time
    assert len({(m.points[0].x, m.points[0].y) for m in current}) > 1  # it moves


def test_the_text_names_the_match_its_time_and_the_verification(ros2_output: Path) -> None:
    store = get_typestore(Stores.EMPTY)
    schemas = Path(__file__).resolve().parents[1] / "schemas" / "ros2" / "foxglove_msgs"
    from rosbags.typesys import get_types_from_msg

    types: dict[str, Any] = {}
    for file in schemas.glob("*.msg"):
        types.update(get_types_from_msg(file.read_text(), f"foxglove_msgs/msg/{file.stem}"))
    store.register(types)
    decoded = (
        store.deserialize_cdr(data, "foxglove_msgs/msg/ImageAnnotations")
        for _, data in messages(ros2_output, TEXTS)
    )
    annotations = next(a for a in decoded if a.texts)  # the empty ones say "no loop"
    text = annotations.texts[0].text
    badge = annotations.points[0]  # what Foxglove 1.48 draws: it draws no texts
    assert (badge.type, len(badge.points), badge.fill_color.g) == (2, 4, 0.8)
    first = min(
        (r for r in read_annotations(ros2_output).loop_closures if r.reported),
        key=lambda r: r.query.log_time_ns,
    )
    assert text.startswith(f"match: frame {first.matched.index} at ")
    assert f"accepted ({first.inliers} inliers, essential)" in text


def test_no_visualization_writes_none_of_them(tmp_path: Path) -> None:
    output = tmp_path / "out.mcap"
    annotate_log(
        ROS2, output, Parameters(), AnnotateOptions(verification=None, visualization=False)
    )
    topics = set(channels(output))
    assert not topics & {MATCH, TEXTS, MARKERS, CURRENT}
    assert {"/doseqslam/loop_closures", "/doseqslam/sequences"} <= topics


def _count_ranged_reads(
    monkeypatch: pytest.MonkeyPatch, source: type[Any]
) -> list[tuple[Any, ...]]:
    """Every `raw_messages` call of `source` (topic, start, end, messages read)."""
    reads: list[tuple[Any, ...]] = []
    original = source.raw_messages

    def spy(self: Any, topic: str, start: int | None = None, end: int | None = None):  # type: ignore[no-untyped-def]
        got = list(original(self, topic, start, end))
        reads.append((topic, start, end, len(got)))
        yield from got

    monkeypatch.setattr(source, "raw_messages", spy)
    return reads


@pytest.mark.parametrize(
    ("name", "source"), [("drive_loops.ros2.mcap", McapSource), ("drive_loops.bag", RosbagsSource)]
)
def test_match_images_come_from_the_copy_with_no_ranged_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str, source: type[Any]
) -> None:
    """The copy streams every match before its query: kept from it, never read again."""
    reads = _count_ranged_reads(monkeypatch, source)
    output = tmp_path / "out.mcap"
    annotate_log(SAMPLES / name, output, Parameters(), NO_VERIFY)
    assert channels(output)[MATCH][1] > 0
    assert reads == []


def test_over_the_budget_each_match_is_read_again_into_the_same_bytes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Bounded memory: with no room for a kept image, one ranged read of one nanosecond per
    loop closure, never the topic, and the output is the same file."""
    kept = tmp_path / "kept.mcap"
    annotate_log(ROS2, kept, Parameters(), NO_VERIFY)
    monkeypatch.setattr(visualization, "KEPT_MATCHES_BYTES", 1)
    reads = _count_ranged_reads(monkeypatch, McapSource)
    read_again = tmp_path / "read_again.mcap"
    annotate_log(ROS2, read_again, Parameters(), NO_VERIFY)
    loops = reported_loops(read_again)
    assert len(reads) == loops > 0
    assert all(s is not None and e == s + 1 and n == 1 for _, s, e, n in reads)
    assert read_again.read_bytes() == kept.read_bytes()


def test_a_copier_that_passes_no_camera_message_reads_each_match_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A log format whose copier does not call `message_copied` still gets its match images."""
    monkeypatch.setattr(_Annotator, "message_copied", lambda *args: None)
    reads = _count_ranged_reads(monkeypatch, McapSource)
    output = tmp_path / "out.mcap"
    annotate_log(ROS2, output, Parameters(), NO_VERIFY)
    assert len(reads) == channels(output)[MATCH][1] > 0


def _copy_without(source: Path, target: Path, dropped: set[str]) -> None:
    """`source` as a new MCAP without the `dropped` topics (a log with no pose topic)."""
    with source.open("rb") as stream, target.open("wb") as out:
        reader = make_reader(stream)
        header = reader.get_header()
        writer = Writer(out)
        writer.start(profile=header.profile, library="test")
        ids: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages():
            if channel.topic in dropped:
                continue
            if channel.id not in ids:
                assert schema is not None
                schema_id = writer.register_schema(schema.name, schema.encoding, schema.data)
                ids[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_id, dict(channel.metadata)
                )
            writer.add_message(
                ids[channel.id], message.log_time, message.data, message.publish_time
            )
        writer.finish()


def test_a_log_without_poses_gets_images_and_texts_but_no_lines(tmp_path: Path) -> None:
    log = tmp_path / "no_poses.mcap"
    _copy_without(ROS2, log, {"/odom", "/ground_truth/pose"})
    output = tmp_path / "out.mcap"
    annotate_log(log, output, Parameters(), NO_VERIFY)
    found = channels(output)
    assert MARKERS not in found and CURRENT not in found and CURRENT_POSE not in found
    assert found[MATCH][1] == found[TEXTS][1] > 0


def test_an_annotated_output_annotates_again_with_the_same_camera(
    ros2_output: Path, tmp_path: Path
) -> None:
    """The match image topic is an image topic too; the camera auto-choice skips ours."""
    output = tmp_path / "again.mcap"
    result = annotate_log(ros2_output, output, Parameters(), NO_VERIFY)
    assert result.topic == "/camera/image/compressed"
    assert channels(output)[MATCH][1] == channels(output)[TEXTS][1]


def test_json_profile_writes_foxglove_scene_update_and_image_annotations(tmp_path: Path) -> None:
    output = tmp_path / "out.mcap"
    annotate_log(SAMPLES / "drive_loops.foxglove.mcap", output, Parameters(), NO_VERIFY)
    found = channels(output)
    assert found[MATCH][0] == "foxglove.CompressedImage"
    assert found[TEXTS][0] == "foxglove.ImageAnnotations"
    assert found[MARKERS][0] == found[CURRENT][0] == "foxglove.SceneUpdate"
    [(_, data)] = list(messages(output, MARKERS))
    *_, (_, so_far) = messages(output, LOOP_LINES)
    scenes = [json.loads(data)["entities"], json.loads(so_far)["entities"]]
    assert [[entity["lines"][0]["type"] for entity in s] for s in scenes] == [[0], [2]]
    assert len(scenes[1][0]["lines"][0]["points"]) == 2 * reported_loops(output)
    texts = [json.loads(d)["texts"] for _, d in messages(output, TEXTS)]
    assert all("not verified (--no-verify)" in t[0]["text"] for t in texts if t)


def test_ros1_profile_channels_carry_md5sums(tmp_path: Path) -> None:
    output = tmp_path / "out.mcap"
    annotate_log(SAMPLES / "drive_loops.bag", output, Parameters(), NO_VERIFY)
    with output.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    topics = (MATCH, TEXTS, MARKERS, CURRENT, LOOP_LINES)
    ours = {c.topic: c for c in summary.channels.values() if c.topic in topics}
    assert len(ours) == 5
    names = {t: summary.schemas[c.schema_id].name for t, c in ours.items()}
    assert names[MARKERS] == "visualization_msgs/MarkerArray"
    assert names[TEXTS] == "foxglove_msgs/ImageAnnotations"
    assert all(len(c.metadata["md5sum"]) == 32 for c in ours.values())


def _with_broken_odometry(source: Path, target: Path) -> None:
    """`source` without its poses, plus an /odom topic whose one pose is NaN."""
    _copy_without(source, target.with_suffix(".tmp"), {"/odom", "/ground_truth/pose"})
    store = get_typestore(Stores.ROS2_HUMBLE)
    typename = "nav_msgs/msg/Odometry"
    types = store.types
    header = types["std_msgs/msg/Header"](types["builtin_interfaces/msg/Time"](1, 0), "odom")
    pose = store.types["geometry_msgs/msg/Pose"](
        types["geometry_msgs/msg/Point"](math.nan, 0.0, 0.0),
        types["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0),
    )
    covariance = np.zeros(36)
    twist = types["geometry_msgs/msg/TwistWithCovariance"](
        types["geometry_msgs/msg/Twist"](
            types["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0),
            types["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0),
        ),
        covariance,
    )
    odometry = types[typename](
        header, "base", types["geometry_msgs/msg/PoseWithCovariance"](pose, covariance), twist
    )
    definition, _ = store.generate_msgdef(typename, ros_version=2)
    with target.with_suffix(".tmp").open("rb") as stream, target.open("wb") as out:
        reader = make_reader(stream)
        writer = Writer(out)
        writer.start(profile="ros2", library="test")
        odom_schema = writer.register_schema(typename, "ros2msg", definition.encode())
        odom = writer.register_channel("/odom", "cdr", odom_schema)
        writer.add_message(odom, 10**9, bytes(store.serialize_cdr(odometry, typename)), 10**9)
        ids: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages():
            if channel.id not in ids:
                assert schema is not None
                schema_id = writer.register_schema(schema.name, schema.encoding, schema.data)
                ids[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_id, dict(channel.metadata)
                )
            writer.add_message(ids[channel.id], message.log_time, message.data, message.log_time)
        writer.finish()


def test_unreadable_poses_leave_out_the_lines_and_nothing_else(tmp_path: Path) -> None:
    log = tmp_path / "nan_pose.mcap"
    _with_broken_odometry(ROS2, log)
    output = tmp_path / "out.mcap"
    annotate_log(log, output, Parameters(), NO_VERIFY)
    found = channels(output)
    assert MARKERS not in found and CURRENT not in found and CURRENT_POSE not in found
    assert found[MATCH][1] == found[TEXTS][1] > 0


def test_a_match_image_not_found_again_fails_with_no_output(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The log changed under the run: SourceError (exit 3), and no output appears."""
    monkeypatch.setattr(visualization, "KEPT_MATCHES_BYTES", 0)  # each match read again
    monkeypatch.setattr(McapSource, "raw_messages", lambda *args: iter(()))
    output = tmp_path / "out.mcap"
    with pytest.raises(SourceError, match="is not found again"):
        annotate_log(ROS2, output, Parameters(), NO_VERIFY)
    assert list(tmp_path.iterdir()) == []


# Issue #19 item 5: pipes and `-` are refused with one line (they are read by seeking).


@pytest.mark.parametrize(
    "command",
    [
        ["info", "{fifo}"],
        ["annotate", "{fifo}", "-o", "{tmp}/out.mcap"],
        ["export", "{fifo}", "--format", "tum", "-o", "{tmp}/out.tum"],
        ["evaluate", "{fifo}", "--gt", str(SAMPLES / "drive_loops.gt.npz")],
    ],
)
def test_a_pipe_as_input_is_refused_without_blocking(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: list[str]
) -> None:
    fifo = tmp_path / "log.mcap"
    os.mkfifo(fifo)  # no writer: opening it for reading would block for ever
    args = [part.format(fifo=fifo, tmp=tmp_path) for part in command]
    assert main(args) == 3
    error = capsys.readouterr().err
    assert error == f"doseqslam-logs: error: {fifo}: the log is a pipe (FIFO), not a file: " \
        "logs are read by seeking; save it to a file\n"  # fmt: skip
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log.mcap"]


def test_a_pipe_in_a_batch_fails_that_log_only(tmp_path: Path) -> None:
    fifo = tmp_path / "log.mcap"
    os.mkfifo(fifo)
    assert main(["batch", str(fifo), "-o", str(tmp_path / "out")]) == 1
    [entry] = [json.loads(line) for line in (tmp_path / "out" / "manifest.jsonl").open()]
    assert entry["exit_code"] == 3 and "a pipe (FIFO)" in entry["error"]


@pytest.mark.parametrize(
    "command",
    [
        ["annotate", str(ROS2), "-o", "-"],
        ["info", "-"],
        ["annotate", "-", "-o", "out.mcap"],
        ["export", str(ROS2), "--format", "tum", "-o", "-"],
        ["diff", "-", str(ROS2)],
    ],
)
def test_dash_for_standard_input_or_output_is_a_usage_error(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    command: list[str],
) -> None:
    monkeypatch.chdir(tmp_path)  # a file named `-` would appear here
    assert main(command) == 2
    error = capsys.readouterr().err
    assert error.startswith("doseqslam-logs: error: -: standard input and output are not")
    assert error.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


# Issue #19 item 5: the output's compression and chunk size, as `mcap` has them.


def _chunks(path: Path) -> tuple[set[str], int]:
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    return {c.compression for c in summary.chunk_indexes}, len(summary.chunk_indexes)


def test_compression_and_chunk_size_shape_the_chunks_not_the_content(tmp_path: Path) -> None:
    outputs = {}
    for compression in ("zstd", "lz4", "none"):
        output = tmp_path / f"{compression}.mcap"
        args = ["annotate", str(ROS2), "-o", str(output), "--no-verify"]
        assert main([*args, "--compression", compression, "--chunk-size", "65536"]) == 0
        outputs[compression] = output
    assert _chunks(outputs["zstd"]) == ({"zstd"}, _chunks(outputs["lz4"])[1])
    assert _chunks(outputs["lz4"])[0] == {"lz4"}
    assert _chunks(outputs["none"])[0] == {""}  # MCAP spells no compression ""
    default = tmp_path / "default.mcap"
    assert main(["annotate", str(ROS2), "-o", str(default), "--no-verify"]) == 0
    assert _chunks(default)[1] < _chunks(outputs["zstd"])[1]  # 1 MiB chunks by default
    records = [
        {t: list(messages(o, t)) for t in ("/doseqslam/loop_closures", MATCH, MARKERS)}
        for o in (default, *outputs.values())
    ]
    assert all(r == records[0] for r in records)  # the same messages, byte for byte


@pytest.mark.parametrize(
    "option", [["--compression", "gzip"], ["--chunk-size", "0"], ["--chunk-size", "1k"]]
)
def test_a_bad_compression_or_chunk_size_is_a_usage_error(
    tmp_path: Path, option: list[str]
) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["annotate", str(ROS2), "-o", str(tmp_path / "out.mcap"), *option])
    assert exit_.value.code == 2
    assert list(tmp_path.iterdir()) == []
