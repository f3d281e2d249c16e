"""`annotate --recover`: copy every readable record of a damaged MCAP into a clean one.

A recording cut short (power loss, full disk, killed recorder) has no summary and ends in the
middle of a record; bit rot makes a chunk fail its CRC check. `salvage_mcap` streams the file
from the start and writes what it can read into a new, complete and indexed MCAP:

* every schema, channel, message, attachment and metadata record up to the first record that
  cannot be read (the cut); what follows is lost and the report says from which byte on;
* a chunk that fails its CRC check (or does not decompress) is dropped whole, and its messages
  are counted by topic when the chunk can still be parsed without the check.

The input is only read. The report is what annotate puts in its summary and metadata, so that
nothing is lost silently.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    Footer,
    Header,
    Message,
    Metadata,
    Schema,
)
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from doseqslam_logs.errors import SourceError
from doseqslam_logs.sources.mcap_source import describe_read_error


@dataclass
class SalvageReport:
    """What `salvage_mcap` could and could not read."""

    file_size: int
    bytes_used: int = 0  # offset just after the last record that was read
    complete: bool = False  # the file ends with its footer
    stop_reason: str = ""  # why reading stopped before the footer ("" if it did not)
    messages: int = 0  # messages copied
    corrupt_chunks: int = 0  # chunks dropped (CRC mismatch, does not decompress)
    lost_by_topic: Counter[str] = field(default_factory=Counter)  # their messages, by topic
    uncountable_chunks: int = 0  # dropped chunks whose messages could not even be counted
    orphan_messages: int = 0  # messages whose channel record was lost

    @property
    def damaged(self) -> bool:
        return not self.complete or self.corrupt_chunks > 0 or self.orphan_messages > 0

    def describe(self) -> str:
        """One line, e.g. "truncated at byte 86530 of 86530 (the file ends in the middle of a
        record: truncated?); 1 corrupt chunk dropped (3 messages)"."""
        parts = []
        if not self.complete:
            parts.append(
                f"read {self.bytes_used} of {self.file_size} bytes, the rest is lost "
                f"({self.stop_reason or 'no footer'})"
            )
        if self.corrupt_chunks:
            lost = sum(self.lost_by_topic.values())
            unknown = f", {self.uncountable_chunks} of them uncountable" * bool(
                self.uncountable_chunks
            )
            parts.append(
                f"{self.corrupt_chunks} corrupt chunk(s) dropped ({lost} messages{unknown})"
            )
        if self.orphan_messages:
            parts.append(f"{self.orphan_messages} messages of unknown channels dropped")
        return "; ".join(parts) or "nothing to recover: the file is whole"

    def as_metadata(self) -> dict[str, object]:
        return {
            "file_size": self.file_size,
            "bytes_used": self.bytes_used,
            "complete": self.complete,
            "stop_reason": self.stop_reason,
            "messages": self.messages,
            "corrupt_chunks": self.corrupt_chunks,
            "lost_by_topic": dict(sorted(self.lost_by_topic.items())),
            "uncountable_chunks": self.uncountable_chunks,
            "orphan_messages": self.orphan_messages,
        }


class _Salvager:
    def __init__(self, target: BinaryIO, report: SalvageReport) -> None:
        self.target = target
        self.report = report
        self.writer: Writer | None = None
        self.schemas: dict[int, Schema] = {}
        self.schema_ids: dict[int, int] = {}  # input schema id -> output schema id
        self.channels: dict[int, Channel] = {}
        self.channel_ids: dict[int, int] = {}  # input channel id -> output channel id

    def start(self, header: Header) -> None:
        # Uncompressed: the copy is read once or twice and deleted; CPU matters more.
        self.writer = Writer(self.target, compression=CompressionType.NONE)
        self.writer.start(profile=header.profile, library=header.library)

    def record(self, record: object) -> None:
        writer = self.writer
        if isinstance(record, Header):
            if writer is None:
                self.start(record)
            return
        if writer is None:
            return
        if isinstance(record, Schema):
            self.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            self.channels.setdefault(record.id, record)
        elif isinstance(record, Message):
            self.message(writer, record)
        elif isinstance(record, Chunk):
            self.chunk(record)
        elif isinstance(record, Attachment):
            writer.add_attachment(
                record.create_time, record.log_time, record.name, record.media_type, record.data
            )
        elif isinstance(record, Metadata):
            writer.add_metadata(record.name, dict(record.metadata))
        elif isinstance(record, Footer):
            self.report.complete = True
        # DataEnd, indexes, statistics, summary offsets: the writer makes its own.

    def message(self, writer: Writer, message: Message) -> None:
        channel_id = self.output_channel(writer, message.channel_id)
        if channel_id is None:
            self.report.orphan_messages += 1
            return
        writer.add_message(
            channel_id, message.log_time, message.data, message.publish_time, message.sequence
        )
        self.report.messages += 1

    def output_channel(self, writer: Writer, input_id: int) -> int | None:
        if input_id in self.channel_ids:
            return self.channel_ids[input_id]
        channel = self.channels.get(input_id)
        if channel is None:
            return None
        schema_id = 0
        if channel.schema_id != 0:
            if channel.schema_id not in self.schema_ids:
                schema = self.schemas.get(channel.schema_id)
                if schema is None:
                    return None
                self.schema_ids[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            schema_id = self.schema_ids[channel.schema_id]
        self.channel_ids[input_id] = writer.register_channel(
            channel.topic, channel.message_encoding, schema_id, dict(channel.metadata)
        )
        return self.channel_ids[input_id]

    def chunk(self, chunk: Chunk) -> None:
        try:
            records = breakup_chunk(chunk, validate_crc=True)
        except Exception:  # CRC mismatch, or it does not decompress or parse
            self.report.corrupt_chunks += 1
            self.count_lost(chunk)
            return
        for record in records:
            self.record(record)

    def count_lost(self, chunk: Chunk) -> None:
        try:
            records = breakup_chunk(chunk, validate_crc=False)
        except Exception:
            self.report.uncountable_chunks += 1
            return
        inner = {r.id: r.topic for r in records if isinstance(r, Channel)}
        for record in records:
            if isinstance(record, Message):
                known = self.channels.get(record.channel_id)
                topic = known.topic if known is not None else inner.get(record.channel_id, "?")
                self.report.lost_by_topic[topic] += 1

    def finish(self) -> None:
        if self.writer is None:
            return
        for channel_id in self.channels:  # channels whose messages were all lost
            self.output_channel(self.writer, channel_id)
        for schema_id, schema in self.schemas.items():  # schemas no channel used
            if schema_id not in self.schema_ids:
                self.schema_ids[schema_id] = self.writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
        self.writer.finish()  # type: ignore[no-untyped-call]  # mcap leaves it unannotated


def salvage_mcap(source: Path, target: BinaryIO) -> SalvageReport:
    """Write every readable record of the MCAP file `source` to `target` (module docstring).

    Raises:
        SourceError: `source` cannot be opened, or not even its header record can be read.
    """
    try:
        file = source.open("rb")
    except OSError as exc:
        raise SourceError(f"{source}: cannot open ({exc.strerror or exc})") from exc
    with file:
        size = file.seek(0, 2)
        file.seek(0)
        report = SalvageReport(file_size=size)
        salvager = _Salvager(target, report)
        records = StreamReader(file, emit_chunks=True, record_size_limit=max(size, 1)).records
        while not report.complete:
            try:
                record = next(records)
            except StopIteration:
                break
            except Exception as exc:  # whatever the damage makes the mcap library raise
                report.stop_reason = describe_read_error(exc)
                break
            if salvager.writer is None and not isinstance(record, Header):
                report.stop_reason = "the file does not start with a header record"
                break
            salvager.record(record)  # write errors (OSError) are the caller's
            report.bytes_used = file.tell()
        if salvager.writer is None:
            raise SourceError(
                f"{source}: nothing to recover: not even the MCAP header can be read "
                f"({report.stop_reason or 'empty'})"
            )
        salvager.finish()
    return report
