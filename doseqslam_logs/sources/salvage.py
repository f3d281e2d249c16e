"""`annotate --recover`: copy every readable record of a damaged MCAP into a clean one.

A recording cut short (power loss, full disk, killed recorder) has no summary and ends in the
middle of a record; bit rot makes a chunk fail its CRC check or garbles a length field.
`salvage_mcap` walks the file's records from the start, each within the bounds its record
length gives, and writes what it can read into a new, complete and indexed MCAP:

* every schema, channel, message, attachment and metadata record it can read;
* a chunk that fails its CRC check, does not decompress, or whose fields do not fit inside its
  record (e.g. a huge records-length field) is dropped whole; its messages are counted by topic
  from the chunk itself when it still parses without the check, else from the message index
  records that follow it;
* a chunk whose uncompressed size field is wrong (over the chunk cap of `chunk_limits`,
  larger or smaller than its records) is read as a streaming decoder reads it, whatever the
  field says, and never held past the cap: its records are kept whole when they fit the cap
  and pass the CRC check, and the chunk is counted; one that really holds more than the cap
  is dropped and counted from its message indexes;
* a record whose own length is impossible (past the end of the file, or not what the summary's
  chunk index says for a chunk there) is stepped over: to the length the chunk index gives,
  else to the next offset where a well-formed chunk record starts (found by a scan);
* a chunk cut short by the end of the file is decompressed as a stream (lz4, zstd, or read as
  it is when uncompressed) and every whole record before the cut is kept. These messages have
  no CRC to check (the CRC covers the whole chunk); their images are still checked by the
  decoder.

When the file still has its summary (only the data section is damaged), its channels and
schemas stand in for ones lost in a dropped chunk, and its Statistics record says how many
messages the file held. The input is only read. The report is what annotate puts in its summary
and metadata, so that nothing is lost silently.
"""

from __future__ import annotations

import io
import mmap
import struct
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    Footer,
    Header,
    McapRecord,
    Message,
    MessageIndex,
    Metadata,
    Schema,
)
from mcap.stream_reader import breakup_chunk
from mcap.summary import Summary
from mcap.writer import CompressionType, Writer

from doseqslam_logs.errors import SourceError
from doseqslam_logs.sources import chunk_limits
from doseqslam_logs.sources.base import MCAP_MAGIC
from doseqslam_logs.sources.mcap_source import is_complete

_RECORD = struct.Struct("<BQ")  # opcode, record length
_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size, CRC, compression length
_U64 = struct.Struct("<Q")
_INDEX_HEAD = struct.Struct("<HI")  # message index: channel id, byte length of its pairs
_COMPRESSIONS = ("", "lz4", "zstd")
_MAX_COMPRESSION_NAME = 16
_TRUNCATED = "the file ends in the middle of a record: truncated?"


@dataclass
class SalvageReport:
    """What `salvage_mcap` could and could not read."""

    file_size: int
    bytes_used: int = 0  # offset just after the last record that was read whole
    complete: bool = False  # the file ends with its footer
    stop_reason: str = ""  # why reading stopped before the footer ("" if it did not)
    messages: int = 0  # messages copied
    corrupt_chunks: int = 0  # chunks dropped (CRC mismatch, does not decompress, bad fields)
    oversized_chunks: int = 0  # of corrupt_chunks: holding more than the chunk cap
    wrong_size_chunks: int = 0  # chunks read whole although their size field is wrong
    lost_by_topic: Counter[str] = field(default_factory=Counter)  # their messages, by topic
    uncountable_chunks: int = 0  # dropped chunks whose messages could not even be counted
    orphan_messages: int = 0  # messages whose channel record was lost
    partial_chunk_messages: int = 0  # of `messages`: whole ones from a chunk cut short
    skipped_regions: int = 0  # damaged stretches stepped over to the next valid record
    skipped_bytes: int = 0
    repaired_lengths: int = 0  # chunk record lengths taken from the summary's chunk index
    corrupt_records: int = 0  # records within sound bounds that do not parse (skipped)
    known_messages: int = 0  # the Statistics record's count, else copied + counted as lost
    known_from: str = ""  # "the Statistics record" or "the records read"

    @property
    def damaged(self) -> bool:
        damage = (
            self.corrupt_chunks,
            self.wrong_size_chunks,
            self.orphan_messages,
            self.skipped_regions,
            self.repaired_lengths,
            self.corrupt_records,
        )
        return not self.complete or any(damage) or self.known_messages > self.messages

    def describe(self) -> str:
        """One line, e.g. "read 86530 of 90112 bytes, the rest is lost (the file ends in the
        middle of a record: truncated?); 1 corrupt chunk(s) dropped (3 messages); recovered
        9 of 12 known messages"."""
        parts = []
        if not self.complete:
            parts.append(
                f"read {self.bytes_used} of {self.file_size} bytes, the rest is lost "
                f"({self.stop_reason or 'no footer'})"
            )
        if self.partial_chunk_messages:
            parts.append(f"{self.partial_chunk_messages} whole messages from a chunk cut short")
        if self.corrupt_chunks:
            lost = sum(self.lost_by_topic.values())
            unknown = f", {self.uncountable_chunks} of them uncountable" * bool(
                self.uncountable_chunks
            )
            oversized = (
                f", {self.oversized_chunks} of these chunk(s) over the cap of "
                f"{chunk_limits.MAX_CHUNK_BYTES} bytes uncompressed"
            ) * bool(self.oversized_chunks)
            parts.append(
                f"{self.corrupt_chunks} corrupt chunk(s) dropped "
                f"({lost} messages{unknown}){oversized}"
            )
        if self.wrong_size_chunks:
            parts.append(f"{self.wrong_size_chunks} chunk(s) with a wrong size field read whole")
        if self.skipped_regions:
            parts.append(
                f"{self.skipped_regions} damaged region(s) of {self.skipped_bytes} bytes "
                "stepped over to the next valid chunk"
            )
        if self.repaired_lengths:
            parts.append(f"{self.repaired_lengths} chunk length(s) taken from the chunk index")
        if self.corrupt_records:
            parts.append(f"{self.corrupt_records} unparsable records skipped")
        if self.orphan_messages:
            parts.append(f"{self.orphan_messages} messages of unknown channels dropped")
        if not parts:
            return "nothing to recover: the file is whole"
        parts.append(
            f"recovered {self.messages} of {self.known_messages} known messages "
            f"(known from {self.known_from})"
        )
        return "; ".join(parts)

    def as_metadata(self) -> dict[str, object]:
        return {
            "file_size": self.file_size,
            "bytes_used": self.bytes_used,
            "complete": self.complete,
            "stop_reason": self.stop_reason,
            "messages": self.messages,
            "known_messages": self.known_messages,
            "known_from": self.known_from,
            "corrupt_chunks": self.corrupt_chunks,
            "oversized_chunks": self.oversized_chunks,
            "wrong_size_chunks": self.wrong_size_chunks,
            "lost_by_topic": dict(sorted(self.lost_by_topic.items())),
            "uncountable_chunks": self.uncountable_chunks,
            "orphan_messages": self.orphan_messages,
            "partial_chunk_messages": self.partial_chunk_messages,
            "skipped_regions": self.skipped_regions,
            "skipped_bytes": self.skipped_bytes,
            "repaired_lengths": self.repaired_lengths,
            "corrupt_records": self.corrupt_records,
        }


# ---------------------------------------------------------------------------------------------
# Chunk records, parsed within their record's bounds


@dataclass(frozen=True)
class _ChunkHead:
    chunk: Chunk  # with `data` the records bytes present (all of them unless cut short)
    records_length: int  # what the chunk says its records take


def _chunk_head(body: bytes) -> _ChunkHead | None:
    """The chunk's fields, None when they do not fit a chunk (compression name too long or not
    text, or the body too short for them); `chunk.data` is at most what the body holds."""
    if len(body) < _CHUNK_HEAD.size:
        return None
    start, end, size, crc, name_length = _CHUNK_HEAD.unpack_from(body)
    offset = _CHUNK_HEAD.size + name_length
    if name_length > _MAX_COMPRESSION_NAME or len(body) < offset + _U64.size:
        return None
    try:
        compression = body[_CHUNK_HEAD.size : offset].decode("ascii")
    except UnicodeDecodeError:
        return None
    (records_length,) = _U64.unpack_from(body, offset)
    data = body[offset + _U64.size : offset + _U64.size + records_length]
    chunk = Chunk(
        compression=compression,
        data=data,
        message_end_time=end,
        message_start_time=start,
        uncompressed_crc=crc,
        uncompressed_size=size,
    )
    return _ChunkHead(chunk, records_length)


def _is_chunk_at(data: bytes | mmap.mmap, offset: int, size: int) -> bool:
    """Whether a well-formed chunk record starts at `offset`: its fields add up exactly to its
    record length and name a known compression (what a resync accepts)."""
    if offset + _RECORD.size > size:
        return False
    opcode, length = _RECORD.unpack_from(data, offset)
    body_start = offset + _RECORD.size
    if opcode != Opcode.CHUNK or body_start + length > size:
        return False
    head = _chunk_head(bytes(data[body_start : body_start + min(length, 64)]))
    if head is None or head.chunk.compression not in _COMPRESSIONS:
        return False
    fixed = _CHUNK_HEAD.size + len(head.chunk.compression) + _U64.size
    return bool(fixed + head.records_length == length)


def _decompress_prefix(chunk: Chunk) -> bytes:
    """As much of a cut-short chunk's records as a streaming decompressor gets out of it, at
    most what the chunk claims (and never over the chunk cap)."""
    limit = min(chunk.uncompressed_size, chunk_limits.MAX_CHUNK_BYTES)
    return chunk_limits.decompress_at_most(chunk.compression, chunk.data, limit)


def _chunk_data(chunk: Chunk, validate_crc: bool) -> tuple[bytes, bool]:
    """The chunk's records and whether its size field is wrong (raises as
    `chunk_limits.stream_chunk_records`); the plain read, faster, comes first: it reads every
    chunk whose field is right."""
    try:
        data = chunk_limits.chunk_records(chunk, validate_crc)
    except chunk_limits.ChunkTooLargeError:  # claims over the cap, or holds more than it claims
        return chunk_limits.stream_chunk_records(chunk, validate_crc), True
    return data, len(data) != chunk.uncompressed_size


def _records_of(data: bytes) -> list[McapRecord]:
    """The records of a chunk's decompressed bytes, as the mcap library reads them (raises
    for records that do not parse)."""
    plain = Chunk(
        compression="",
        data=data,
        message_end_time=0,
        message_start_time=0,
        uncompressed_crc=0,
        uncompressed_size=len(data),
    )
    return breakup_chunk(plain)


def _whole_records(data: bytes) -> list[McapRecord]:
    """The schema, channel and message records that lie whole in `data` (a chunk's records)."""
    records: list[McapRecord] = []
    position = 0
    while position + _RECORD.size <= len(data):
        opcode, length = _RECORD.unpack_from(data, position)
        body = position + _RECORD.size
        if body + length > len(data):
            break
        record = _parse(opcode, data[body : body + length])
        if isinstance(record, Schema | Channel | Message):
            records.append(record)
        position = body + length
    return records


_PARSERS: dict[int, Callable[[ReadDataStream, int], McapRecord]] = {
    Opcode.HEADER: lambda stream, _: Header.read(stream),
    Opcode.FOOTER: lambda stream, _: Footer.read(stream),
    Opcode.SCHEMA: lambda stream, _: Schema.read(stream),
    Opcode.CHANNEL: lambda stream, _: Channel.read(stream),
    Opcode.MESSAGE: Message.read,
    Opcode.MESSAGE_INDEX: lambda stream, _: MessageIndex.read(stream),
    Opcode.ATTACHMENT: lambda stream, _: Attachment.read(stream),
    Opcode.METADATA: lambda stream, _: Metadata.read(stream),
}


def _parse(opcode: int, body: bytes) -> McapRecord | None:
    """The record of a body whose bounds are known; None for a record type we do not copy.

    Raises whatever the mcap library raises for a body that does not parse."""
    parser = _PARSERS.get(opcode)
    if parser is None:
        return None
    return parser(ReadDataStream(io.BytesIO(body)), len(body))


def _index_chain(data: bytes | mmap.mmap, start: int, end: int) -> list[MessageIndex]:
    """The message index records that end a damaged region [start, end) exactly, as they
    follow a chunk in the data section: the first offset from which well-formed message
    index records chain up to `end`."""
    offset = data.find(b"\x07", start, end)
    while offset != -1:
        chain = _chain_from(data, offset, end)
        if chain:
            return chain
        offset = data.find(b"\x07", offset + 1, end)
    return []


def _chain_from(data: bytes | mmap.mmap, offset: int, end: int) -> list[MessageIndex] | None:
    records = []
    while offset < end:
        if offset + _RECORD.size + _INDEX_HEAD.size > end:
            return None
        opcode, length = _RECORD.unpack_from(data, offset)
        body = offset + _RECORD.size
        if opcode != Opcode.MESSAGE_INDEX or body + length > end:
            return None
        _, pairs_length = _INDEX_HEAD.unpack_from(data, body)
        if pairs_length != length - _INDEX_HEAD.size or pairs_length % 16:
            return None
        stream = ReadDataStream(io.BytesIO(bytes(data[body : body + length])))
        records.append(MessageIndex.read(stream))
        offset = body + length
    return records


# ---------------------------------------------------------------------------------------------
# Writing what was read


class _Salvager:
    def __init__(self, target: BinaryIO, report: SalvageReport) -> None:
        self.target = target
        self.report = report
        self.writer: Writer | None = None
        self.schemas: dict[int, Schema] = {}
        self.schema_ids: dict[int, int] = {}  # input schema id -> output schema id
        self.channels: dict[int, Channel] = {}
        self.channel_ids: dict[int, int] = {}  # input channel id -> output channel id
        # The last chunk was dropped uncounted: the message indexes after it count its messages.
        self.count_from_indexes = False
        self.counted_by_index = False

    def start(self, header: Header) -> None:
        # Uncompressed: the copy is read once or twice and deleted; CPU matters more.
        self.writer = Writer(self.target, compression=CompressionType.NONE)
        self.writer.start(profile=header.profile, library=header.library)

    def adopt_summary(self, summary: Summary) -> None:
        """The summary's schemas and channels, for messages whose own were in a lost chunk."""
        for schema in summary.schemas.values():
            self.schemas.setdefault(schema.id, schema)
        for channel in summary.channels.values():
            self.channels.setdefault(channel.id, channel)

    def top_level(self, opcode: int, body: bytes) -> None:
        """One record of the data section, its bounds already checked."""
        if opcode == Opcode.CHUNK:
            self.chunk_body(body)
            return
        try:
            record = _parse(opcode, body)
        except Exception:  # sound bounds, garbled fields: that record only is lost
            self.report.corrupt_records += 1
            return
        if isinstance(record, MessageIndex):
            self.message_index(record)
        elif record is not None:
            self.count_from_indexes = False
            self.record(record)

    def record(self, record: McapRecord) -> None:
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

    def chunk_body(self, body: bytes) -> None:
        self.count_from_indexes = False
        head = _chunk_head(body)
        if head is None or len(head.chunk.data) != head.records_length:
            self.drop_uncounted()  # its fields do not fit inside its record
            return
        try:
            data, wrong_size = _chunk_data(head.chunk, validate_crc=True)
            records = _records_of(data)
        except chunk_limits.ChunkTooLargeError:
            self.report.oversized_chunks += 1
            self.drop_uncounted()  # what fits the cap is not kept: counted from its indexes
            return
        except Exception:  # CRC mismatch, or it does not decompress or parse
            self.report.corrupt_chunks += 1
            self.count_lost(head.chunk)
            return
        self.report.wrong_size_chunks += wrong_size
        for record in records:
            self.record(record)

    def partial_chunk(self, body: bytes) -> None:
        """A chunk cut short by the end of the file: its whole records before the cut."""
        head = _chunk_head(body)
        if head is None or head.chunk.compression not in _COMPRESSIONS:
            return
        try:
            data = _decompress_prefix(head.chunk)
        except Exception:  # damaged before the cut as well: nothing to trust
            return
        before = self.report.messages
        for record in _whole_records(data):
            self.record(record)
        self.report.partial_chunk_messages += self.report.messages - before

    def drop_uncounted(self) -> None:
        self.report.corrupt_chunks += 1
        self.report.uncountable_chunks += 1
        self.count_from_indexes, self.counted_by_index = True, False

    def count_lost(self, chunk: Chunk) -> None:
        try:
            records = _records_of(_chunk_data(chunk, validate_crc=False)[0])
        except Exception:
            self.report.uncountable_chunks += 1
            self.count_from_indexes, self.counted_by_index = True, False
            return
        inner = {r.id: r.topic for r in records if isinstance(r, Channel)}
        for record in records:
            if isinstance(record, Message):
                self.report.lost_by_topic[self.topic_of(record.channel_id, inner)] += 1

    def message_index(self, index: MessageIndex) -> None:
        """After a chunk dropped uncounted: its messages of one channel, by the index."""
        if not self.count_from_indexes:
            return
        if not self.counted_by_index:
            self.report.uncountable_chunks -= 1
            self.counted_by_index = True
        self.report.lost_by_topic[self.topic_of(index.channel_id, {})] += len(index.records)

    def topic_of(self, channel_id: int, inner: dict[int, str]) -> str:
        known = self.channels.get(channel_id)
        return known.topic if known is not None else inner.get(channel_id, "?")

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


# ---------------------------------------------------------------------------------------------
# Walking the file


class _Walker:
    """The file's top-level records in order, each read within its record's bounds."""

    def __init__(self, data: mmap.mmap, salvager: _Salvager, summary: Summary | None) -> None:
        self.data, self.size = data, len(data)
        self.salvager, self.report = salvager, salvager.report
        self.whole = data[-len(MCAP_MAGIC) :] == MCAP_MAGIC  # a length past it is damage
        self.chunk_lengths: dict[int, int] = {}  # chunk start -> chunk record length
        if summary is not None:
            self.chunk_lengths = {
                c.chunk_start_offset: c.chunk_length
                for c in summary.chunk_indexes
                if c.chunk_start_offset + c.chunk_length <= self.size
            }

    def run(self) -> None:
        position: int | None = len(MCAP_MAGIC)
        while position is not None and not self.report.complete:
            position = self.step(position)

    def step(self, position: int) -> int | None:
        """Read the record at `position`; the offset of the next one (None: stop)."""
        if position + _RECORD.size > self.size:
            return self.stop(_TRUNCATED if position < self.size else "no footer")
        opcode, length = _RECORD.unpack_from(self.data, position)
        end: int = position + _RECORD.size + length
        indexed = self.chunk_lengths.get(position)
        if indexed is not None and (opcode != Opcode.CHUNK or indexed != end - position):
            self.report.repaired_lengths += 1  # the index knows better than a damaged header
            opcode, end = Opcode.CHUNK, position + indexed
        if end > self.size or opcode == 0:
            return self.resync(position, opcode)
        body = bytes(self.data[position + _RECORD.size : end])
        if self.salvager.writer is None and opcode != Opcode.HEADER:
            return self.stop("the file does not start with a header record")
        self.salvager.top_level(opcode, body)  # write errors (OSError) are the caller's
        self.report.bytes_used = end
        return end

    def resync(self, position: int, opcode: int) -> int | None:
        """After a record whose length cannot be right: the next chunk the index knows, or the
        next well-formed one a scan finds; none: the file was cut in that record."""
        after = self.next_chunk(position)
        if after is None:
            if opcode == Opcode.CHUNK:
                self.salvager.partial_chunk(bytes(self.data[position + _RECORD.size :]))
            known = opcode in _PARSERS or opcode == Opcode.CHUNK
            if known and not self.whole:
                return self.stop(_TRUNCATED)
            return self.stop(f"a damaged record at byte {position}, and no valid chunk after it")
        self.report.skipped_regions += 1
        self.report.skipped_bytes += after - position
        indexes = _index_chain(self.data, position + _RECORD.size, after)
        if opcode == Opcode.CHUNK or indexes:  # a chunk lost: its indexes count its messages
            self.salvager.drop_uncounted()
            for index in indexes:
                self.salvager.message_index(index)
        return after

    def next_chunk(self, position: int) -> int | None:
        known = [start for start in self.chunk_lengths if start > position]
        if known:
            return min(known)
        offset = self.data.find(b"\x06", position + 1)
        while offset != -1:
            if _is_chunk_at(self.data, offset, self.size):
                return offset
            offset = self.data.find(b"\x06", offset + 1)
        return None

    def stop(self, reason: str) -> int | None:
        """Reading ends here, for `reason` (returns None, the end of `run`'s loop)."""
        self.report.stop_reason = reason
        return None


def _summary_of(file: BinaryIO) -> Summary | None:
    """The summary of a file that still ends with its footer, None otherwise (or damaged)."""
    if not is_complete(file):
        return None
    try:
        file.seek(0)
        summary: Summary | None = SeekingReader(file, validate_crcs=True).get_summary()
    except Exception:
        return None
    return summary


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
        report = SalvageReport(file_size=size)
        salvager = _Salvager(target, report)
        summary = _summary_of(file)
        if summary is not None:
            salvager.adopt_summary(summary)
        if size > len(MCAP_MAGIC):
            with mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ) as data:
                if data[: len(MCAP_MAGIC)] == MCAP_MAGIC:
                    _Walker(data, salvager, summary).run()
                else:
                    report.stop_reason = "the file does not start with the MCAP magic"
        if salvager.writer is None:
            raise SourceError(
                f"{source}: nothing to recover: not even the MCAP header can be read "
                f"({report.stop_reason or 'empty'})"
            )
        salvager.finish()
    _count_known(report, summary)
    return report


def _count_known(report: SalvageReport, summary: Summary | None) -> None:
    if summary is not None and summary.statistics is not None:
        report.known_messages = summary.statistics.message_count
        report.known_from = "the Statistics record"
    else:
        report.known_messages = report.messages + sum(report.lost_by_topic.values())
        report.known_from = "the records read"
