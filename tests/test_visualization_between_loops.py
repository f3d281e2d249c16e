"""Between loop closures the visualization channels say "no loop": a viewer shows the latest
message of each topic, so without messages of their own there they would go on showing the
last loop closure. And the loop lines appear as the loop closures happen."""

from __future__ import annotations

import bisect
import itertools
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.detector import Parameters
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.sinks import no_loop_frame
from doseqslam_logs.sinks.visualization import EVERY_LOOP_LINES, LOOP_LINES_GROWTH, loop_lines_due
from doseqslam_logs.sources import opened
from doseqslam_logs.sources.images import decode_gray
from loggen import make_sample_logs as gen

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
CAMERA = "/camera/image/compressed"
MATCH = "/doseqslam/match/image/compressed"
TEXTS = "/doseqslam/match/annotations"
CURRENT = "/doseqslam/match/marker"
LOOP_LINES = "/doseqslam/loop_lines"
MARKERS = "/doseqslam/markers"
# One input per output profile (a .bag gives a ROS 1-profile MCAP, foxglove protobuf JSON).
NO_VERIFY = AnnotateOptions(verification=None)
PROFILES = {
    "ros2": "drive_loops.ros2.mcap",
    "ros1": "drive_loops.bag",
    "json": "drive_loops.foxglove.mcap",
}


@pytest.fixture(scope="module", params=list(PROFILES))
def drawn(request: pytest.FixtureRequest, annotated_sample: Callable[..., Path]) -> Drawn:
    name = PROFILES[request.param]
    return Drawn(request.param, SAMPLES / name, annotated_sample(name, "--no-verify"))


class Drawn:
    """One annotated sample: its camera frames, loop closures and visualization messages."""

    def __init__(self, profile: str, log: Path, output: Path) -> None:
        self.profile, self.output = profile, output
        with opened(log) as source:
            self.frames = [t for t, _ in source.raw_messages(CAMERA)]
            self.camera = dict(source.raw_messages(CAMERA))
        reported = [r for r in read_annotations(output).loop_closures if r.reported]
        self.match_of = {r.query.log_time_ns: r.matched.log_time_ns for r in reported}
        queries = set(self.match_of)
        previous = [None, *self.frames[:-1]]
        # Where "no loop" is said: the first frame that is no query after each loop closure,
        # and the log's first frame.
        self.no_loop = [
            frame
            for frame, before in zip(self.frames, previous, strict=True)
            if frame not in queries and (before is None or before in queries)
        ]

    def raw(self, topic: str) -> list[tuple[int, bytes]]:
        with opened(self.output) as source:
            return list(source.raw_messages(topic))

    def decoded(self, topic: str) -> list[tuple[int, Any]]:
        with opened(self.output) as source:
            return [(m.log_time_ns, m.message) for m in source.messages(topic)]


def latest(messages: list[tuple[int, Any]], time_ns: int) -> tuple[int, Any]:
    """What a viewer shows of a topic at `time_ns`: its latest message at or before it."""
    times = [t for t, _ in messages]
    return messages[bisect.bisect_right(times, time_ns) - 1]


def is_deletion(profile: str, scene: Any) -> bool:
    """A scene message that removes the current loop closure's line and draws nothing."""
    if profile == "json":  # a namespace of the JSON object, its fields plain dicts
        [deletion] = scene.deletions
        named = (deletion["id"], deletion["type"]) == ("doseqslam/match/0", 0)  # MATCHING_ID
        return named and not scene.entities
    [marker] = scene.markers
    return (marker.ns, marker.id, marker.action, len(marker.points)) == ("doseqslam/match", 0, 2, 0)


def lines_of(profile: str, scene: Any) -> Iterator[Any]:
    """The points of each drawing in a scene message."""
    if profile == "json":
        for entity in scene.entities:
            yield from (line["points"] for line in entity["lines"])
    else:
        yield from (marker.points for marker in scene.markers)


def test_no_loop_is_said_once_after_each_loop_closure_and_at_the_start(drawn: Drawn) -> None:
    assert len(drawn.no_loop) >= 3  # the start and at least two gaps between loop closures
    expected = sorted([*drawn.match_of, *drawn.no_loop])
    for topic in (MATCH, TEXTS, CURRENT):
        assert [t for t, _ in drawn.raw(topic)] == expected, topic
    assert [t for t, _ in drawn.raw(LOOP_LINES)] == sorted(drawn.match_of)


def test_between_loop_closures_a_viewer_shows_no_stale_loop(drawn: Drawn) -> None:
    """At every camera frame: the latest match image is the frame's own match when it is a
    query, else the grey "no loop" frame; the same for the texts and the current line."""
    images = drawn.raw(MATCH)
    texts = drawn.decoded(TEXTS)
    current = drawn.decoded(CURRENT)
    [no_loop_image] = {data for t, data in images if t in drawn.no_loop}  # one, reused
    for frame in drawn.frames:
        match = drawn.match_of.get(frame)
        _, image = latest(images, frame)
        _, annotations = latest(texts, frame)
        _, scene = latest(current, frame)
        if match is None:
            assert image == no_loop_image
            assert (annotations.points, annotations.texts, annotations.circles) == ([], [], [])
            assert is_deletion(drawn.profile, scene)
        else:
            assert image == drawn.camera[match]
            assert (len(annotations.points), len(annotations.texts)) == (1, 1)
            assert [len(points) for points in lines_of(drawn.profile, scene)] == [2]


def test_the_no_loop_frame_is_a_grey_labelled_camera_image(drawn: Drawn) -> None:
    with opened(drawn.output) as source:
        no_loop = next(m for m in source.image_messages(MATCH) if m.log_time_ns in drawn.no_loop)
        camera = next(iter(source.image_messages(CAMERA)))
    assert (no_loop.kind, no_loop.encoding) == (camera.kind, camera.encoding)  # JPEG stays JPEG
    pixels, camera_pixels = decode_gray(no_loop), decode_gray(camera)
    assert pixels.shape == camera_pixels.shape
    assert abs(float(np.median(pixels)) - 128) <= 2  # grey
    assert pixels.max() > 200  # with the white label
    # The camera's schema: the same channel schema as the camera topic.
    with drawn.output.open("rb") as stream:
        from mcap.reader import make_reader

        summary = make_reader(stream).get_summary()
    assert summary is not None
    schema_of = {c.topic: c.schema_id for c in summary.channels.values()}
    assert schema_of[MATCH] == schema_of[CAMERA]


def test_loop_lines_appear_as_the_loop_closures_happen(drawn: Drawn) -> None:
    """The trajectory whole from the start; the loop lines so far at each loop closure."""
    [(first, trajectory)] = drawn.decoded(MARKERS)
    assert first <= drawn.frames[0]
    assert [len(points) for points in lines_of(drawn.profile, trajectory)] == [240]
    so_far = drawn.decoded(LOOP_LINES)
    queries = sorted(drawn.match_of)
    for count, (time, scene) in enumerate(so_far, start=1):
        assert time == queries[count - 1]
        assert [len(points) for points in lines_of(drawn.profile, scene)] == [2 * count]
    # Between the first two frames after the start, no loop line yet: the topic is silent.
    assert so_far[0][0] > drawn.frames[0]


@given(total=st.integers(1, 20_000))
def test_the_loop_lines_written_stay_linear_in_the_loop_closures(total: int) -> None:
    # What a log with thousands of loop closures writes: every line so far at each of the
    # first EVERY_LOOP_LINES, then as they grow by LOOP_LINES_GROWTH, and all at the last.
    written, last = [], 0
    for lines in range(1, total + 1):
        if loop_lines_due(lines, last, total):
            written.append(lines)
            last = lines
    assert written[-1] == total
    assert written[:EVERY_LOOP_LINES] == list(range(1, min(total, EVERY_LOOP_LINES) + 1))
    bound = EVERY_LOOP_LINES * (EVERY_LOOP_LINES + 1) / 2 + (1 / LOOP_LINES_GROWTH + 2) * total
    assert sum(written) <= bound
    grown = [b / a for a, b in itertools.pairwise(written) if a >= EVERY_LOOP_LINES]
    assert all(g <= 1 + LOOP_LINES_GROWTH + 1 / EVERY_LOOP_LINES for g in grown[:-1])


RAW_DRIVE = gen.Config(
    name="raw", seed=4, route="loops", duration=4.0, rate=2.0, width=128, height=96, image="raw"
)


@pytest.fixture(scope="module", params=["rgb8", "mono8"])
def raw_drive(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Any:
    config = replace(
        RAW_DRIVE, formats=("ros2mcap", "bag", "foxglove"), color=request.param == "rgb8"
    )
    return gen.generate(config, tmp_path_factory.mktemp("raw"), progress=False)


@pytest.mark.parametrize("container", ["ros2mcap", "bag", "foxglove"])
def test_the_no_loop_frame_of_a_raw_camera_has_its_encoding_size_and_step(
    raw_drive: Any, container: str, tmp_path: Path
) -> None:
    """sensor_msgs/Image (CDR, ROS 1) and foxglove.RawImage (protobuf): the log's first frame
    is no query, so it gets the "no loop" frame, with the camera's raw layout."""
    output = tmp_path / "out.mcap"
    annotate_log(
        raw_drive.files[container], output, Parameters(), AnnotateOptions(verification=None)
    )
    with opened(output) as source:
        camera = next(iter(source.image_messages("/camera/image_raw")))
        no_loop = next(iter(source.image_messages("/doseqslam/match/image")))
    assert no_loop.log_time_ns == camera.log_time_ns
    layout = ("raw", camera.encoding, camera.width, camera.height, camera.step)
    assert (no_loop.kind, no_loop.encoding, no_loop.width, no_loop.height, no_loop.step) == layout
    pixels = decode_gray(no_loop)
    assert pixels.shape == (96, 128)
    assert np.median(pixels) == 128 and pixels.max() > 200  # grey, with the white label


@pytest.mark.parametrize("ros_version", [1, 2])
@pytest.mark.parametrize("lengths", [(5, 7), (8, 3), (6, 6)])
def test_an_image_field_followed_by_others_is_replaced_and_they_kept(
    ros_version: int, lengths: tuple[int, int]
) -> None:
    """foxglove_msgs/CompressedImage has its format after the data: in CDR it is realigned."""
    typename = "foxglove_msgs/msg/CompressedImage"
    store = get_typestore(Stores.ROS2_HUMBLE if ros_version == 2 else Stores.ROS1_NOETIC)
    definition = "builtin_interfaces/Time timestamp\nstring frame_id\nuint8[] data\nstring format"
    store.register(get_types_from_msg(definition, typename))
    types = store.types
    old, new = (bytes(range(1, 1 + n)) for n in lengths)

    def message(data: bytes) -> bytes:
        built = types[typename](
            types["builtin_interfaces/msg/Time"](1, 2), "cam", np.frombuffer(data, np.uint8), "png"
        )
        if ros_version == 2:
            return bytes(store.serialize_cdr(built, typename))
        return bytes(store.serialize_ros1(built, typename))

    replaced = no_loop_frame._with_data(
        message(old), old, new, "cdr" if ros_version == 2 else "ros1"
    )
    assert replaced is not None
    if ros_version == 2:
        back = store.deserialize_cdr(replaced, typename)
    else:
        back = store.deserialize_ros1(replaced, typename)
    assert (bytes(back.data), back.format, back.frame_id) == (new, "png", "cam")


def test_a_json_image_message_gets_the_new_data_in_base64_and_keeps_its_other_fields() -> None:
    sample = b'{"timestamp":{"sec":1,"nsec":2},"frame_id":"cam","data":"AQID","format":"jpeg"}'
    replaced = no_loop_frame._with_data(sample, b"\x01\x02\x03", b"\x04\x05", "json")
    assert (
        replaced
        == b'{"timestamp":{"sec":1,"nsec":2},"frame_id":"cam","data":"BAU=","format":"jpeg"}'
    )
    assert no_loop_frame._with_data(sample, b"other", b"\x04", "json") is None  # not its image


def _jpeg_message(data: bytes) -> Any:
    from doseqslam_logs.sources.base import ImageMessage

    return ImageMessage("/camera", 0, None, "compressed", "jpeg", 0, 0, 0, False, data)


def test_a_damaged_or_huge_camera_image_is_no_sample_and_prints_nothing(
    capfd: pytest.CaptureFixture[str],
) -> None:
    # The "no loop" frame is made from a camera message as the copy meets it: a damaged JPEG
    # (libjpeg complains on fd 2) or one whose header claims more pixels than the cap (a
    # bomb) is skipped, as the run's decoder skips it, without a word on stderr.
    import cv2

    ok, jpeg = cv2.imencode(".jpg", np.full((48, 64, 3), 90, np.uint8))
    assert ok
    good = jpeg.tobytes()
    damaged = good[:200] + bytes(64) + good[264:]
    sof = good.index(b"\xff\xc0") + 5  # height, then width, big-endian
    huge = good[:sof] + (60000).to_bytes(2, "big") + (60000).to_bytes(2, "big") + good[sof + 4 :]
    capfd.readouterr()
    for data in (damaged, huge):
        assert no_loop_frame._compressed(_jpeg_message(data)) is None, len(data)
    assert no_loop_frame._compressed(_jpeg_message(good)) is not None
    assert capfd.readouterr() == ("", "")
