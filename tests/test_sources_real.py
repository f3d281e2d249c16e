"""The log sources on the real logs in shared/data and on small MCAP files written here.

Pixels are checked against an independent decode: image bytes are cut out of the file or the raw
MCAP record by hand (no rosbags, no mcap_ros2) and decoded with OpenCV or numpy directly.
"""

from __future__ import annotations

import base64
import hashlib
import json
import struct
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType, Writer

from doseqslam_logs.errors import ImageDecodeError, NoCameraError, SourceError
from doseqslam_logs.sources import image_channels, open_source, pick_image_topic
from doseqslam_logs.sources.base import ImageMessage, Source
from doseqslam_logs.sources.images import decode_gray
from doseqslam_logs.sources.mcap_source import McapSource, in_log_time_order
from doseqslam_logs.sources.rosbags_source import RosbagsSource

FIDUCIALS = "ros1_bags_fiducials_raspicam"
TURTLESIM = "ros1_bags_rosbagjs_turtlesim"
TALKER = "ros2_bags_rosbag2_talker"
RERUN = "rosbag2_mcap_rerun_sensor_msgs/rosbag2_2025_09_10-13_03_56_0.mcap"


def frames(source: Source, topic: str, **bounds: int | None) -> list[ImageMessage]:
    return list(source.image_messages(topic, **bounds))


def imdecode_gray(data: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# --- ROS 1 bags with real JPEGs ---------------------------------------------------------------


def jpeg_from_ros1_bag(path: Path) -> bytes:
    """The CompressedImage payload, cut out of the (uncompressed) bag by hand: the serialized
    message holds `string format = "jpg"` and then `uint8[] data` as a u32 length + bytes."""
    blob = path.read_bytes()
    marker = b"\x03\x00\x00\x00jpg"
    start = blob.index(marker) + len(marker)
    (length,) = struct.unpack_from("<I", blob, start)
    jpeg = blob[start + 4 : start + 4 + length]
    assert jpeg[:3] == b"\xff\xd8\xff" and jpeg[-2:] == b"\xff\xd9"
    return jpeg


@pytest.mark.parametrize(
    ("name", "topic", "shape", "stamp_s"),
    [
        ("aruco_images.bag", "/raspicam_node/image/compressed", (960, 1280), 1491682360),
        ("aruco_marker.bag", "/raspicam_node/image/compressed", (720, 1280), 1480460739),
        ("fiducial_board_611.bag", "raspicam_node/camera/image/compressed", (720, 1280), None),
    ],
)
def test_ros1_bag_jpeg(
    shared_data: Path, name: str, topic: str, shape: tuple[int, int], stamp_s: int | None
) -> None:
    path = shared_data / FIDUCIALS / name
    with open_source(path) as source:
        assert isinstance(source, RosbagsSource)
        assert pick_image_topic(source) == topic
        [msg] = frames(source, topic)
    assert (msg.kind, msg.encoding, msg.topic) == ("compressed", "jpg", topic)
    assert msg.data == jpeg_from_ros1_bag(path)
    gray = decode_gray(msg)
    assert gray.shape == shape
    assert np.array_equal(gray, imdecode_gray(jpeg_from_ros1_bag(path)))
    assert msg.header_stamp_ns is not None
    if stamp_s is not None:
        assert msg.header_stamp_ns // 1_000_000_000 == stamp_s


def test_relative_topic_with_or_without_slash(shared_data: Path) -> None:
    with open_source(shared_data / FIDUCIALS / "fiducial_board_611.bag") as source:
        want = "raspicam_node/camera/image/compressed"
        assert pick_image_topic(source, want) == want
        assert pick_image_topic(source, "/" + want) == want
        with pytest.raises(NoCameraError, match="not in the log"):
            pick_image_topic(source, "/camera/image")
        with pytest.raises(NoCameraError, match="CameraInfo, not an image"):
            pick_image_topic(source, "raspicam_node/camera/camera_info")


def test_ros1_channels(shared_data: Path) -> None:
    with open_source(shared_data / FIDUCIALS / "aruco_images.bag") as source:
        channels = {c.topic: c for c in source.channels()}
    assert channels["/raspicam_node/camera_info"].message_count == 15
    image = channels["/raspicam_node/image/compressed"]
    assert (image.message_count, image.is_image, image.message_encoding) == (1, True, "ros1")
    assert image.first_log_time_ns == image.last_log_time_ns is not None


# --- the real ROS 2 MCAP ------------------------------------------------------------------------


def raw_payloads(path: Path, topic: str) -> list[tuple[int, bytes]]:
    with path.open("rb") as file:
        reader = make_reader(file)
        return [(m.log_time, m.data) for _, _, m in reader.iter_messages(topics=[topic])]


def test_rerun_mcap_compressed_image(shared_data: Path) -> None:
    path = shared_data / RERUN
    [(log_time, payload)] = raw_payloads(path, "/compressed_image")
    start = payload.index(b"\xff\xd8\xff")  # the CDR uint8 sequence: u32 length, then bytes
    (length,) = struct.unpack_from("<I", payload, start - 4)
    jpeg = payload[start : start + length]
    assert length == 361_069
    with open_source(path) as source:
        assert isinstance(source, McapSource) and source.indexed
        [msg] = frames(source, "/compressed_image")
    assert (msg.log_time_ns, msg.encoding, msg.data) == (log_time, "jpeg", jpeg)
    assert msg.header_stamp_ns == 1757502238_482648699
    assert msg.publish_time_ns == log_time and msg.sequence == 0
    gray = decode_gray(msg)
    assert gray.shape == (480, 640)
    assert np.array_equal(gray, imdecode_gray(jpeg))


def test_rerun_mcap_rgb8_image(shared_data: Path) -> None:
    path = shared_data / RERUN
    [(_, payload)] = raw_payloads(path, "/image")
    size = 480 * 1920  # the data sequence is the last field: u32 length, then the bytes
    assert struct.unpack_from("<I", payload, len(payload) - size - 4) == (size,)
    rgb = np.frombuffer(payload[-size:], np.uint8).reshape(480, 640, 3)
    with open_source(path) as source:
        [msg] = frames(source, "/image")
    assert (msg.kind, msg.encoding, msg.width, msg.height, msg.step) == (
        "raw",
        "rgb8",
        640,
        480,
        1920,
    )
    assert msg.is_bigendian is False
    assert np.array_equal(decode_gray(msg), cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))


def test_rerun_mcap_channels(shared_data: Path) -> None:
    path = shared_data / RERUN
    counts: Counter[str] = Counter()
    times: dict[str, list[int]] = {}
    with path.open("rb") as file:
        for _, channel, message in make_reader(file).iter_messages(log_time_order=False):
            counts[channel.topic] += 1
            times.setdefault(channel.topic, []).append(message.log_time)
    with open_source(path) as source:
        channels = source.channels()
        assert [c.topic for c in image_channels(source)] == ["/compressed_image", "/image"]
        with pytest.raises(NoCameraError, match=r"2 image topics.*/compressed_image, /image"):
            pick_image_topic(source)
        assert pick_image_topic(source, "image") == "/image"
    assert len(channels) == 32 and sum(c.message_count for c in channels) == 194
    for channel in channels:
        assert channel.message_count == counts[channel.topic]
        assert channel.message_encoding == "cdr"
        if counts[channel.topic]:
            expected = (min(times[channel.topic]), max(times[channel.topic]))
            assert (channel.first_log_time_ns, channel.last_log_time_ns) == expected
        else:
            assert channel.first_log_time_ns is channel.last_log_time_ns is None
    by_topic = {c.topic: c for c in channels}
    assert by_topic["/temperature"].message_count == 0
    assert by_topic["/image"].message_type == "sensor_msgs/msg/Image"


def test_rerun_mcap_time_range(shared_data: Path) -> None:
    with open_source(shared_data / RERUN) as source:
        [msg] = frames(source, "/image")
        t = msg.log_time_ns
        assert len(frames(source, "/image", start_ns=t, end_ns=t + 1)) == 1
        assert len(frames(source, "/image", start_ns=t - 10**9)) == 1
        assert frames(source, "/image", start_ns=t + 1) == []
        assert frames(source, "/image", end_ns=t) == []
        assert frames(source, "/image", start_ns=t, end_ns=t) == []
        with pytest.raises(NoCameraError, match="'/imu' is not an image topic"):
            source.image_messages("/imu")


# --- logs without images ------------------------------------------------------------------------

TURTLESIM_COUNTS = {
    "/rosout": 10,
    "/turtle1/color_sensor": 1351,
    "/turtle2/color_sensor": 1344,
    "/tf_static": 1,
    "/turtle1/pose": 1344,
    "/turtle2/pose": 1344,
    "/tf": 2688,
    "/turtle1/cmd_vel": 357,
    "/turtle2/cmd_vel": 208,
}
TALKER_COUNTS = {"/topic": 10, "/rosout": 10, "/parameter_events": 0}


def assert_no_camera(source: Source, counts: dict[str, int]) -> None:
    channels = source.channels()
    assert {c.topic: c.message_count for c in channels} == counts
    assert not any(c.is_image for c in channels)
    assert image_channels(source) == []
    with pytest.raises(NoCameraError, match="no image topic"):
        pick_image_topic(source)
    # rosbags' messages(connections=[]) would yield every message: must be refused instead.
    with pytest.raises(NoCameraError):
        source.image_messages(channels[0].topic)


@pytest.mark.parametrize("name", ["example.bag", "example-bz2.bag", "example-lz4.bag"])
def test_turtlesim_bags(shared_data: Path, name: str) -> None:
    with open_source(shared_data / TURTLESIM / name) as source:
        assert_no_camera(source, TURTLESIM_COUNTS)
        assert sum(c.message_count for c in source.channels()) == 8647
        rosout = next(c for c in source.channels() if c.topic == "/rosout")
        assert rosout.message_type == "rosgraph_msgs/msg/Log"  # 3 connections, one topic


@pytest.mark.parametrize(
    ("relative", "kind"),
    [
        ("sqlite3_talker", RosbagsSource),
        ("mcap_talker", RosbagsSource),
        ("sqlite3_talker/talker.db3", RosbagsSource),
        ("mcap_talker/talker.mcap", McapSource),
    ],
)
def test_talker_bags(shared_data: Path, relative: str, kind: type) -> None:
    path = shared_data / TALKER / relative
    listing = sorted(p.name for p in path.parent.iterdir())
    with open_source(path) as source:
        assert isinstance(source, kind)
        assert_no_camera(source, TALKER_COUNTS)
    assert sorted(p.name for p in path.parent.iterdir()) == listing  # no sqlite journal left


def test_bare_db3_without_metadata(shared_data: Path, tmp_path: Path) -> None:
    bare = tmp_path / "talker.db3"
    bare.symlink_to(shared_data / TALKER / "sqlite3_talker" / "talker.db3")
    with open_source(bare) as source:
        assert_no_camera(source, TALKER_COUNTS)


def test_sources_do_not_modify_inputs(shared_data: Path) -> None:
    paths = [shared_data / FIDUCIALS / "aruco_marker.bag", shared_data / RERUN]
    before = [sha256(p) for p in paths]
    for path in paths:
        with open_source(path) as source:
            for channel in image_channels(source):
                for msg in source.image_messages(channel.topic):
                    decode_gray(msg)
    assert [sha256(p) for p in paths] == before


# --- not logs -----------------------------------------------------------------------------------


def test_not_a_log_file(shared_data: Path, tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="not a log file") as error:
        open_source(shared_data / "README.md")
    assert not isinstance(error.value, NoCameraError)
    fake = tmp_path / "fake.mcap"
    fake.write_text("not really an mcap")
    with pytest.raises(SourceError, match="not a log file"):
        open_source(fake)
    empty = tmp_path / "empty.bag"
    empty.touch()
    with pytest.raises(SourceError, match="not a log file"):
        open_source(empty)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="no such file"):
        open_source(tmp_path / "nothing.mcap")


def test_directory_without_metadata(shared_data: Path) -> None:
    with pytest.raises(SourceError, match=r"metadata\.yaml"):
        open_source(shared_data / "lip6_outdoor")


def test_a_ros1_bag_is_told_by_its_content_not_its_name(shared_data: Path, tmp_path: Path) -> None:
    original = shared_data / TURTLESIM / "example.bag"
    with open_source(original) as source:
        expected = source.channels()
    for name in ("example.rosbag", "example.mcap"):  # issue #21: .mcap was read as rosbag2
        renamed = tmp_path / name
        renamed.symlink_to(original)
        with open_source(renamed) as source:
            assert source.channels() == expected


# --- small MCAP files written here --------------------------------------------------------------

SEPARATOR = "=" * 80


def ros1_string(text: str) -> bytes:
    return struct.pack("<I", len(text)) + text.encode()


def ros1_header(seq: int, stamp_ns: int) -> bytes:
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    return struct.pack("<III", seq, sec, nsec) + ros1_string("cam")


ROS1_HEADER_DEF = f"{SEPARATOR}\nMSG: std_msgs/Header\nuint32 seq\ntime stamp\nstring frame_id\n"
ROS1_IMAGE_DEF = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
    "uint8 is_bigendian\nuint32 step\nuint8[] data\n" + ROS1_HEADER_DEF
)
ROS1_COMPRESSED_DEF = "std_msgs/Header header\nstring format\nuint8[] data\n" + ROS1_HEADER_DEF


def ros1_image(stamp_ns: int, bgr: np.ndarray, pad: int) -> bytes:
    height, width = bgr.shape[:2]
    rows = np.hstack([bgr.reshape(height, -1), np.zeros((height, pad), np.uint8)]).tobytes()
    return (
        ros1_header(0, stamp_ns)
        + struct.pack("<II", height, width)
        + ros1_string("bgr8")
        + struct.pack("<BI", 0, width * 3 + pad)
        + struct.pack("<I", len(rows))
        + rows
    )


def png(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", image)
    assert ok
    return data.tobytes()


def test_ros1_profile_mcap(tmp_path: Path) -> None:
    path = tmp_path / "ros1.mcap"
    bgr = np.random.default_rng(1).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    gray = np.arange(48, dtype=np.uint8).reshape(6, 8)
    with path.open("wb") as file:
        writer = Writer(file)
        writer.start(profile="ros1")
        raw_schema_id = writer.register_schema(
            "sensor_msgs/Image", "ros1msg", ROS1_IMAGE_DEF.encode()
        )
        png_schema_id = writer.register_schema(
            "sensor_msgs/CompressedImage", "ros1msg", ROS1_COMPRESSED_DEF.encode()
        )
        raw_channel = writer.register_channel("/cam/raw", "ros1", raw_schema_id)
        png_channel = writer.register_channel("/cam/png", "ros1", png_schema_id)
        writer.add_message(raw_channel, 100, ros1_image(5_000_000_007, bgr, pad=3), 100)
        payload = ros1_header(9, 6_000_000_000) + ros1_string("png")
        payload += struct.pack("<I", len(png(gray))) + png(gray)
        writer.add_message(png_channel, 200, payload, 200, sequence=4)
        writer.finish()
    with open_source(path) as source:
        assert {c.topic: c.message_encoding for c in image_channels(source)} == {
            "/cam/raw": "ros1",
            "/cam/png": "ros1",
        }
        [raw] = frames(source, "/cam/raw")
        [compressed] = frames(source, "/cam/png")
    assert (raw.header_stamp_ns, raw.step) == (5_000_000_007, 24)
    assert np.array_equal(decode_gray(raw), cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    assert (compressed.header_stamp_ns, compressed.sequence) == (6_000_000_000, 4)
    assert np.array_equal(decode_gray(compressed), gray)


def cdr_string(body: bytearray, text: str) -> None:
    encoded = text.encode() + b"\0"
    body += struct.pack("<I", len(encoded)) + encoded
    body += b"\0" * (-len(body) % 4)  # the next u32 is 4-aligned


def cdr_compressed_image(stamp_ns: int, fmt: str, data: bytes) -> bytes:
    """sensor_msgs/msg/CompressedImage in little-endian CDR, serialized by hand."""
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    body = bytearray(struct.pack("<iI", sec, nanosec))
    cdr_string(body, "cam")
    cdr_string(body, fmt)
    body += struct.pack("<I", len(data)) + data
    return b"\x00\x01\x00\x00" + bytes(body)


ROS2_COMPRESSED_MSG = (
    "std_msgs/Header header\nstring format\nuint8[] data\n"
    f"{SEPARATOR}\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
    f"{SEPARATOR}\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
)
ROS2_COMPRESSED_IDL = f"""{SEPARATOR}
IDL: sensor_msgs/msg/CompressedImage
module sensor_msgs {{ module msg {{
  struct CompressedImage {{
    std_msgs::msg::Header header;
    string format;
    sequence<uint8> data;
  }};
}}; }};
{SEPARATOR}
IDL: std_msgs/msg/Header
module std_msgs {{ module msg {{
  struct Header {{ builtin_interfaces::msg::Time stamp; string frame_id; }};
}}; }};
{SEPARATOR}
IDL: builtin_interfaces/msg/Time
module builtin_interfaces {{ module msg {{
  struct Time {{ int32 sec; uint32 nanosec; }};
}}; }};
"""


@pytest.mark.parametrize(
    ("schema_encoding", "schema"),
    [("ros2msg", ROS2_COMPRESSED_MSG), ("ros2idl", ROS2_COMPRESSED_IDL)],
)
def test_ros2_profile_mcap(tmp_path: Path, schema_encoding: str, schema: str) -> None:
    path = tmp_path / "ros2.mcap"
    images = [np.full((4, 5), 10 * i, np.uint8) for i in range(3)]
    with path.open("wb") as file:
        writer = Writer(file, compression=CompressionType.LZ4)
        writer.start(profile="ros2")
        schema_id = writer.register_schema(
            "sensor_msgs/msg/CompressedImage", schema_encoding, schema.encode()
        )
        channel = writer.register_channel("/cam", "cdr", schema_id)
        for i, image in enumerate(images):
            writer.add_message(channel, 1000 + i, cdr_compressed_image(i, "png", png(image)), 0)
        writer.add_message(channel, 2000, b"\x00\x01\x00\x00\x05", 0)  # truncated message
        writer.finish()
    with open_source(path) as source:
        messages = frames(source, "/cam")
    assert [m.header_stamp_ns for m in messages[:3]] == [0, 1, 2]
    for msg, image in zip(messages, images, strict=False):
        assert np.array_equal(decode_gray(msg), image)
    # A corrupt message comes through (the iteration goes on) and fails only when decoded.
    assert messages[3].log_time_ns == 2000 and messages[3].decode_error
    with pytest.raises(ImageDecodeError, match="cannot deserialize"):
        decode_gray(messages[3])


def write_foxglove_protobuf(path: Path, images: list[np.ndarray]) -> None:
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
    from mcap_protobuf.writer import Writer as ProtobufWriter

    with path.open("wb") as file:
        writer = ProtobufWriter(file, chunk_size=200)  # several chunks, to exercise seeking
        for i, image in enumerate(images):
            t = 10 * (i + 1)
            compressed = CompressedImage(frame_id="cam", format="png", data=png(image))
            compressed.timestamp.FromNanoseconds(t + 5)
            writer.write_message("/png", compressed, log_time=t, publish_time=t + 1, sequence=i)
            words = image.astype("<u2") * 257  # mono16 little-endian: high byte == image
            raw = RawImage(
                frame_id="cam", width=5, height=4, encoding="mono16", step=12,
                data=np.hstack([words.view(np.uint8), np.zeros((4, 2), np.uint8)]).tobytes(),
            )  # fmt: skip
            raw.timestamp.FromNanoseconds(t + 7)
            writer.write_message("/raw", raw, log_time=t + 2, publish_time=t + 2)
        writer.finish()


def test_foxglove_protobuf_mcap_and_time_range(tmp_path: Path) -> None:
    path = tmp_path / "foxglove.mcap"
    images = [np.random.default_rng(i).integers(0, 256, (4, 5), dtype=np.uint8) for i in range(6)]
    write_foxglove_protobuf(path, images)
    with open_source(path) as source:
        channels = {c.topic: c for c in source.channels()}
        assert channels["/png"].message_type == "foxglove.CompressedImage"
        assert (channels["/raw"].message_count, channels["/raw"].message_encoding) == (
            6,
            "protobuf",
        )
        assert (channels["/png"].first_log_time_ns, channels["/png"].last_log_time_ns) == (10, 60)
        assert isinstance(source, McapSource) and source.indexed
        pngs = frames(source, "/png")
        raws = frames(source, "/raw")
        window = frames(source, "/png", start_ns=20, end_ns=50)
    assert [m.log_time_ns for m in pngs] == [10, 20, 30, 40, 50, 60]
    assert [(m.header_stamp_ns, m.publish_time_ns, m.sequence) for m in pngs[:2]] == [
        (15, 11, 0),
        (25, 21, 1),
    ]
    assert [m.header_stamp_ns for m in raws] == [17, 27, 37, 47, 57, 67]
    for png_msg, raw_msg, image in zip(pngs, raws, images, strict=True):
        assert np.array_equal(decode_gray(png_msg), image)
        assert np.array_equal(decode_gray(raw_msg), image)
    assert [m.log_time_ns for m in window] == [20, 30, 40]
    assert all(np.array_equal(decode_gray(m), images[i + 1]) for i, m in enumerate(window))


def test_foxglove_json_mcap(tmp_path: Path) -> None:
    path = tmp_path / "json.mcap"
    image = np.arange(20, dtype=np.uint8).reshape(4, 5) * 12
    rgb = np.dstack([image, image // 2, 255 - image])
    with path.open("wb") as file:
        writer = Writer(file)
        writer.start()
        png_schema = writer.register_schema("foxglove.CompressedImage", "jsonschema", b"{}")
        raw_schema = writer.register_schema("foxglove.RawImage", "jsonschema", b"{}")
        png_channel = writer.register_channel("/png", "json", png_schema)
        raw_channel = writer.register_channel("/raw", "json", raw_schema)
        compressed = {
            "timestamp": {"sec": 3, "nsec": 4},
            "frame_id": "cam",
            "format": "png",
            "data": base64.b64encode(png(image)).decode(),
        }
        raw = {
            "timestamp": {"sec": 5, "nsec": 6},
            "frame_id": "cam",
            "width": 5,
            "height": 4,
            "encoding": "rgb8",
            "step": 15,
            "data": base64.b64encode(rgb.tobytes()).decode(),
        }
        writer.add_message(png_channel, 1, json.dumps(compressed).encode(), 1)
        writer.add_message(raw_channel, 2, json.dumps(raw).encode(), 2)
        writer.add_message(raw_channel, 3, b"{not json", 3)
        writer.finish()
    with open_source(path) as source:
        assert {c.topic: c.message_encoding for c in image_channels(source)} == {
            "/png": "json",
            "/raw": "json",
        }
        [png_msg] = frames(source, "/png")
        raw_msg, broken = frames(source, "/raw")
    assert png_msg.header_stamp_ns == 3_000_000_004
    assert np.array_equal(decode_gray(png_msg), image)
    assert raw_msg.header_stamp_ns == 5_000_000_006
    assert np.array_equal(decode_gray(raw_msg), cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    assert broken.decode_error is not None and "JSONDecodeError" in broken.decode_error


def write_unindexed(path: Path, log_times: list[int], *, chunked: bool) -> None:
    with path.open("wb") as file:
        if chunked:  # chunks, but no chunk or message indexes in the summary
            writer = Writer(file, chunk_size=100, index_types=IndexType.NONE)
        else:  # no chunks and no summary section at all
            writer = Writer(
                file,
                use_chunking=False,
                index_types=IndexType.NONE,
                use_statistics=False,
                repeat_channels=False,
                repeat_schemas=False,
                use_summary_offsets=False,
            )
        writer.start()
        schema = writer.register_schema("foxglove.CompressedImage", "jsonschema", b"{}")
        channel = writer.register_channel("/cam", "json", schema)
        other = writer.register_channel("/other", "json", 0)
        for t in log_times:
            image = np.full((2, 3), t, np.uint8)
            payload = {"format": "png", "data": base64.b64encode(png(image)).decode()}
            writer.add_message(channel, t, json.dumps(payload).encode(), t)
            writer.add_message(other, t, b"{}", t)
        writer.finish()


@pytest.mark.parametrize("chunked", [False, True])
def test_unindexed_mcap(tmp_path: Path, chunked: bool) -> None:
    path = tmp_path / "unindexed.mcap"
    write_unindexed(path, [30, 10, 20, 50, 40, 60], chunked=chunked)
    with path.open("rb") as file:
        summary = make_reader(file).get_summary()
    assert summary is None or not summary.chunk_indexes
    with open_source(path) as source:
        assert isinstance(source, McapSource) and not source.indexed
        channels = {c.topic: c for c in source.channels()}
        all_frames = frames(source, "/cam")
        window = frames(source, "/cam", start_ns=20, end_ns=50)
    cam = channels["/cam"]
    assert (cam.message_count, cam.first_log_time_ns, cam.last_log_time_ns) == (6, 10, 60)
    assert (cam.is_image, channels["/other"].is_image, channels["/other"].message_count) == (
        True,
        False,
        6,
    )
    assert [m.log_time_ns for m in all_frames] == [10, 20, 30, 40, 50, 60]
    assert [int(decode_gray(m)[0, 0]) for m in all_frames] == [10, 20, 30, 40, 50, 60]
    assert [m.log_time_ns for m in window] == [20, 30, 40]
    assert all(m.header_stamp_ns is None for m in all_frames)  # no timestamp field written


def test_reorder_window_is_bounded() -> None:
    def order(times: list[int], window: int) -> list[int]:
        records = [(None, None, SimpleNamespace(log_time=t)) for t in times]
        return [r[2].log_time for r in in_log_time_order(records, window)]  # type: ignore[arg-type]

    assert order([3, 1, 2, 5, 4, 6], window=2) == [1, 2, 3, 4, 5, 6]
    assert order([9, 1, 2, 3, 0], window=2) == [1, 2, 0, 3, 9]  # 0 came more than 2 late


def test_truncated_mcap_is_a_source_error(tmp_path: Path) -> None:
    path = tmp_path / "foxglove.mcap"
    write_foxglove_protobuf(path, [np.zeros((4, 5), np.uint8)] * 6)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size * 2 // 3])
    with open_source(cut) as source, pytest.raises(SourceError, match="truncated"):
        source.channels()


def test_unsupported_message_encoding(tmp_path: Path) -> None:
    path = tmp_path / "flatbuffer.mcap"
    with path.open("wb") as file:
        writer = Writer(file)
        writer.start()
        schema = writer.register_schema("foxglove.CompressedImage", "flatbuffer", b"\0")
        channel = writer.register_channel("/cam", "flatbuffer", schema)
        writer.add_message(channel, 1, b"\0\0\0\0", 1)
        writer.finish()
    with open_source(path) as source:
        assert pick_image_topic(source) == "/cam"
        with pytest.raises(SourceError, match=r"'flatbuffer'.*not supported"):
            frames(source, "/cam")
