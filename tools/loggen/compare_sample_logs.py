"""Compare two folders of generated sample logs the way that holds on every processor.

    python -m loggen.compare_sample_logs sample_logs /tmp/regenerated

The generator renders through floating-point NumPy and OpenCV kernels whose SIMD paths (AVX2,
AVX-512, NEON) round differently in the last bit, so a log regenerated on another processor may
differ from the committed one by a few bytes. What must not differ is everything a log *means*:

- side files (`*.json`, `*.poses.csv`, `*.gt.npz`, `metadata.yaml`): byte for byte;
- the README: byte for byte except the byte sizes of the logs it lists;
- every log: the same container facts (MCAP profile, schemas, channels, metadata records; bag
  connections with their definitions), the same messages in the same order with the same topics,
  types, log and publish times, and every decoded field exactly (stamps, frame ids, CameraInfo,
  image formats and sizes), with two exceptions:
  - the float fields of poses and velocities (`pose.*`, `twist.*`) to `POSE_TOLERANCE`: they go
    through NumPy's sin/cos/exp, whose AVX-512 and AVX2 paths differ by an ulp;
  - image pixels, decoded, within `PixelTolerance`: a pixel that lands on a rounding boundary in
    a float kernel changes by one level, and JPEG spreads that over its 8x8 (or 16x16) block.

Exit status 0 when the folders agree, 1 (with one line per difference) when they do not.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from google.protobuf.message import Message as ProtobufMessage
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

# 1e-9 m and 1e-9 of a unit quaternion: far below anything physical, far above an ulp (~1e-16
# relative) of the values the generator writes.
POSE_TOLERANCE = 1e-9
LOG_SUFFIXES = (".mcap", ".bag", ".db3")
# "| `drive_loops.ros2.mcap` | ROS 2 MCAP (...) | 995,353 |" and "Total: 7,416,579 bytes"
_README_SIZES = [
    (re.compile(r"^(\| `[^`]+` \| .* \| )[\d,]+( \|)$", re.MULTILINE), r"\1<bytes>\2"),
    (re.compile(r"^Total: [\d,]+ bytes", re.MULTILINE), "Total: <bytes> bytes"),
]


@dataclass(frozen=True)
class PixelTolerance:
    """How far decoded images may drift between processors (measured: with every SIMD extension
    of NumPy and OpenCV switched off, at most 3 levels on 4.4e-5 of the values; see
    sample_logs/README.md)."""

    level: int = 1  # "close": within one grey level
    frame_share: float = 0.01  # in each frame, at least 99 % of the values are close
    log_share: float = 0.001  # over a log, at least 99.9 % are
    max_level: int = 32  # and no value is further off than this


@dataclass
class PixelStats:
    values: int = 0
    far: int = 0  # values more than `level` apart
    max_level: int = 0
    worst_frame_share: float = 0.0
    frames_differing: int = 0

    def add(self, a: np.ndarray, b: np.ndarray, level: int) -> None:
        d = np.abs(a.astype(np.int16) - b.astype(np.int16))
        far = int(np.count_nonzero(d > level))
        self.values += d.size
        self.far += far
        self.max_level = max(self.max_level, int(d.max(initial=0)))
        self.worst_frame_share = max(self.worst_frame_share, far / max(d.size, 1))
        self.frames_differing += bool(d.any())

    def problems(self, name: str, tolerance: PixelTolerance) -> list[str]:
        share = self.far / max(self.values, 1)
        summary = (
            f"{self.frames_differing} frames differ, {share:.2e} of the values by more than"
            f" {tolerance.level} (worst frame {self.worst_frame_share:.2e}), at most"
            f" {self.max_level} levels"
        )
        bad = (
            share > tolerance.log_share
            or self.worst_frame_share > tolerance.frame_share
            or self.max_level > tolerance.max_level
        )
        return [f"{name}: images beyond tolerance: {summary}"] if bad else []


@dataclass(frozen=True)
class Record:
    """One message of a log: where it stands and what it says, field by field."""

    topic: str
    message_type: str
    log_time_ns: int
    publish_time_ns: int | None
    fields: dict[str, Any] = field(hash=False)


# -- reading any container ---------------------------------------------------------------------


def _flatten(value: Any, path: str = "") -> Iterator[tuple[str, Any]]:
    if is_dataclass(value) and not isinstance(value, type):
        for f in fields(value):
            if f.name != "__msgtype__":
                yield from _flatten(getattr(value, f.name), f"{path}.{f.name}".lstrip("."))
    elif isinstance(value, ProtobufMessage):
        # Every field, not ListFields(): proto3 leaves out zeros, and 0.0 against 1e-17 would
        # then look like a missing field rather than a value within tolerance.
        for descriptor in value.DESCRIPTOR.fields:
            name = f"{path}.{descriptor.name}".lstrip(".")
            yield from _flatten(getattr(value, descriptor.name), name)
    elif isinstance(value, (list, tuple)) or type(value).__name__ == "RepeatedScalarContainer":
        items = list(value)
        if all(isinstance(x, (int, float)) for x in items):
            yield path, np.asarray(items)
        else:
            for i, item in enumerate(items):
                yield from _flatten(item, f"{path}[{i}]")
    else:
        yield path, value


def _mcap_records(path: Path) -> tuple[list[str], list[Record]]:
    typestore = get_typestore(Stores.ROS2_HUMBLE)
    with path.open("rb") as file:
        reader = make_reader(file)
        protobuf = ProtobufDecoderFactory()
        header = reader.get_header()
        summary = reader.get_summary()
        facts = [f"profile {header.profile!r} library {header.library!r}"]
        if summary is not None:
            for known in sorted(summary.schemas.values(), key=lambda s: s.id):
                facts.append(f"schema {known.id} {known.name} {known.encoding} {known.data!r}")
            for ch in sorted(summary.channels.values(), key=lambda c: c.id):
                facts.append(
                    f"channel {ch.id} {ch.topic} {ch.message_encoding} schema {ch.schema_id}"
                    f" {sorted(ch.metadata.items())}"
                )
        for metadata in reader.iter_metadata():
            facts.append(f"metadata {metadata.name} {sorted(metadata.metadata.items())}")
        for attachment in reader.iter_attachments():
            facts.append(f"attachment {attachment.name} {attachment.data!r}")
        records = []
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            assert schema is not None, f"{path}: schemaless channel {channel.topic}"
            if channel.message_encoding == "cdr":
                decoded: Any = typestore.deserialize_cdr(message.data, schema.name)
            else:
                decode = protobuf.decoder_for(channel.message_encoding, schema)
                assert decode is not None, f"{path}: no decoder for {channel.message_encoding}"
                decoded = decode(message.data)
            records.append(_record(channel.topic, schema.name, message, decoded))
        return facts, records


def _record(topic: str, message_type: str, message: Any, decoded: Any) -> Record:
    return Record(
        topic,
        message_type,
        message.log_time,
        message.publish_time,
        dict(_flatten(decoded)),
    )


def _rosbags_records(path: Path) -> tuple[list[str], list[Record]]:
    bag = path.parent if path.suffix == ".db3" else path
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        facts = [
            f"connection {c.topic} {c.msgtype} {c.msgcount} {c.digest} {c.msgdef.data!r}"
            for c in sorted(reader.connections, key=lambda c: (c.topic, c.id))
        ]
        records = [
            Record(c.topic, c.msgtype, t, None, dict(_flatten(reader.deserialize(raw, c.msgtype))))
            for c, t, raw in reader.messages()
        ]
    return facts, records


def read_log(path: Path) -> tuple[list[str], list[Record]]:
    """The container facts and the decoded messages of an MCAP file, ROS 1 bag or rosbag2 .db3."""
    with path.open("rb") as file:
        is_mcap = file.read(8) == b"\x89MCAP0\r\n"
    return _mcap_records(path) if is_mcap else _rosbags_records(path)


# -- comparing ---------------------------------------------------------------------------------


def _pixels(record: Record) -> np.ndarray:
    data = np.frombuffer(bytes(record.fields["data"]), np.uint8)
    if "CompressedImage" in record.message_type:
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError(f"{record.topic} at {record.log_time_ns}: image does not decode")
        return image
    return data  # raw: the bytes are the pixels (rows, step and encoding compared exactly)


def _is_image(record: Record) -> bool:
    return record.message_type.split("/")[-1].split(".")[-1] in {
        "Image",
        "CompressedImage",
        "RawImage",
    }


def _same(a: Any, b: Any, tolerance: float) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        if a.shape != b.shape or a.dtype.kind != b.dtype.kind:
            return False
        if a.dtype.kind == "f" and tolerance > 0:
            return bool(np.allclose(a, b, rtol=0.0, atol=tolerance))
        return bool(np.array_equal(a, b))
    if isinstance(a, float) and isinstance(b, float) and tolerance > 0:
        return abs(a - b) <= tolerance
    return bool(type(a) is type(b) and a == b)


def _field_tolerance(name: str) -> float:
    return POSE_TOLERANCE if name.split(".")[0] in {"pose", "twist"} else 0.0


def compare_records(
    name: str, a: list[Record], b: list[Record], pixels: PixelTolerance
) -> list[str]:
    """What differs between two logs' messages, one line per kind of difference."""
    if len(a) != len(b):
        return [f"{name}: {len(a)} messages against {len(b)}"]
    problems: list[str] = []
    stats = PixelStats()
    for i, (x, y) in enumerate(zip(a, b, strict=True)):
        where = f"{name}: message {i} ({x.topic} at {x.log_time_ns})"
        if (x.topic, x.message_type, x.log_time_ns, x.publish_time_ns) != (
            y.topic,
            y.message_type,
            y.log_time_ns,
            y.publish_time_ns,
        ):
            problems.append(f"{where}: against {y.topic} {y.message_type} at {y.log_time_ns}")
            continue
        if x.fields.keys() != y.fields.keys():
            problems.append(f"{where}: fields {sorted(x.fields)} against {sorted(y.fields)}")
            continue
        image = _is_image(x)
        for key in x.fields:
            if image and key == "data":
                stats.add(_pixels(x), _pixels(y), pixels.level)
            elif not _same(x.fields[key], y.fields[key], _field_tolerance(key)):
                problems.append(f"{where}: {key} {x.fields[key]!r} against {y.fields[key]!r}")
    return problems[:20] + stats.problems(name, pixels)


def compare_logs(a: Path, b: Path, pixels: PixelTolerance = PixelTolerance()) -> list[str]:
    facts_a, records_a = read_log(a)
    facts_b, records_b = read_log(b)
    if len(facts_a) != len(facts_b):
        return [f"{a.name}: {len(facts_a)} container facts against {len(facts_b)}"]
    pairs = zip(facts_a, facts_b, strict=True)
    problems = [f"{a.name}: {x!r} against {y!r}" for x, y in pairs if x != y]
    return problems + compare_records(a.name, records_a, records_b, pixels)


def _readme_without_sizes(text: str) -> str:
    for pattern, replacement in _README_SIZES:
        text = pattern.sub(replacement, text)
    return text


def compare_folders(a: Path, b: Path, pixels: PixelTolerance = PixelTolerance()) -> list[str]:
    """Every difference between two sample folders that matters on any processor."""
    files_a = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    if files_a != files_b:
        return [f"files {[str(p) for p in files_a]} against {[str(p) for p in files_b]}"]
    problems: list[str] = []
    for relative in files_a:
        x, y = a / relative, b / relative
        if relative.name == "README.md":
            same = _readme_without_sizes(x.read_text()) == _readme_without_sizes(y.read_text())
            problems += [] if same else [f"{relative}: differs beyond the log sizes"]
        elif relative.suffix in LOG_SUFFIXES:
            problems += compare_logs(x, y, pixels)
        elif x.read_bytes() != y.read_bytes():
            problems.append(f"{relative}: differs (compared byte for byte)")
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("a", type=Path, help="a sample folder (e.g. sample_logs)")
    parser.add_argument("b", type=Path, help="the folder to compare it with")
    args = parser.parse_args(argv)
    problems = compare_folders(args.a, args.b)
    for problem in problems:
        print(problem)
    if not problems:
        print(f"{args.a} and {args.b} agree (logs within the cross-processor tolerance)")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
