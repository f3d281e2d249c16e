"""`doseqslam-logs layout`: a Foxglove layout naming each annotated log's own topics and the
frame its markers are drawn in, which Lichtblick's rules accept (test_lichtblick_layout);
docs/foxglove_layout.json is what it writes for the optimized ROS 2 sample."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import test_lichtblick_layout as lichtblick
from mcap.reader import make_reader
from mcap.writer import Writer

from doseqslam_logs.cli.main import main
from doseqslam_logs.export.layout import layout_of
from doseqslam_logs.sinks.visualization import MATCH_ANNOTATIONS_TOPIC

REPO = Path(__file__).resolve().parents[1]
SAMPLES = ("drive_loops.ros2.mcap", "drive_loops.bag", "drive_loops.foxglove.mcap")
CAMERA = "/camera/image/compressed"
ANNOTATIONS = "/doseqslam/match/annotations"
SCENE = ["/doseqslam/markers", "/doseqslam/match/marker", "/doseqslam/loop_lines"]
CURRENT_POSE = "/doseqslam/current_pose"
PATHS = ["/doseqslam/odometry_path", "/doseqslam/optimized_path"]


def run_layout(log: Path, output: Path) -> dict[str, Any]:
    assert main(["layout", str(log), "-o", str(output)]) == 0
    layout: dict[str, Any] = json.loads(output.read_text())
    return layout


def panels(layout: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    configs = layout["configById"]
    query, match = configs["ImageViewPanel!query"], configs["ImageViewPanel!match"]
    return query, match, configs["3D!loops"]


def check_lichtblick(layout: dict[str, Any], log: Path) -> None:
    lichtblick.test_every_panel_of_the_migrated_layout_is_a_lichtblick_panel(layout)
    lichtblick.test_the_migrated_image_panels_show_the_same_topics(layout)
    lichtblick.check_topics_render(layout, lichtblick.topics_of(log))


def copy_renamed(
    source: Path, target: Path, renamed: dict[str, str], copied_as: dict[str, str] | None = None
) -> None:
    """`source` as a new MCAP with the topics of `renamed` renamed, and each message of a
    topic of `copied_as` also on the topic it names (same schema); metadata kept."""
    copied_as = copied_as or {}
    with source.open("rb") as stream, target.open("wb") as out:
        reader = make_reader(stream)
        writer = Writer(out)
        writer.start(profile=reader.get_header().profile, library="test")
        ids: dict[str, int] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            assert schema is not None
            topic = renamed.get(channel.topic, channel.topic)
            for name in (topic, *([copied_as[topic]] if topic in copied_as else [])):
                if name not in ids:
                    schema_id = writer.register_schema(schema.name, schema.encoding, schema.data)
                    ids[name] = writer.register_channel(
                        name, channel.message_encoding, schema_id, dict(channel.metadata)
                    )
                writer.add_message(ids[name], message.log_time, message.data, message.log_time)
        stream.seek(0)
        for record in make_reader(stream).iter_metadata():
            writer.add_metadata(record.name, dict(record.metadata))
        writer.finish()


@pytest.mark.parametrize("sample", SAMPLES)
def test_each_profile_gets_its_topics_and_the_odometry_frame(
    sample: str, annotated_sample: Callable[..., Path], tmp_path: Path
) -> None:
    output = annotated_sample(sample, "--no-verify")
    layout = run_layout(output, tmp_path / "layout.json")
    query, match, scene = panels(layout)
    assert query["cameraTopic"] == CAMERA and query["enabledMarkerTopics"] == [ANNOTATIONS]
    assert match["cameraTopic"] == "/doseqslam/match/image/compressed"
    assert match["enabledMarkerTopics"] == []  # no match annotations in this output
    # No paths before optimize; the ground truth beside the odometry, drawn as an arrow.
    assert list(scene["topics"]) == [*SCENE, CURRENT_POSE, "/ground_truth/pose"]
    assert scene["topics"][CURRENT_POSE]["type"] == "arrow"
    assert scene["followTf"] == "odom"
    check_lichtblick(layout, output)


def test_another_camera_topic_and_odometry_frame_are_named(
    annotated_sample: Callable[..., Path], tmp_path: Path
) -> None:
    # The camera and the other pose topic renamed; the run's odometry the ground truth (frame
    # map), so the /odom nav_msgs/Odometry, which the 3-D panel does not draw, is left out.
    log = tmp_path / "renamed.mcap"
    renamed = {CAMERA: "/front/compressed", "/ground_truth/pose": "/mocap/pose"}
    copy_renamed(REPO / "sample_logs" / "drive_loops.ros2.mcap", log, renamed)
    output = tmp_path / "out.mcap"
    options = ["--no-verify", "--odometry-topic", "/mocap/pose"]
    assert main(["annotate", str(log), "-o", str(output), *options]) == 0
    layout = run_layout(output, tmp_path / "layout.json")
    query, match, scene = panels(layout)
    assert query["cameraTopic"] == "/front/compressed"
    assert match["cameraTopic"] == "/doseqslam/match/image/compressed"
    assert scene["followTf"] == "map"
    assert list(scene["topics"]) == [*SCENE, CURRENT_POSE]
    check_lichtblick(layout, output)


def test_the_match_annotations_go_on_the_match_image(
    annotated_sample: Callable[..., Path], tmp_path: Path
) -> None:
    with_them = tmp_path / "with_match_annotations.mcap"
    source = annotated_sample("drive_loops.ros2.mcap", "--no-verify")
    copy_renamed(source, with_them, {}, {ANNOTATIONS: MATCH_ANNOTATIONS_TOPIC})
    layout = layout_of(with_them)
    query, match, _ = panels(layout)
    assert match["enabledMarkerTopics"] == [MATCH_ANNOTATIONS_TOPIC]
    assert query["enabledMarkerTopics"] == [ANNOTATIONS]
    check_lichtblick(layout, with_them)


@pytest.mark.slow
def test_the_docs_layout_is_the_one_written_for_the_optimized_ros2_sample(
    annotated_sample: Callable[..., Path], tmp_path: Path
) -> None:
    pytest.importorskip("gtsam")
    optimized = tmp_path / "optimized.mcap"
    assert main(["optimize", str(annotated_sample(SAMPLES[0])), "-o", str(optimized)]) == 0
    layout = run_layout(optimized, tmp_path / "layout.json")
    assert json.loads((REPO / "docs" / "foxglove_layout.json").read_text()) == layout
    _, _, scene = panels(layout)
    assert list(scene["topics"]) == [*SCENE, *PATHS, CURRENT_POSE, "/ground_truth/pose"]


@pytest.mark.parametrize("name", ["drive_loops.ros2.mcap", "drive_loops.bag", "missing.mcap"])
def test_a_log_not_annotated_is_refused_in_one_line_with_exit_3(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    layout = tmp_path / "layout.json"
    assert main(["layout", str(REPO / "sample_logs" / name), "-o", str(layout)]) == 3
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and error.startswith("doseqslam-logs: error: "), error
    assert not layout.exists() and list(tmp_path.iterdir()) == []


def test_the_layout_replaces_only_a_regular_file(
    annotated_sample: Callable[..., Path], tmp_path: Path
) -> None:
    output = annotated_sample("drive_loops.ros2.mcap", "--no-verify")
    assert main(["layout", str(output), "-o", str(tmp_path)]) == 6
    old = tmp_path / "layout.json"
    old.write_text("old")
    assert run_layout(output, old) == layout_of(output)
    assert [p.name for p in tmp_path.iterdir()] == ["layout.json"]
