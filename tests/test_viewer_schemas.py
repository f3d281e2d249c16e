"""Issue #19: the JSON schemas use only what Foxglove's and Lichtblick's `parseJsonSchema`
supports, NaN floats are omitted (NaN is not JSON), and logs written with the previous
schemas ($ref times, `["number", "null"]` floats written as null) still read back the same.
The ros1-profile output, which rosbags cannot open, converts to a .bag that it reads
(`to-bag`), and any other log is refused naming what converts it."""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from rosbags.highlevel import AnyReader, AnyReaderError
from test_sinks import check_json_schema, make_annotations, write_json_mcap

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.annotations.records import (
    CANDIDATE,
    LOOP_CLOSURE,
    SEQUENCE,
    LoopClosureRecord,
)
from doseqslam_logs.annotations.schema_files import read_schema
from doseqslam_logs.cli.main import main
from doseqslam_logs.errors import OutputError
from doseqslam_logs.sinks.atomic import atomic_path
from doseqslam_logs.sinks.encoders import JsonEncoder
from doseqslam_logs.sinks.mcap_writer import write_annotated_mcap

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "sample_logs"


NAMES = ("LoopClosure", "Sequence")
OURS = (LOOP_CLOSURE.topic, SEQUENCE.topic, CANDIDATE.topic)
SCALARS = {"boolean", "string", "number", "integer"}


# --- parseJsonSchema's rules (packages/mcap-support/src/parseJsonSchema.ts, Foxglove Studio
# 1.48 and Lichtblick), read from its source: what it throws on, in Python ----------------


def parse_json_schema(schema: dict[str, Any], key_path: tuple[str, ...] = ()) -> None:
    """Raises ValueError with the viewer's message where `parseJsonSchema` throws."""
    if schema.get("type") != "object":
        raise ValueError(f'Expected "type": "object" for schema, got {schema.get("type")!r}')
    for name, field in schema["properties"].items():  # the viewer iterates it unchecked
        path = ".".join((*key_path, name))
        if "oneOf" in field:
            if not all(isinstance(option.get("const"), (int, float)) for option in field["oneOf"]):
                raise ValueError(f"Unsupported type for {path}: oneOf alternatives must be numbers")
            continue
        kind = field.get("type")
        if kind == "object":
            parse_json_schema(field, (*key_path, name))
        elif kind == "array":
            _parse_array_items(field["items"], path, (*key_path, name))
        elif kind not in SCALARS:  # also "null", a list of types, and a bare "$ref"
            raise ValueError(f"Unsupported type {_js(kind)} for {path}")
        elif kind == "string" and field.get("contentEncoding") not in (None, "base64"):
            raise ValueError(f"Unsupported contentEncoding for {path}")


def _parse_array_items(items: dict[str, Any], path: str, key_path: tuple[str, ...]) -> None:
    kind = items.get("type")
    if kind == "object":
        parse_json_schema(items, key_path)
    elif kind not in SCALARS:
        raise ValueError(f"Unsupported type {_js(kind)} for array item {path}")
    elif kind == "string" and "contentEncoding" in items:
        raise ValueError(f"Unsupported contentEncoding for array item {path}")


def _js(value: Any) -> str:
    """JSON.stringify as the viewer's messages show it (undefined for an absent type)."""
    return "undefined" if value is None else json.dumps(value)


# --- the previous schemas, as logs annotated before this change hold them ---------------


def old_form_schema(schema: dict[str, Any]) -> dict[str, Any]:
    """The schema as it was: times as a $ref to $defs/Time, floats typed number-or-null."""
    old = json.loads(json.dumps(schema))
    for prop in old["properties"].values():
        if prop.get("type") == "object":
            time = {k: prop.pop(k) for k in ("properties", "required", "additionalProperties")}
            old.setdefault("$defs", {})["Time"] = {"type": "object", **time}
            del prop["type"]
            prop["$ref"] = "#/$defs/Time"
        for node in (prop, prop.get("items", {})):
            if node.get("type") == "number":
                node["type"] = ["number", "null"]
    old["required"] = list(old["properties"])
    return old


def old_form_message(new: dict[str, Any], schema: dict[str, Any]) -> dict[str, Any]:
    """The message as it was: every property, a NaN float written as null (in an array too:
    fixed-size, or parallel to the candidate query indices)."""
    old = {}
    for name, prop in schema["properties"].items():
        if name in new:
            old[name] = new[name]
        elif prop["type"] == "array":
            size = prop.get("minItems", len(new.get("candidate_query_indices", [])))
            old[name] = [None] * size
        else:
            old[name] = None
    return old


# --- tests ----------------------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_the_json_schemas_parse_as_foxglove_and_lichtblick_parse_them(name: str) -> None:
    schema = json.loads(read_schema(f"json/{name}.json"))
    parse_json_schema(schema)
    assert {"$ref", "$defs"}.isdisjoint(_keys(schema))


@pytest.mark.parametrize("name", ["foxglove.PoseInFrame", "foxglove.PosesInFrame"])
def test_the_json_pose_schemas_optimize_writes_parse_too(name: str) -> None:
    schema = json.loads(read_schema(f"json/{name}.json"))
    parse_json_schema(schema)
    assert {"$ref", "$defs"}.isdisjoint(_keys(schema))


def _keys(node: Any) -> set[str]:
    if isinstance(node, dict):
        return set(node).union(*(_keys(value) for value in node.values()))
    if isinstance(node, list):
        return set().union(*(_keys(item) for item in node))
    return set()


@pytest.mark.parametrize(("name", "first_time"), [("LoopClosure", "query_log_time"),
                                                  ("Sequence", "first_log_time")])  # fmt: skip
def test_the_previous_schemas_fail_as_the_viewer_reported(name: str, first_time: str) -> None:
    """The check is the viewer's: it refuses the old form with the Problems tab's message."""
    old = old_form_schema(json.loads(read_schema(f"json/{name}.json")))
    with pytest.raises(ValueError, match=f"^Unsupported type undefined for {first_time}$"):
        parse_json_schema(old)


def test_nan_floats_are_omitted_and_the_rest_is_valid_json() -> None:
    encoder = JsonEncoder()
    record = _a_loop_closure()
    fields = record.to_message()
    fields.update(gamma_next=math.nan, f=math.inf, rotation_xyzw=[0.0, math.nan, 0.0, 1.0])
    text = encoder.encode(LOOP_CLOSURE, fields).decode()
    value = json.loads(text)  # strict JSON: no NaN, no null
    assert "NaN" not in text and "null" not in text and "Infinity" not in text
    assert {"gamma_next", "f", "rotation_xyzw"}.isdisjoint(value)
    schema = json.loads(read_schema("json/LoopClosure.json"))
    check_json_schema(value, schema, schema)
    back = LoopClosureRecord.from_message(value)
    assert math.isnan(back.gamma_next) and math.isnan(back.f)
    assert all(math.isnan(x) for x in back.rotation_xyzw)


def test_a_log_written_with_the_previous_schemas_reads_back_the_same(tmp_path: Path) -> None:
    source, new, old = tmp_path / "log.mcap", tmp_path / "new.mcap", tmp_path / "old.mcap"
    write_annotated_mcap(source, new, make_annotations(write_json_mcap(source, "foxglove")))
    schemas = {n: old_form_schema(json.loads(read_schema(f"json/{n}.json"))) for n in NAMES}
    _rewrite_ours(new, old, schemas, old_form_message)
    assert "$ref" in _keys(_schemas_of(old)) and "$ref" not in _keys(_schemas_of(new))
    now, before = read_annotations(new), read_annotations(old)
    assert before.loop_closures and before.sequences
    # repr: NaN (a missing float) is not equal to itself.
    assert repr(before.loop_closures) == repr(now.loop_closures)
    assert repr(before.sequences) == repr(now.sequences)
    assert before.metadata == now.metadata
    assert before.frame_times and now.frame_times
    assert before.frame_times.to_json() == now.frame_times.to_json()
    assert any(math.isnan(s.best_score) for s in now.sequences)


def test_the_ros1_output_converts_to_a_bag_that_rosbags_reads(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    output, bag = tmp_path / "annotated.mcap", tmp_path / "annotated.bag"
    assert main(["annotate", str(REPO / "sample_logs" / "drive_loops.bag"), "-o", str(output),
                 "--no-verify"]) == 0  # fmt: skip
    with pytest.raises(AnyReaderError, match="Profile is not ros2"), AnyReader([output]):
        pass  # what rosbags, rosbags-convert and evo say: README.md says so, and what to do
    ours = read_annotations(output).loop_closures
    assert main(["to-bag", str(output), "-o", str(bag)]) == 0
    with output.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics is not None
    # A bag has a connection only for a topic with messages (--no-verify: no candidates).
    counts = summary.statistics.channel_message_counts
    count, topics = summary.statistics.message_count, sum(n > 0 for n in counts.values())
    assert capsys.readouterr().out.endswith(f"{bag}: {count} messages on {topics} topics\n")
    with AnyReader([bag]) as reader:
        topics = {c.topic: c for c in reader.connections}
        assert {"/camera/image/compressed", LOOP_CLOSURE.topic, SEQUENCE.topic} <= set(topics)
        closures = [reader.deserialize(raw, c.msgtype)
                    for c, _, raw in reader.messages([topics[LOOP_CLOSURE.topic]])]  # fmt: skip
    assert [(m.query_index, m.match_index) for m in closures] == [
        (lc.query.index, lc.match.index) for lc in ours
    ]
    written = bag.read_bytes()
    assert main(["to-bag", str(output), "-o", str(bag)]) == 0  # replaced atomically, the same
    assert bag.read_bytes() == written
    assert sorted(p.name for p in tmp_path.iterdir()) == ["annotated.bag", "annotated.mcap"]
    assert main(["to-bag", str(output), "-o", str(output)]) == 6  # never over the input


@pytest.mark.parametrize(
    ("log", "code", "said"),
    [
        ("foxglove.mcap", 2, "MCAP profile 'foxglove', not 'ros1'"),
        ("ros1.mcap", 2, "channel /log is not ROS 1 (message encoding 'json')"),
        ("drive_loops.ros2.mcap", 2, "a ROS 2 MCAP, not ROS 1: rosbags and evo read it as it"),
        ("drive_loops.rosbag2", 2, "a rosbag2 bag, not a ROS 1 MCAP: `rosbags-convert --src"),
        ("drive_varrate.bag", 2, "a ROS 1 .bag already"),
        ("missing.mcap", 3, "missing.mcap: no such file or directory"),
    ],
)
def test_the_bag_conversion_refuses_a_log_that_is_not_ros1(
    log: str, code: int, said: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "in"
    folder.mkdir()
    for profile in ("foxglove", "ros1"):  # JSON channels, in a ros1-profile file too
        source, new = folder / f"{profile}.log", folder / f"{profile}.mcap"
        write_annotated_mcap(source, new, make_annotations(write_json_mcap(source, profile)))
    path = SAMPLES / log if log.startswith("drive_") else folder / log
    assert main(["to-bag", str(path), "-o", str(tmp_path / "out.bag")]) == code
    error = capsys.readouterr().err
    assert error.startswith("doseqslam-logs: error: ") and said in error
    assert len(error.splitlines()) == 1
    if "ROS 2" in said or "rosbag2" in said:  # what does convert it
        assert f"`rosbags-convert --src {path} --dst OUT.bag`" in error
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]  # nothing written, no temporary


def test_the_bag_appears_whole_or_not_at_all(tmp_path: Path) -> None:
    """atomic_path, for a writer that creates its file itself: a temporary name like
    atomic_output's (a killed run's file is removed by the next write), nothing left after an
    interrupt or an error, the final name written only at the end."""
    final = tmp_path / "out.bag"
    with pytest.raises(KeyboardInterrupt), atomic_path(final) as temporary:
        assert re.fullmatch(r"\.out\.bag\.\d+\.[0-9a-f]{8}\.tmp", temporary.name)
        assert not temporary.exists()
        temporary.write_bytes(b"half")
        raise KeyboardInterrupt
    failed = pytest.raises(OutputError, match=r"out\.bag: cannot write the output: boom")
    with failed, atomic_path(final) as temporary:
        temporary.write_bytes(b"half")
        raise ValueError("boom")
    assert list(tmp_path.iterdir()) == []
    with atomic_path(final) as temporary:
        temporary.write_bytes(b"whole")
        assert not final.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["out.bag"] and final.read_bytes() == b"whole"


def _schemas_of(path: Path) -> list[Any]:
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    return [json.loads(s.data) for s in summary.schemas.values() if s.encoding == "jsonschema"]


def _a_loop_closure() -> LoopClosureRecord:
    annotations = make_annotations(1_700_000_000 * 10**9)
    records = [m.record for m in annotations.messages]
    return next(r for r in records if isinstance(r, LoopClosureRecord))


Transform = Callable[[dict[str, Any], dict[str, Any]], dict[str, Any]]


def _rewrite_ours(src: Path, dst: Path, schemas: dict[str, Any], transform: Transform) -> None:
    """Our channels, metadata and attachments of `src`, with our schemas replaced and our
    messages transformed: all that `read_annotations` reads."""
    with src.open("rb") as stream, dst.open("wb") as out:
        reader, writer = make_reader(stream), Writer(out)
        writer.start(reader.get_header().profile, "test")
        channel_ids: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages(topics=list(OURS)):
            name = schema.name.rsplit("/", 1)[-1]
            if channel.id not in channel_ids:
                data = json.dumps(schemas[name]).encode()
                schema_id = writer.register_schema(schema.name, schema.encoding, data)
                channel_ids[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_id, dict(channel.metadata)
                )
            data = json.dumps(transform(json.loads(message.data), schemas[name])).encode()
            writer.add_message(channel_ids[channel.id], message.log_time, data,
                               message.publish_time, message.sequence)  # fmt: skip
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, dict(record.metadata))
        for attachment in reader.iter_attachments():
            writer.add_attachment(attachment.create_time, attachment.log_time, attachment.name,
                                  attachment.media_type, attachment.data)  # fmt: skip
        writer.finish()  # type: ignore[no-untyped-call]


def test_annotate_writes_a_bag_for_a_bag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log, bag, mcap = SAMPLES / "drive_loops.bag", tmp_path / "out.bag", tmp_path / "out.mcap"
    assert main(["annotate", str(log), "-o", str(bag), "--no-verify"]) == 0
    assert capsys.readouterr().out.startswith(f"{bag}: 240 frames")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.bag"]  # no MCAP left beside it
    assert main(["annotate", str(log), "-o", str(mcap), "--no-verify"]) == 0
    ours = read_annotations(mcap).loop_closures
    with AnyReader([bag]) as reader:
        topics = {c.topic: c for c in reader.connections}
        closures = [reader.deserialize(raw, c.msgtype)
                    for c, _, raw in reader.messages([topics[LOOP_CLOSURE.topic]])]  # fmt: skip
    assert [(m.query_index, m.match_index) for m in closures] == [
        (lc.query.index, lc.match.index) for lc in ours
    ]
    capsys.readouterr()
    ros2 = SAMPLES / "drive_loops.ros2.mcap"
    assert main(["annotate", str(ros2), "-o", str(tmp_path / "x.bag")]) == 2  # before the run
    error = capsys.readouterr().err
    assert "a .bag output needs a ROS 1 .bag input" in error and len(error.splitlines()) == 1
    assert not (tmp_path / "x.bag").exists()
