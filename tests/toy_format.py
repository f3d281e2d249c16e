"""A toy log format, written the way a new format is added to the tool: one module (its Source
and its copier) plus one `LogFormat` entry (`TOY`). tests/test_log_formats.py registers it and
annotates a toy log end to end.

A toy log is the magic line, then records of (log time: int64 LE, length: uint32 LE, JPEG
bytes), all of one camera topic.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterator
from pathlib import Path

from mcap.writer import Writer

from doseqslam_logs.errors import SourceError
from doseqslam_logs.sources.base import ChannelInfo, DecodedMessage, ImageMessage, SourceDefaults
from doseqslam_logs.sources.copying import Copied, CopyHooks
from doseqslam_logs.sources.formats import CopyPlan, LogFormat

MAGIC = b"TOYLOG v1\n"
TOPIC = "/toy/camera"
TYPE = "toy.JpegFrame"
_RECORD = struct.Struct("<qI")


def write_toy_log(path: Path, frames: list[tuple[int, bytes]]) -> None:
    """A toy log of (log time, JPEG bytes) frames."""
    with path.open("wb") as file:
        file.write(MAGIC)
        for log_time_ns, jpeg in frames:
            file.write(_RECORD.pack(log_time_ns, len(jpeg)) + jpeg)


def _records(path: Path) -> Iterator[tuple[int, bytes]]:
    with path.open("rb") as file:
        if file.read(len(MAGIC)) != MAGIC:
            raise SourceError(f"{path}: not a toy log")
        while head := file.read(_RECORD.size):
            if len(head) < _RECORD.size:
                raise SourceError(f"{path}: a truncated record")
            log_time_ns, size = _RECORD.unpack(head)
            yield log_time_ns, file.read(size)


class ToySource(SourceDefaults):
    """The `Source` of a toy log."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._times = [t for t, _ in _records(path)]

    def channels(self) -> list[ChannelInfo]:
        first, last = (self._times[0], self._times[-1]) if self._times else (None, None)
        return [ChannelInfo(TOPIC, TYPE, "json", len(self._times), first, last, is_image=True)]

    def image_messages(
        self, topic: str, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[ImageMessage]:
        for log_time_ns, jpeg in self.raw_messages(topic, start_ns, end_ns):
            yield ImageMessage(topic, log_time_ns, None, "compressed", "jpeg", 0, 0, 0, False, jpeg)

    def messages(self, topic: str) -> Iterator[DecodedMessage]:
        return iter(())  # a toy log has no other topic

    def raw_messages(
        self, topic: str, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[tuple[int, bytes]]:
        for log_time_ns, jpeg in _records(self.path):
            after_start = start_ns is None or log_time_ns >= start_ns
            if topic == TOPIC and after_start and (end_ns is None or log_time_ns < end_ns):
                yield log_time_ns, jpeg


def copy_toy(path: Path, writer: Writer, hooks: CopyHooks) -> Copied:
    """Every frame of the toy log as a JSON message of one channel."""
    if not hooks.keeps_topic(TOPIC):
        return Copied(0, [TOPIC])
    schema = json.dumps({"type": "object", "properties": {"jpeg_bytes": {"type": "integer"}}})
    schema_id = writer.register_schema(TYPE, "jsonschema", schema.encode())
    channel_id = writer.register_channel(TOPIC, "json", schema_id, {})
    hooks.channel_copied(TOPIC, "json", schema_id, {})
    copied = 0
    for log_time_ns, jpeg in _records(path):
        hooks.before_message(log_time_ns)
        data = json.dumps({"jpeg_bytes": len(jpeg)}).encode()
        writer.add_message(channel_id, log_time_ns, data, log_time_ns, copied)
        copied += 1
    return Copied(copied, [])


TOY = LogFormat(
    name="toy",
    described="toy log",
    probe=lambda path, head: head.startswith(MAGIC),
    open=ToySource,
    plan_copy=lambda path: CopyPlan("toy", path, "", copy_toy),
    suffixes=(".toy",),
)
