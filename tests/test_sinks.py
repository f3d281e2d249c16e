"""The annotated-MCAP writer: lossless copies of real logs, our channels, atomic output."""

from __future__ import annotations

import hashlib
import json
import math
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Reader as Ros1Reader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.annotations.records import (
    ACCEPTED,
    LOOP_CLOSURE,
    REJECTED,
    SEQUENCE,
    SKIPPED,
    FrameTimes,
    LoopClosureRecord,
    TimedMessage,
)
from doseqslam_logs.annotations.schema_files import read_schema
from doseqslam_logs.annotations.writer import loop_closure_messages, sequence_messages
from doseqslam_logs.detector.events import Candidate, SequenceDecision
from doseqslam_logs.errors import OutputError, SourceError
from doseqslam_logs.sinks.encoders import ENCODERS, Ros1Encoder, Ros2Encoder, encoder_for_profile
from doseqslam_logs.sinks.mcap_writer import Annotations, write_annotated_mcap
from doseqslam_logs.sources.formats import plan_copy

REPO = Path(__file__).resolve().parents[1]
ROS2_MCAP = "rosbag2_mcap_rerun_sensor_msgs/rosbag2_2025_09_10-13_03_56_0.mcap"
ROS1_BAG = "ros1_bags_fiducials_raspicam/aruco_images.bag"
ROSBAG2_DB3 = "ros2_bags_rosbag2_talker/sqlite3_talker"
ROSBAG2_MCAP_DIR = "ros2_bags_rosbag2_talker/mcap_talker"
OURS = ("/doseqslam/loop_closures", "/doseqslam/sequences", "/doseqslam/candidates")
FRAMES = 40
STEP_NS = 100_000_000  # 10 frames a second
PARAMETERS_HASH = "0123456789abcdef"


# --- annotations --------------------------------------------------------------------------


def make_decisions(method: str = "doseqslam") -> list[SequenceDecision]:
    """No database, rejected with candidates (no second score), accepted."""

    def candidates(first: int, last: int, match: int) -> tuple[Candidate, ...]:
        return tuple(
            Candidate(q, match + q - first, 0, 0, 0.01 * (q - first))
            for q in range(first, last + 1)
        )

    common: dict[str, Any] = {"threshold": 0.75, "method": method}
    return [
        SequenceDecision(0, 0, 9, 0, 9, 0, None, None, None, None, 1.0, None, 0.5, 0.9,
                         accepted=False, candidates=(), **common),
        SequenceDecision(1, 10, 19, 10, 19, 5, 0, 1.0, 0.4, None, 0.8, 1.0, 0.3, 0.85,
                         accepted=False, candidates=candidates(10, 19, 0), **common),
        SequenceDecision(2, 30, 34, 30, 34, 20, 2, 1.1, 0.2, 0.5, 0.4, 0.3, None, 0.3,
                         accepted=True, candidates=candidates(30, 34, 2), **common),
    ]  # fmt: skip


def make_frame_times(start_ns: int) -> FrameTimes:
    """Frames 0-19 without header stamp, 20-39 stamped 5 ms before their log time."""
    log_times = [start_ns + i * STEP_NS for i in range(FRAMES)]
    stamps = [-1] * 20 + [t - 5_000_000 for t in log_times[20:]]
    return FrameTimes(log_times, stamps)


def make_annotations(start_ns: int, tag: str = "first") -> Annotations:
    metadata = {"tool_version": "0.1.0", "run": tag, "image_topic": "/image"}
    return Annotations.from_decisions(
        make_decisions(), make_frame_times(start_ns), "doseqslam", PARAMETERS_HASH, metadata
    )


# --- reading outputs ----------------------------------------------------------------------


def read_mcap(path: Path) -> dict[str, Any]:
    """Every record of an MCAP file, as mcap's own reader yields them."""
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None
        messages = [
            (channel.topic, m.log_time, m.publish_time, m.sequence, m.data)
            for _, channel, m in reader.iter_messages(log_time_order=False)
        ]
        return {
            "header": reader.get_header(),
            "schemas": summary.schemas,
            "channels": summary.channels,
            "messages": messages,
            "attachments": [
                (a.name, a.media_type, a.create_time, a.log_time, a.data)
                for a in reader.iter_attachments()
            ],
            "metadata": [(m.name, m.metadata) for m in reader.iter_metadata()],
        }


def channel_records(content: dict[str, Any], ours: bool = False) -> Counter[tuple[Any, ...]]:
    """Channels with their schema's name, encoding and data (ids may be renumbered)."""
    found: Counter[tuple[Any, ...]] = Counter()
    for channel in content["channels"].values():
        if channel.topic.startswith("/doseqslam/") != ours:
            continue
        schema = content["schemas"].get(channel.schema_id)
        described = (schema.name, schema.encoding, schema.data) if schema else None
        metadata = tuple(sorted(channel.metadata.items()))
        found[(channel.topic, channel.message_encoding, metadata, described)] += 1
    return found


def input_messages(content: dict[str, Any]) -> list[tuple[Any, ...]]:
    return sorted(m for m in content["messages"] if not m[0].startswith("/doseqslam/"))


def assert_copied(input_content: dict[str, Any], output: dict[str, Any]) -> None:
    assert output["header"].profile == input_content["header"].profile
    assert channel_records(output) == channel_records(input_content)
    schemas_in = Counter((s.name, s.encoding, s.data) for s in input_content["schemas"].values())
    schemas_out = Counter(
        (s.name, s.encoding, s.data)
        for s in output["schemas"].values()
        if not s.name.startswith("doseqslam_msgs/")
    )
    assert schemas_out == schemas_in
    assert input_messages(output) == input_messages(input_content)
    ours = [a for a in output["attachments"] if a[0] == "doseqslam/frame_times"]
    assert len(ours) == 1  # our frame-times attachment, replaced when re-annotating
    theirs = [a for a in input_content["attachments"] if a[0] != "doseqslam/frame_times"]
    assert [a for a in output["attachments"] if a[0] != "doseqslam/frame_times"] == theirs
    kept = [m for m in input_content["metadata"] if m[0] != "doseqslam"]
    assert [m for m in output["metadata"] if m[0] != "doseqslam"] == kept


def our_messages(path: Path) -> dict[str, list[Any]]:
    """Our messages decoded with mcap_ros2 (ROS 2 outputs), by topic, with their log times."""
    found: dict[str, list[Any]] = {topic: [] for topic in OURS}
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for _, channel, message, decoded in reader.iter_decoded_messages(topics=list(OURS)):
            found[channel.topic].append((message.log_time, decoded))
    return found


def sha256(path: Path) -> str:
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    digest = hashlib.sha256()
    for file in files:
        digest.update(file.name.encode() + file.read_bytes())
    return digest.hexdigest()


def leftovers(folder: Path, keep: set[str]) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name not in keep)


# --- a small non-ROS MCAP -----------------------------------------------------------------


def write_json_mcap(path: Path, profile: str, topic_prefix: str = "/") -> int:
    """A foxglove-style JSON log with an attachment, metadata, an unused schema and a channel
    without schema; returns its first log time."""
    start = 1_700_000_000_000_000_000
    with path.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile=profile, library="test")
        schema = writer.register_schema(
            "foxglove.Log", "jsonschema", b'{"type":"object","properties":{"message":{}}}'
        )
        writer.register_schema("unused.Schema", "jsonschema", b'{"type":"object"}')
        logs = writer.register_channel(topic_prefix + "log", "json", schema, {"origin": "test"})
        raw = writer.register_channel(topic_prefix + "raw", "json", 0)
        writer.add_attachment(5, start, "calibration.yaml", "text/yaml", b"fx: 500\n")
        writer.add_metadata("robot", {"name": "r2", "site": "lab"})
        for i in range(50):
            data = json.dumps({"message": f"tick {i}"}).encode()
            writer.add_message(logs, start + i * STEP_NS, data, start + i * STEP_NS + 1, i)
            writer.add_message(raw, start + i * STEP_NS + 7, b"{}", start + i * STEP_NS + 7, i)
        writer.finish()  # type: ignore[no-untyped-call]
    return start


# --- a tiny JSON Schema checker (the jsonschema package is not a dependency) --------------


def check_json_schema(value: Any, schema: dict[str, Any], root: dict[str, Any]) -> None:
    """Checks the keywords our schema files use: $ref, type, properties, required,
    additionalProperties, items, minimum, maximum."""
    if "$ref" in schema:
        name = schema["$ref"].removeprefix("#/$defs/")
        check_json_schema(value, root["$defs"][name], root)
    types = schema.get("type")
    if types is not None:
        allowed = types if isinstance(types, list) else [types]
        assert any(json_type_matches(value, t) for t in allowed), (value, allowed)
    if isinstance(value, dict):
        assert set(schema.get("required", [])) <= set(value)
        properties = schema.get("properties", {})
        if schema.get("additionalProperties") is False:
            assert set(value) <= set(properties), set(value) - set(properties)
        for name, item in value.items():
            if name in properties:
                check_json_schema(item, properties[name], root)
    if isinstance(value, list) and "items" in schema:
        for item in value:
            check_json_schema(item, schema["items"], root)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        assert value >= schema.get("minimum", -math.inf)
        assert value <= schema.get("maximum", math.inf)


def json_type_matches(value: Any, json_type: str) -> bool:
    checks: dict[str, Any] = {
        "null": lambda v: v is None,
        "boolean": lambda v: isinstance(v, bool),
        "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
        "number": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
        "string": lambda v: isinstance(v, str),
        "array": lambda v: isinstance(v, list),
        "object": lambda v: isinstance(v, dict),
    }
    return bool(checks[json_type](value))


def all_numbers(value: Any) -> list[float]:
    if isinstance(value, dict):
        return [n for item in value.values() for n in all_numbers(item)]
    if isinstance(value, list):
        return [n for item in value for n in all_numbers(item)]
    return [value] if isinstance(value, (int, float)) and not isinstance(value, bool) else []


# --- message dicts and schema files -------------------------------------------------------


def msg_fields(text: str) -> list[tuple[str, str]]:
    """(type, name) of every field of a .msg text."""
    fields = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            kind, name = line.split()[:2]
            fields.append((kind, name))
    return fields


@pytest.mark.parametrize("name", ["LoopClosure", "Sequence"])
def test_schema_files_agree_with_the_message_dicts(name: str) -> None:
    ros2 = msg_fields(read_schema(f"ros2/{name}.msg"))
    ros1 = msg_fields(read_schema(f"ros1/{name}.msg"))
    schema = json.loads(read_schema(f"json/{name}.json"))
    names = [n for _, n in ros2]
    assert [n for _, n in ros1] == names
    assert list(schema["properties"]) == names
    # Every field is required but the floats, which the JSON profile omits when NaN.
    floats = {n for kind, n in ros2 if kind.startswith("float64")}
    assert schema["required"] == [n for n in names if n not in floats]
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    # The two ROS flavours differ only in how they spell a time.
    for (type2, _), (type1, _) in zip(ros2, ros1, strict=True):
        assert type1 == ("time" if type2 == "builtin_interfaces/Time" else type2)
    messages = loop_closure_messages if name == "LoopClosure" else sequence_messages
    built = messages(make_decisions(), make_frame_times(0), "doseqslam", PARAMETERS_HASH)
    assert built and all(list(m.fields) == names for m in built)
    for message in built:
        check_json_schema(json.loads(encoder_for_profile("").encode(message.type, message.fields)),
                          schema, schema)  # fmt: skip


def test_message_values() -> None:
    frame_times = make_frame_times(1_000 * STEP_NS)
    sequences = sequence_messages(make_decisions(), frame_times, "doseqslam", PARAMETERS_HASH)
    closures = loop_closure_messages(make_decisions(), frame_times, "doseqslam", PARAMETERS_HASH)
    empty, rejected, accepted = (m.fields for m in sequences)
    assert not empty["has_candidate"] and empty["best_start"] == -1
    assert math.isnan(empty["best_score"]) and math.isnan(empty["gamma_previous"])
    assert empty["candidate_query_indices"] == [] and empty["database_size"] == 0
    assert rejected["candidate_query_indices"] == list(range(10, 20))
    assert rejected["candidate_match_indices"] == list(range(10))
    assert math.isnan(rejected["second_score"]) and not rejected["accepted"]
    assert accepted["accepted"] and math.isnan(accepted["gamma_next"])
    assert sequences[2].log_time_ns == frame_times.log_time(34)
    # Only the accepted sequence reports loop closures: one per frame, query log time.
    assert [m.fields["query_index"] for m in closures] == [30, 31, 32, 33, 34]
    first = closures[0].fields
    assert closures[0].log_time_ns == frame_times.log_time(30)
    assert first["match_index"] == 2 and not first["match_has_stamp"]
    assert first["query_has_stamp"] and first["match_stamp"] == {"sec": 0, "nsec": 0}
    assert (first["match_first_index"], first["match_last_index"]) == (2, 6)
    assert (first["sequence_first_index"], first["sequence_last_index"]) == (30, 34)
    stamp = frame_times.stamp(30)
    assert stamp is not None
    assert first["query_stamp"] == {"sec": stamp // 10**9, "nsec": stamp % 10**9}


def test_frame_times_and_decisions_are_checked() -> None:
    with pytest.raises(ValueError):
        FrameTimes([1, 2, 3], [1, 2])
    with pytest.raises(ValueError):
        FrameTimes([1, 2], [-2, 0])
    short = FrameTimes.from_pairs([(10, None), (20, 15)])
    assert short.stamp(0) is None and short.stamp(1) == 15 and len(short) == 2
    with pytest.raises(ValueError, match="frame index"):
        sequence_messages(make_decisions(), short, "doseqslam", PARAMETERS_HASH)
    with pytest.raises(ValueError, match="seqslam"):
        sequence_messages(make_decisions(), make_frame_times(0), "seqslam", PARAMETERS_HASH)


def test_encoders_registry_and_ros_definitions() -> None:
    assert type(encoder_for_profile("ros2")) is Ros2Encoder
    assert type(encoder_for_profile("ros1")) is Ros1Encoder
    assert encoder_for_profile("foxglove").message_encoding == "json"
    assert set(ENCODERS) == {"ros1", "ros2", ""}
    ros2 = Ros2Encoder()
    data = ros2.schema_data(SEQUENCE).decode()
    assert data.startswith(read_schema("ros2/Sequence.msg"))
    assert data.endswith("=" * 80 + "\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n")
    with pytest.raises(ValueError, match="missing fields"):
        ros2.encode(LOOP_CLOSURE, {"query_index": 1})
    ros1 = Ros1Encoder()
    assert ros1.schema_data(LOOP_CLOSURE).decode() == read_schema("ros1/LoopClosure.msg")
    assert len(ros1.md5sum(LOOP_CLOSURE)) == 32


# --- ROS 2 MCAP ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ros2_output(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    source = shared_data / ROS2_MCAP
    before = sha256(source)
    output = tmp_path_factory.mktemp("ros2") / "annotated.mcap"
    start = min(m[1] for m in read_mcap(source)["messages"])
    summary = write_annotated_mcap(source, output, make_annotations(start))
    assert summary.copied_messages == 194 and summary.profile == "ros2"
    assert summary.written == {OURS[0]: 5, OURS[1]: 3, OURS[2]: 0}
    assert sha256(source) == before  # the input is never modified
    return output


def test_ros2_mcap_keeps_every_input_record(shared_data: Path, ros2_output: Path) -> None:
    source = read_mcap(shared_data / ROS2_MCAP)
    output = read_mcap(ros2_output)
    assert_copied(source, output)
    assert ("rosbag2", {"ROS_DISTRO": "humble"}) in output["metadata"]
    assert output["metadata"][-1] == (
        "doseqslam", {"tool_version": "0.1.0", "run": "first", "image_topic": "/image"}
    )  # fmt: skip


def test_ros2_mcap_our_channels_decode_with_mcap_ros2(shared_data: Path, ros2_output: Path) -> None:
    output = read_mcap(ros2_output)
    ours = channel_records(output, ours=True)
    assert {(k[0], k[1], k[3][0], k[3][1]) for k in ours} == {
        (OURS[0], "cdr", "doseqslam_msgs/msg/LoopClosure", "ros2msg"),
        (OURS[1], "cdr", "doseqslam_msgs/msg/Sequence", "ros2msg"),
        (OURS[2], "cdr", "doseqslam_msgs/msg/LoopClosure", "ros2msg"),
    }
    start = min(m[1] for m in read_mcap(shared_data / ROS2_MCAP)["messages"])
    decoded = our_messages(ros2_output)
    closures, sequences = decoded[OURS[0]], decoded[OURS[1]]
    assert [t for t, _ in closures] == [start + i * STEP_NS for i in range(30, 35)]
    assert [m.query_index for _, m in closures] == [30, 31, 32, 33, 34]
    assert closures[0][1].match_log_time.sec == (start + 2 * STEP_NS) // 10**9
    assert closures[0][1].parameters_hash == PARAMETERS_HASH
    assert [t for t, _ in sequences] == [start + i * STEP_NS for i in (9, 19, 34)]
    assert list(sequences[1][1].candidate_match_indices) == list(range(10))
    assert sequences[0][1].best_start == -1 and math.isnan(sequences[0][1].best_score)


def test_ros2_mcap_output_opens_with_rosbags(ros2_output: Path) -> None:
    # rosbags reads a lone .mcap file as a rosbag2 storage, with types from embedded msgdefs.
    with AnyReader([ros2_output]) as reader:
        assert len(list(reader.messages())) == 194 + 8
        ours = [c for c in reader.connections if c.topic in OURS]
        decoded: list[Any] = [
            reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(ours)
        ]
    closures = [m for m in decoded if m.__msgtype__ == "doseqslam_msgs/msg/LoopClosure"]
    assert [m.query_index for m in closures] == [30, 31, 32, 33, 34]
    sequences = [m for m in decoded if m.__msgtype__ == "doseqslam_msgs/msg/Sequence"]
    assert [m.sequence_id for m in sequences] == [0, 1, 2]
    assert list(sequences[2].candidate_differences) == pytest.approx([0, 0.01, 0.02, 0.03, 0.04])


def test_ros2_mcap_output_is_deterministic(
    shared_data: Path, ros2_output: Path, tmp_path: Path
) -> None:
    start = min(m[1] for m in read_mcap(shared_data / ROS2_MCAP)["messages"])
    again = tmp_path / "again.mcap"
    write_annotated_mcap(shared_data / ROS2_MCAP, again, make_annotations(start))
    assert again.read_bytes() == ros2_output.read_bytes()


def test_annotating_again_replaces_our_channels(
    shared_data: Path, ros2_output: Path, tmp_path: Path
) -> None:
    start = min(m[1] for m in read_mcap(shared_data / ROS2_MCAP)["messages"])
    second = tmp_path / "second.mcap"
    # Shifted by one frame, so that the new content is told apart from the old.
    summary = write_annotated_mcap(ros2_output, second, make_annotations(start + STEP_NS, "2nd"))
    assert summary.replaced_topics == sorted(OURS)
    output = read_mcap(second)
    assert_copied(read_mcap(shared_data / ROS2_MCAP), output)
    assert sorted(c.topic for c in output["channels"].values() if c.topic in OURS) == sorted(OURS)
    names = [s.name for s in output["schemas"].values() if s.name.startswith("doseqslam_msgs")]
    assert sorted(names) == ["doseqslam_msgs/msg/LoopClosure", "doseqslam_msgs/msg/Sequence"]
    assert [m for m in output["metadata"] if m[0] == "doseqslam"] == [
        ("doseqslam", {"tool_version": "0.1.0", "run": "2nd", "image_topic": "/image"})
    ]
    closures = our_messages(second)[OURS[0]]
    assert [t for t, _ in closures] == [start + (i + 1) * STEP_NS for i in range(30, 35)]


@pytest.mark.parametrize("source_name", [ROS2_MCAP, ROS1_BAG, ROSBAG2_DB3])
def test_sidecar_holds_only_ours(shared_data: Path, tmp_path: Path, source_name: str) -> None:
    output = tmp_path / "sidecar.mcap"
    summary = write_annotated_mcap(
        shared_data / source_name, output, make_annotations(0), sidecar=True
    )
    assert summary.copied_messages == 0
    content = read_mcap(output)
    assert sorted(c.topic for c in content["channels"].values()) == sorted(OURS)
    assert Counter(m[0] for m in content["messages"]) == {OURS[0]: 5, OURS[1]: 3}
    assert [m[0] for m in content["metadata"]] == ["doseqslam"]
    assert content["header"].profile == plan_copy(shared_data / source_name).profile


def with_verdicts(annotations: Annotations, verdicts: dict[int, str]) -> Annotations:
    """The annotations with each pair's verification: `verdicts` by query index, else
    accepted."""
    messages = [
        TimedMessage(
            replace(m.record, verification=verdicts.get(m.record.query.index, ACCEPTED)),
            m.log_time_ns,
        )
        if isinstance(m.record, LoopClosureRecord)
        else m
        for m in annotations.messages
    ]
    return replace(annotations, messages=messages)


@pytest.mark.parametrize("source_name", [ROS2_MCAP, ROS1_BAG, "json"])
def test_pairs_not_reported_are_written_on_the_candidates_topic(
    shared_data: Path, tmp_path: Path, source_name: str
) -> None:
    source = shared_data / source_name
    if source_name == "json":
        write_json_mcap(source := tmp_path / "log.mcap", "foxglove")
    verdicts = {31: REJECTED, 33: SKIPPED}
    output = tmp_path / "sidecar.mcap"
    annotations = with_verdicts(make_annotations(0), verdicts)
    summary = write_annotated_mcap(source, output, annotations, sidecar=True)
    assert summary.written == {OURS[0]: 3, OURS[1]: 3, OURS[2]: 2}
    content = read_mcap(output)
    channels = {c.topic: c for c in content["channels"].values()}
    assert channels[OURS[0]].schema_id == channels[OURS[2]].schema_id  # one LoopClosure schema
    by_topic = {topic: [m[1] for m in content["messages"] if m[0] == topic] for topic in OURS}
    assert by_topic[OURS[0]] == [30 * STEP_NS, 32 * STEP_NS, 34 * STEP_NS]
    assert by_topic[OURS[2]] == [31 * STEP_NS, 33 * STEP_NS]
    # Read back, the two topics are one list again, in query order, verdicts as written.
    log = read_annotations(output)
    assert [(lc.query.index, lc.verification) for lc in log.loop_closures] == [
        (30, ACCEPTED), (31, REJECTED), (32, ACCEPTED), (33, SKIPPED), (34, ACCEPTED)
    ]  # fmt: skip
    assert [lc.query.index for lc in log.reported_loop_closures] == [30, 32, 34]


# --- ROS 1 bag ----------------------------------------------------------------------------


def test_ros1_bag_copied_losslessly(shared_data: Path, tmp_path: Path) -> None:
    source = shared_data / ROS1_BAG
    before = sha256(source)
    with Ros1Reader(source) as bag:
        connections = {c.id: c for c in bag.connections}
        expected = sorted(
            (connections[c.id].topic, t, t, 0, bytes(raw)) for c, t, raw in bag.messages()
        )
        start = bag.start_time
    output = tmp_path / "ros1.mcap"
    summary = write_annotated_mcap(source, output, make_annotations(start))
    assert summary.input_kind == "ros1-bag" and summary.copied_messages == len(expected) == 16
    assert sha256(source) == before
    content = read_mcap(output)
    assert content["header"].profile == "ros1"
    assert input_messages(content) == expected
    for channel in content["channels"].values():
        schema = content["schemas"][channel.schema_id]
        assert channel.message_encoding == "ros1" and schema.encoding == "ros1msg"
        if channel.topic not in OURS:
            connection = next(c for c in connections.values() if c.topic == channel.topic)
            assert schema.data.decode() == connection.msgdef.data
            assert schema.name == connection.msgtype.replace("/msg/", "/")
            assert channel.metadata["md5sum"] == connection.digest


def test_ros1_bag_our_messages_deserialize_with_rosbags(shared_data: Path, tmp_path: Path) -> None:
    output = tmp_path / "ros1.mcap"
    write_annotated_mcap(shared_data / ROS1_BAG, output, make_annotations(10**18))
    content = read_mcap(output)
    typestore = get_typestore(Stores.EMPTY)
    for schema in content["schemas"].values():
        if schema.name.startswith("doseqslam_msgs/"):
            typename = schema.name.replace("/", "/msg/")
            typestore.register(get_types_from_msg(schema.data.decode(), typename))
            assert schema.data.decode() == read_schema(f"ros1/{typename.rsplit('/')[-1]}.msg")
    md5s = {c.topic: c.metadata["md5sum"] for c in content["channels"].values()}
    assert md5s[OURS[0]] == typestore.generate_msgdef("doseqslam_msgs/msg/LoopClosure")[1]
    closures: list[Any] = [
        typestore.deserialize_ros1(m[4], "doseqslam_msgs/msg/LoopClosure")
        for m in content["messages"]
        if m[0] == OURS[0]
    ]
    assert [c.query_index for c in closures] == [30, 31, 32, 33, 34]
    assert closures[0].query_log_time.sec == (10**18 + 30 * STEP_NS) // 10**9
    sequences: list[Any] = [
        typestore.deserialize_ros1(m[4], "doseqslam_msgs/msg/Sequence")
        for m in content["messages"]
        if m[0] == OURS[1]
    ]
    assert [s.accepted for s in sequences] == [False, False, True]


# --- rosbag2 ------------------------------------------------------------------------------


def db3_messages(folder: Path) -> list[tuple[str, int, int, int, bytes]]:
    """The messages straight from the sqlite3 file, read-only, without rosbags."""
    uri = f"file:{folder / 'talker.db3'}?mode=ro&immutable=1"
    with sqlite3.connect(uri, uri=True) as db:
        rows = db.execute(
            "SELECT topics.name, timestamp, data FROM messages JOIN topics ON topic_id = topics.id"
        ).fetchall()
    return sorted((topic, t, t, 0, bytes(data)) for topic, t, data in rows)


def test_rosbag2_db3_copied_losslessly(shared_data: Path, tmp_path: Path) -> None:
    source = shared_data / ROSBAG2_DB3
    before = sha256(source)
    expected = db3_messages(source)
    output = tmp_path / "talker.mcap"
    summary = write_annotated_mcap(source, output, make_annotations(expected[0][1]))
    assert summary.input_kind == "rosbag2" and summary.copied_messages == len(expected) == 20
    assert sha256(source) == before
    content = read_mcap(output)
    assert content["header"].profile == "ros2"
    assert input_messages(content) == expected
    topics = {c.topic: c for c in content["channels"].values()}
    assert set(topics) == {"/topic", "/rosout", "/parameter_events", *OURS}
    assert all(c.message_encoding == "cdr" for c in topics.values())
    assert "offered_qos_profiles" in topics["/topic"].metadata
    string_schema = content["schemas"][topics["/topic"].schema_id]
    assert (string_schema.name, string_schema.encoding) == ("std_msgs/msg/String", "ros2msg")
    assert string_schema.data == b"string data"
    # Both readers decode our messages and the bag's.
    decoded = our_messages(output)
    assert [m.query_index for _, m in decoded[OURS[0]]] == [30, 31, 32, 33, 34]
    with AnyReader([output]) as reader:
        conns = [c for c in reader.connections if c.topic in ("/topic", OURS[1])]
        values = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(conns)]
    assert sum(getattr(v, "data", "").startswith("Hello, world!") for v in values) == 10
    assert [v.sequence_id for v in values if hasattr(v, "sequence_id")] == [0, 1, 2]


def test_rosbag2_mcap_folder_is_copied_as_mcap(shared_data: Path, tmp_path: Path) -> None:
    source = shared_data / ROSBAG2_MCAP_DIR
    assert plan_copy(source).kind == "mcap"
    output = tmp_path / "talker.mcap"
    write_annotated_mcap(source, output, make_annotations(1_585_866_235_112_411_371))
    assert_copied(read_mcap(source / "talker.mcap"), read_mcap(output))


def test_profiles_of_each_input_kind(shared_data: Path, tmp_path: Path) -> None:
    assert plan_copy(shared_data / ROS2_MCAP).profile == "ros2"
    assert plan_copy(shared_data / ROS1_BAG).profile == "ros1"
    assert plan_copy(shared_data / ROSBAG2_DB3).profile == "ros2"
    assert plan_copy(shared_data / ROSBAG2_DB3 / "talker.db3").path == shared_data / ROSBAG2_DB3
    write_json_mcap(tmp_path / "log.mcap", "foxglove")
    assert plan_copy(tmp_path / "log.mcap").profile == "foxglove"
    (tmp_path / "notes.txt").write_text("not a log")
    with pytest.raises(SourceError, match=r"notes\.txt"):
        plan_copy(tmp_path / "notes.txt")
    with pytest.raises(SourceError, match="missing"):
        plan_copy(tmp_path / "missing.mcap")


# --- JSON (foxglove, no profile) ----------------------------------------------------------


@pytest.mark.parametrize("profile", ["", "foxglove"])
def test_json_profile_channels_follow_the_json_schemas(tmp_path: Path, profile: str) -> None:
    source = tmp_path / "log.mcap"
    start = write_json_mcap(source, profile)
    output = tmp_path / "annotated.mcap"
    write_annotated_mcap(source, output, make_annotations(start))
    source_content, content = read_mcap(source), read_mcap(output)
    assert_copied(source_content, content)
    assert ("unused.Schema", "jsonschema", b'{"type":"object"}') in {
        (s.name, s.encoding, s.data) for s in content["schemas"].values()
    }
    schemas = {}
    for channel in content["channels"].values():
        if channel.topic in OURS:
            schema = content["schemas"][channel.schema_id]
            assert (channel.message_encoding, schema.encoding) == ("json", "jsonschema")
            name = schema.name.rsplit("/", 1)[-1]
            assert schema.data.decode() == read_schema(f"json/{name}.json")
            schemas[channel.topic] = json.loads(schema.data)
    ours = [(m[0], json.loads(m[4])) for m in content["messages"] if m[0] in OURS]
    assert Counter(topic for topic, _ in ours) == {OURS[0]: 5, OURS[1]: 3}
    for topic, value in ours:
        check_json_schema(value, schemas[topic], schemas[topic])
        assert all(abs(n) < 2**53 for n in all_numbers(value))
    first_sequence = next(v for t, v in ours if t == OURS[1])
    assert "best_score" not in first_sequence and first_sequence["best_start"] == -1
    assert first_sequence["last_log_time"] == {"sec": start // 10**9, "nsec": 9 * STEP_NS}


def test_messages_interleave_by_log_time(tmp_path: Path) -> None:
    source = tmp_path / "log.mcap"
    start = write_json_mcap(source, "")
    output = tmp_path / "annotated.mcap"
    write_annotated_mcap(source, output, make_annotations(start))
    with output.open("rb") as stream:
        # File order (not re-sorted by the reader): ours sit between the input's by log time.
        times = [m.log_time for _, _, m in make_reader(stream).iter_messages(log_time_order=False)]
    assert times == sorted(times)


def test_channel_prefix_is_ours_only_under_doseqslam(tmp_path: Path) -> None:
    source = tmp_path / "log.mcap"
    start = write_json_mcap(source, "", topic_prefix="/doseqslam_other/")
    output = tmp_path / "annotated.mcap"
    summary = write_annotated_mcap(source, output, make_annotations(start))
    assert summary.replaced_topics == [] and summary.copied_messages == 100


# --- safety -------------------------------------------------------------------------------


def test_same_path_is_refused(shared_data: Path, tmp_path: Path) -> None:
    source = tmp_path / "log.mcap"
    write_json_mcap(source, "")
    before = sha256(source)
    with pytest.raises(OutputError, match="overwrite the input"):
        write_annotated_mcap(source, source, make_annotations(0))
    link = tmp_path / "link.mcap"
    os.link(source, link)
    with pytest.raises(OutputError, match="overwrite the input"):
        write_annotated_mcap(source, link, make_annotations(0))
    assert sha256(source) == before
    bag = shared_data / ROSBAG2_DB3
    for inside in (bag / "talker.db3", bag / "annotated.mcap"):
        with pytest.raises(OutputError, match="inside the input bag"):
            write_annotated_mcap(bag, inside, make_annotations(0))
    assert not (bag / "annotated.mcap").exists()


def test_failure_mid_write_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, shared_data: Path
) -> None:
    source = shared_data / ROS2_MCAP
    output = tmp_path / "out.mcap"
    calls = {"n": 0}
    original = Writer.add_message

    def failing(self: Writer, *args: Any, **kwargs: Any) -> None:
        calls["n"] += 1
        if calls["n"] == 100:
            raise OSError(28, "No space left on device")
        original(self, *args, **kwargs)

    monkeypatch.setattr(Writer, "add_message", failing)
    with pytest.raises(OutputError, match="No space left"):
        write_annotated_mcap(source, output, make_annotations(0))
    assert leftovers(tmp_path, set()) == []


def test_failure_keeps_an_existing_output_untouched(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    source = tmp_path / "log.mcap"
    start = write_json_mcap(source, "")
    output = tmp_path / "out.mcap"
    output.write_bytes(b"previous result")

    def broken(*_: Any) -> bytes:
        raise ValueError("cannot encode")

    monkeypatch.setattr(encoder_for_profile("").__class__, "encode", broken)
    with pytest.raises(OutputError, match="cannot encode"):
        write_annotated_mcap(source, output, make_annotations(start))
    assert output.read_bytes() == b"previous result"
    assert leftovers(tmp_path, {"log.mcap", "out.mcap"}) == []


def test_unreadable_input_is_a_source_error(shared_data: Path, tmp_path: Path) -> None:
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes((shared_data / ROS2_MCAP).read_bytes()[:700_000])
    with pytest.raises(SourceError, match=r"truncated\.mcap"):
        write_annotated_mcap(truncated, tmp_path / "out.mcap", make_annotations(0))
    assert leftovers(tmp_path, {"truncated.mcap"}) == []


KILL_SNIPPET = textwrap.dedent(
    """
    import sys, time
    from doseqslam_logs.detector.events import SequenceDecision
    from doseqslam_logs.sinks import encoders
    from doseqslam_logs.sinks.mcap_writer import Annotations, write_annotated_mcap
    from doseqslam_logs.annotations.records import FrameTimes

    original = encoders.Ros2Encoder.encode
    def slow(self, message_type, fields):
        time.sleep(0.001)
        return original(self, message_type, fields)
    encoders.Ros2Encoder.encode = slow

    count = 100_000
    times = FrameTimes(range(0, count * 10, 10), [-1] * count)
    decisions = [
        SequenceDecision(i, i, i, i, i, 0, None, None, None, None, 1.0, None, None, 1.0, 0.75,
                         False, (), "doseqslam")
        for i in range(count)
    ]
    annotations = Annotations.from_decisions(decisions, times, "doseqslam", "0" * 16, {})
    write_annotated_mcap(sys.argv[1], sys.argv[2], annotations, sidecar=True)
    """
)


def test_killed_writer_leaves_no_output(shared_data: Path, tmp_path: Path) -> None:
    output = tmp_path / "sidecar.mcap"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    process = subprocess.Popen(
        [sys.executable, "-c", KILL_SNIPPET, str(shared_data / ROS2_MCAP), str(output)], env=env
    )
    try:
        deadline = time.monotonic() + 60
        # Wait until the writer is under way: its temporary file exists, then let it write.
        while not list(tmp_path.iterdir()):
            assert process.poll() is None, "the writer ended before it could be killed"
            assert time.monotonic() < deadline, "the writer never started"
            time.sleep(0.02)
        time.sleep(1.0)
        assert process.poll() is None, "the writer ended before it could be killed"
        process.send_signal(signal.SIGKILL)
    finally:
        process.kill()
        process.wait()
    assert process.returncode == -signal.SIGKILL
    assert not output.exists()
    # A killed process cannot clean up: only its hidden temporary file is left behind.
    assert all(p.name.startswith(".sidecar.mcap.") for p in tmp_path.iterdir())


def test_metadata_must_be_strings() -> None:
    with pytest.raises(TypeError):
        Annotations([], {"frames_used": 3})  # type: ignore[dict-item]
