"""MCAP files of any profile: ROS 2 (cdr), ROS 1 (ros1), Foxglove protobuf and Foxglove JSON.

Indexed files (a summary with chunk indexes) are read chunk by chunk in log-time order, so a time
range only touches the chunks that overlap it. Files without an index (written without chunks, or
with the summary switched off) are streamed from the start; see `McapSource.image_messages` for how
their order is restored.

Damage is reported, never read around: a file cut short (it does not end with a footer and the
magic) raises SourceError as soon as it is listed or read, a chunk whose CRC does not match its
data raises SourceError when it is read, and records are never trusted to be larger than the
file. `salvage.salvage_mcap` (annotate --recover) is the way to use what such a file still holds.
"""

from __future__ import annotations

import base64
import contextlib
import errno
import functools
import heapq
import inspect
import io
import json
import struct
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import IO, Any

from mcap.exceptions import EndOfFile, InvalidMagic, McapError, RecordLengthLimitExceeded
from mcap.reader import McapReader, NonSeekingReader, SeekingReader
from mcap.records import Channel, Chunk, Message, MessageIndex, Schema
from mcap.stream_reader import CRCValidationError, StreamReader, breakup_chunk
from mcap.summary import Summary

from doseqslam_logs.errors import DoseqslamError, NoCameraError, SourceError
from doseqslam_logs.sources.base import (
    MCAP_MAGIC,
    ChannelInfo,
    DecodedMessage,
    ImageMessage,
    Promise,
    SideMessage,
)
from doseqslam_logs.sources.chunk_limits import ChunkTooLargeError, check_chunk_size
from doseqslam_logs.sources.handles import HandlePool
from doseqslam_logs.sources.images import RecordInfo, image_from_payload, is_image_type
from doseqslam_logs.sources.mcap_index import indexed_topic_messages

Deserializer = Callable[[bytes], Any]
_Record = tuple[Schema | None, Channel, Message]

# How many image messages an unindexed file may hold back to restore log-time order. Out-of-order
# writes come from several recorder threads and are displaced by a few messages at most; a window
# of images (not bytes) keeps memory at a few dozen frames.
REORDER_WINDOW = 64

# mcap 1.6 renamed the time bounds (start_time/end_time still work but warn).
_NEW_TIME_NAMES = "starting_at" in inspect.signature(SeekingReader.iter_messages).parameters

_FOOTER = b"\x02" + (20).to_bytes(8, "little")  # opcode and length of the footer record
RECOVER_HINT = "annotate --recover uses every complete message it holds"


# ---------------------------------------------------------------------------------------------
# Deserializers, one per (message encoding, schema encoding)


def _ros2msg(schema: Schema) -> Deserializer:
    from mcap_ros2.decoder import DecoderFactory

    decoder: Deserializer | None = DecoderFactory().decoder_for("cdr", schema)
    if decoder is None:
        raise ValueError("mcap_ros2 has no decoder for it")
    return decoder


def _idl_sections(text: str) -> list[str]:
    """The IDL texts in a ros2idl schema: rosbag2 writes the type and each dependency as one
    section, headed by a line of 80 '=' and a line 'IDL: pkg/msg/Type'."""
    sections = []
    for part in text.split("=" * 80 + "\n"):
        body = part.partition("\n")[2] if part.startswith("IDL: ") else part
        if body.strip():
            sections.append(body)
    return sections


def _ros2idl(schema: Schema) -> Deserializer:
    # mcap_ros2 only reads .msg schemas, so IDL schemas go through rosbags.
    from rosbags.typesys import Stores, get_types_from_idl, get_typestore

    types: dict[str, Any] = {}
    for section in _idl_sections(schema.data.decode()):
        types.update(get_types_from_idl(section))
    store = get_typestore(Stores.EMPTY)
    store.register(types)  # all at once: a section may use types from a later one
    name = schema.name
    return lambda payload: store.deserialize_cdr(payload, name)


def _ros1msg(schema: Schema) -> Deserializer:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    from rosbags.typesys.msg import normalize_msgtype

    # One store per schema: ROS 1 and ROS 2 definitions of e.g. std_msgs/Header differ, and
    # rosbags refuses to hold two definitions under one name.
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(schema.data.decode(), schema.name))
    name = normalize_msgtype(schema.name)
    return lambda payload: store.deserialize_ros1(payload, name)


def _protobuf(schema: Schema) -> Deserializer:
    from mcap_protobuf.decoder import DecoderFactory

    decoder: Deserializer | None = DecoderFactory().decoder_for("protobuf", schema)
    if decoder is None:
        raise ValueError("mcap_protobuf has no decoder for it")
    return decoder


def _json_message(payload: bytes) -> SimpleNamespace:
    """A Foxglove JSON message with the attribute names of the protobuf one: base64 `data`
    becomes bytes and `timestamp` {sec, nsec} an object."""
    fields = dict(json.loads(payload))
    if isinstance(fields.get("data"), str):
        fields["data"] = base64.b64decode(fields["data"], validate=True)
    stamp = fields.get("timestamp")
    fields["timestamp"] = SimpleNamespace(**stamp) if isinstance(stamp, dict) else None
    return SimpleNamespace(**fields)


def _json(schema: Schema) -> Deserializer:
    return _json_message


DESERIALIZERS: dict[tuple[str, str], Callable[[Schema], Deserializer]] = {
    ("cdr", "ros2msg"): _ros2msg,
    ("cdr", "ros2idl"): _ros2idl,
    ("ros1", "ros1msg"): _ros1msg,
    ("protobuf", "protobuf"): _protobuf,
    ("json", "jsonschema"): _json,
}


# ---------------------------------------------------------------------------------------------
# Channel statistics


@dataclass
class _ChannelStats:
    channel: Channel
    type_name: str
    count: int = 0
    first: int | None = None
    last: int | None = None

    def add_times(self, times: Iterable[int]) -> None:
        for time in times:
            self.count += 1
            self.first = time if self.first is None else min(self.first, time)
            self.last = time if self.last is None else max(self.last, time)


def _type_name(schemas: dict[int, Schema], channel: Channel) -> str:
    schema = schemas.get(channel.schema_id)
    return schema.name if schema is not None else ""


def _stats_from_index(
    file: IO[bytes], summary: Summary, size_limit: int
) -> list[_ChannelStats] | None:
    """Counts and first/last times from the message index records, without reading any chunk;
    None when the file has no message indexes."""
    chunks = summary.chunk_indexes
    if not chunks or any(not chunk.message_index_offsets for chunk in chunks):
        return None
    stats = {
        cid: _ChannelStats(channel, _type_name(summary.schemas, channel))
        for cid, channel in summary.channels.items()
    }
    for chunk in chunks:
        for cid, offset in chunk.message_index_offsets.items():
            file.seek(offset)
            index = next(StreamReader(file, skip_magic=True, record_size_limit=size_limit).records)
            if not isinstance(index, MessageIndex) or cid not in stats:
                return None
            stats[cid].add_times(time for time, _ in index.records)
    if summary.statistics is not None:
        for cid, entry in stats.items():
            entry.count = summary.statistics.channel_message_counts.get(cid, 0)
    return list(stats.values())


@dataclass
class _StreamTally:
    """What one pass over every record finds: the channels' messages, and what the message
    index records after each chunk say the chunks hold (`indexed`: every chunk has them)."""

    stats: dict[int, _ChannelStats]
    index_counts: Counter[int]
    indexed: bool


def _tally_stream(file: IO[bytes], size_limit: int) -> _StreamTally:
    """Counts and first/last times by one pass over every record (chunks are decompressed one
    at a time, so memory stays at one chunk)."""
    file.seek(0)
    schemas: dict[int, Schema] = {}
    stats: dict[int, _ChannelStats] = {}
    index_counts: Counter[int] = Counter()
    chunks = indexed_chunks = 0
    # Chunks are emitted whole so that each one's message indexes can be told apart; the
    # data section's CRC is still checked by the reader, each chunk's by breakup_chunk.
    reader = StreamReader(file, validate_crcs=True, emit_chunks=True, record_size_limit=size_limit)
    for outer in reader.records:
        if isinstance(outer, Chunk):
            chunks += 1
        elif isinstance(outer, MessageIndex):
            # A chunk's indexes follow it: count each chunk once, at its first index.
            indexed_chunks += indexed_chunks < chunks
            index_counts[outer.channel_id] += len(outer.records)
        inner = breakup_chunk(outer, validate_crc=True) if isinstance(outer, Chunk) else [outer]
        for record in inner:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel) and record.id not in stats:
                stats[record.id] = _ChannelStats(record, _type_name(schemas, record))
            elif isinstance(record, Message):
                if record.channel_id not in stats:
                    raise ValueError(f"a message refers to the unknown channel {record.channel_id}")
                stats[record.channel_id].add_times((record.log_time,))
    return _StreamTally(stats, index_counts, chunks > 0 and indexed_chunks == chunks)


def _index_counts_by_topic(tally: _StreamTally) -> Counter[str] | None:
    """The message indexes' counts by topic (None unless every chunk has its indexes)."""
    if not tally.indexed:
        return None
    counts: Counter[str] = Counter()
    for cid, count in tally.index_counts.items():
        entry = tally.stats.get(cid)
        if entry is not None:
            counts[entry.channel.topic] += count
    return counts


def _topic_info(topic: str, group: list[_ChannelStats]) -> ChannelInfo:
    firsts = [s.first for s in group if s.first is not None]
    lasts = [s.last for s in group if s.last is not None]
    return ChannelInfo(
        topic=topic,
        # Several channels may share a topic (one per publisher); they normally share a type.
        message_type=", ".join(dict.fromkeys(s.type_name for s in group)),
        message_encoding=", ".join(dict.fromkeys(s.channel.message_encoding for s in group)),
        message_count=sum(s.count for s in group),
        first_log_time_ns=min(firsts) if firsts else None,
        last_log_time_ns=max(lasts) if lasts else None,
        is_image=any(is_image_type(s.type_name) for s in group),
    )


def _group_by_topic(stats: list[_ChannelStats]) -> list[ChannelInfo]:
    by_topic: dict[str, list[_ChannelStats]] = {}
    for entry in stats:
        by_topic.setdefault(entry.channel.topic, []).append(entry)
    return [_topic_info(topic, group) for topic, group in by_topic.items()]


# ---------------------------------------------------------------------------------------------
# Reading


def _iter_topic(
    reader: McapReader,
    topics: str | Sequence[str],
    start_ns: int | None,
    end_ns: int | None,
    ordered: bool,
) -> Iterator[_Record]:
    names = [topics] if isinstance(topics, str) else list(topics)
    if _NEW_TIME_NAMES:
        return reader.iter_messages(
            topics=names, log_time_order=ordered, starting_at=start_ns, ending_before=end_ns
        )
    return reader.iter_messages(
        topics=names, start_time=start_ns, end_time=end_ns, log_time_order=ordered
    )


def in_log_time_order(records: Iterable[_Record], window: int) -> Iterator[_Record]:
    """Restore log-time order in a stream that is sorted up to `window` messages.

    A heap holds at most `window` messages; a message that was written more than `window`
    messages later than its log time would place it comes out late, i.e. out of order.
    Equal log times keep their file order.
    """
    heap: list[tuple[int, int, _Record]] = []
    for position, record in enumerate(records):
        item = (record[2].log_time, position, record)
        if len(heap) < window:
            heapq.heappush(heap, item)
        else:
            yield heapq.heappushpop(heap, item)[2]
    while heap:
        yield heapq.heappop(heap)[2]


def describe_read_error(exc: BaseException) -> str:
    """One line saying what is wrong with the file, from an exception of the mcap library (or
    of a decompressor, struct, ...) raised while reading it."""
    if isinstance(exc, ChunkTooLargeError):
        return str(exc)
    if isinstance(exc, EndOfFile):
        return "the file ends in the middle of a record: truncated?"
    if isinstance(exc, CRCValidationError):
        return f"a {type(exc.record).__name__.lower()} fails its CRC check: the file is corrupt"
    if isinstance(exc, RecordLengthLimitExceeded):
        return "a record claims to be larger than the file: the file is corrupt"
    if isinstance(exc, InvalidMagic):
        return "the MCAP magic is missing where it belongs: the file is corrupt"
    if isinstance(exc, MemoryError):
        return "a record claims an impossible size: the file is corrupt"
    words = _corrupt_structure(exc)
    if words is not None:
        return f"{words}: the file is corrupt"
    text = " ".join(str(exc).split())
    if len(text) > 200:
        text = text[:200] + "..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


# What Python (not the mcap library) raises when a record's fields are damaged, in our words:
# the parser read a length or offset that points nowhere, or text that is not text.
_BAD_OFFSET_TEXTS = ("read length must be non-negative", "negative seek value", "offset-sized")


def _corrupt_structure(exc: BaseException) -> str | None:
    """What is damaged, for the exceptions a damaged record makes the parser raise; None for
    any other exception."""
    if isinstance(exc, UnicodeDecodeError):
        return "a record holds a name or text that is not UTF-8"
    if isinstance(exc, struct.error):
        return "a record is shorter than its fields"
    if isinstance(exc, OverflowError) or (
        isinstance(exc, ValueError) and any(t in str(exc) for t in _BAD_OFFSET_TEXTS)
    ):
        return "a record's length or offset is impossible"
    if isinstance(exc, OSError) and exc.errno == errno.EINVAL:
        return "a record's offset points outside the file"
    if isinstance(exc, SystemError) and "Negative size" in str(exc):
        return "a record's length is shorter than its own header"
    if type(exc).__module__.split(".")[0] in ("zstandard", "lz4", "_lz4") or (
        isinstance(exc, RuntimeError) and str(exc).startswith("LZ4")
    ):
        return "a chunk does not decompress"
    if type(exc) is McapError:  # ours (mcap_index) and the library's, in words already
        return " ".join(str(exc).split())
    return None


def is_complete(file: IO[bytes]) -> bool:
    """Whether the file ends with a footer record and the closing magic, as every finished
    MCAP does; a recording cut short (power loss, full disk, killed recorder) does not."""
    size = file.seek(0, 2)
    if size < 2 * len(MCAP_MAGIC) + 29:
        return False
    file.seek(size - len(MCAP_MAGIC) - 29)
    tail = file.read(29 + len(MCAP_MAGIC))
    return tail.endswith(MCAP_MAGIC) and tail.startswith(_FOOTER)


def _close_handle(file: IO[bytes]) -> None:
    file.close()


class McapSource:
    """An MCAP file, opened read-only.

    Raises (constructor):
        SourceError: the file cannot be opened or does not start with the MCAP magic.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self._file: IO[bytes] = open(self.path, "rb")  # noqa: SIM115 - closed by close()
        except OSError as exc:
            raise SourceError(f"{self.path}: cannot open ({exc.strerror or exc})") from exc
        try:
            self.size = self._file.seek(0, 2)
            self.complete = is_complete(self._file)
            self._summary = self._read_summary()
        except BaseException:
            self._file.close()
            raise
        # Every read borrows a handle: the one opened here, another only for reads at once.
        self._handles: HandlePool[IO[bytes]] = HandlePool(
            self._open_handle, _close_handle, first=self._file
        )
        self._channels: list[ChannelInfo] | None = None
        # Without a summary: messages per topic by the message index records, when every chunk
        # has them (None: no chunks, or some without; set by channels()).
        self._index_counts: Counter[str] | None = None
        self._deserializers: dict[tuple[int, str], Deserializer] = {}

    def _open_handle(self) -> IO[bytes]:
        return open(self.path, "rb")  # closed by the pool

    @property
    def handles_opened(self) -> int:
        """How many times this source opened its file (for tests and benchmarks)."""
        return self._handles.opened

    def _reader(self, file: IO[bytes]) -> SeekingReader:
        return SeekingReader(file, validate_crcs=True, record_size_limit=max(self.size, 1))

    def _read_summary(self) -> Summary | None:
        try:
            self._file.seek(0)
            reader = self._reader(self._file)
        except Exception as exc:
            raise SourceError(
                f"{self.path}: not an MCAP file ({describe_read_error(exc)})"
            ) from exc
        if not self.complete:
            return None  # cut short: channels() and image_messages() say so
        try:
            summary: Summary | None = reader.get_summary()
        # A damaged summary: streaming still reads the data section.
        except Exception:
            return None
        return summary

    def _check_complete(self) -> None:
        if not self.complete:
            raise SourceError(
                f"{self.path}: truncated MCAP file: it ends after {self.size} bytes without a "
                f"footer (recording cut short?); {RECOVER_HINT}"
            )

    def _check_chunk_sizes(self) -> None:
        """Refuse a chunk over the cap from the chunk index, before anything is decompressed
        (without an index each chunk's own header is checked as it is read)."""
        for chunk in self._summary.chunk_indexes if self._summary is not None else []:
            try:
                check_chunk_size(chunk.uncompressed_size)
            except ChunkTooLargeError as exc:
                raise SourceError(f"{self.path}: {exc}; {RECOVER_HINT}") from exc

    @property
    def summary(self) -> Summary | None:
        """The file's summary section as read when it was opened (None: cut short, damaged,
        or written without one)."""
        return self._summary

    @property
    def indexed(self) -> bool:
        """Whether the file has chunk indexes, so that reading can seek."""
        return self._summary is not None and bool(self._summary.chunk_indexes)

    def channels(self) -> list[ChannelInfo]:
        """Every topic of the file, with counts and first/last log times.

        Counts come from the statistics record and times from the message indexes when the file
        has them; otherwise one pass over the file counts them.

        Raises:
            SourceError: the file is corrupt or truncated.
        """
        self._check_complete()
        self._check_chunk_sizes()
        if self._channels is None:
            limit = max(self.size, 1)
            try:
                stats = None
                with self._handles.borrowed() as file:
                    if self._summary:
                        stats = _stats_from_index(file, self._summary, limit)
                    if stats is None:
                        tally = _tally_stream(file, limit)
                        stats = list(tally.stats.values())
                        self._index_counts = _index_counts_by_topic(tally)
            except Exception as exc:
                raise SourceError(
                    f"{self.path}: cannot list the channels ({describe_read_error(exc)}); "
                    f"{RECOVER_HINT}"
                ) from exc
            self._channels = _group_by_topic(stats)
        return list(self._channels)

    def promised_messages(self, topic: str) -> Promise | None:
        """The count of the Statistics record for `topic`; without a summary, that of the
        message index records that follow every chunk (None without either: cut short, no
        indexes). A record the data section no longer holds (e.g. its opcode flipped, which a
        reader must skip as an unknown record, or messages swallowed by one whose length is
        shorter than its header) is missing against it."""
        statistics = self._summary.statistics if self._summary is not None else None
        if statistics is not None:
            assert self._summary is not None
            ids = [cid for cid, ch in self._summary.channels.items() if ch.topic == topic]
            count = sum(statistics.channel_message_counts.get(cid, 0) for cid in ids)
            return Promise(count, "the Statistics record")
        if self._summary is not None:
            return None
        self.channels()  # one pass, which also reads the message indexes
        if self._index_counts is None or topic not in self._index_counts:
            return None
        return Promise(self._index_counts[topic], "the message index")

    def unattributed_messages(self) -> int:
        """0: a message of an undeclared channel makes the file unreadable (SourceError)."""
        return 0

    def image_messages(
        self, topic: str, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[ImageMessage]:
        """The image messages of `topic` with log time in [start_ns, end_ns), in log-time order.

        Unindexed files are streamed and re-sorted within `REORDER_WINDOW` messages (see
        `in_log_time_order`): files written by a single recorder are in order already.
        A message that does not deserialize is yielded with `decode_error` set.

        Raises:
            NoCameraError: `topic` (exact name) is not an image topic of this file (at call time).
            SourceError: while iterating, the file is corrupt or truncated, or the channel's
                message/schema encoding is not supported or its schema does not parse.
        """
        self._check_image_topic(topic)
        messages = self._images(topic, (), start_ns, end_ns)
        return (m for m in messages if isinstance(m, ImageMessage))  # no side topic: all are

    def image_and_side_messages(
        self,
        topic: str,
        side_topics: Sequence[str],
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[ImageMessage | SideMessage]:
        """`image_messages` of `topic` and the messages of `side_topics` in one pass: through
        the message indexes, each chunk is read once for them all."""
        self._check_image_topic(topic)
        return self._images(topic, tuple(side_topics), start_ns, end_ns)

    def _check_image_topic(self, topic: str) -> None:
        image_topics = [c.topic for c in self.channels() if c.is_image]
        if topic not in image_topics:
            raise NoCameraError(
                f"{self.path}: {topic!r} is not an image topic (image topics: "
                f"{', '.join(image_topics) or 'none'})"
            )

    def _images(
        self, topic: str, side_topics: tuple[str, ...], start_ns: int | None, end_ns: int | None
    ) -> Iterator[ImageMessage | SideMessage]:
        if start_ns is not None and end_ns is not None and start_ns >= end_ns:
            return
        try:
            records = self._lent_records((topic, *side_topics), start_ns, end_ns)
            for schema, channel, message in records:
                if channel.topic != topic:
                    decode = functools.partial(self._decode, schema, channel, message)
                    yield SideMessage(channel.topic, message.log_time, decode)
                elif schema is not None and is_image_type(schema.name):
                    yield self._to_image(schema, channel, message)
        except DoseqslamError:
            raise
        except Exception as exc:
            raise SourceError(
                f"{self.path}: cannot read the messages of {topic} ({describe_read_error(exc)}); "
                f"{RECOVER_HINT}"
            ) from exc

    def raw_messages(
        self, topic: str, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[tuple[int, bytes]]:
        """(log time, message bytes as stored) of `topic` in [start_ns, end_ns), log-time order.

        Raises SourceError (while iterating) for a damaged file.
        """
        with self._reading(topic):
            for _, _, message in self._lent_records(topic, start_ns, end_ns):
                yield message.log_time, bytes(message.data)

    def messages(self, topic: str) -> Iterator[DecodedMessage]:
        """Every message of `topic` in log-time order, decoded with the file's schema.

        Raises SourceError (while iterating) for a damaged file or an unsupported encoding.
        """
        self._check_complete()
        with self._reading(topic):
            for schema, channel, message in self._lent_records(topic, None, None):
                yield self._decode(schema, channel, message)

    def _decode(self, schema: Schema | None, channel: Channel, message: Message) -> DecodedMessage:
        """One message decoded (`decode_error` when it is damaged); SourceError when its topic
        cannot be decoded at all (no schema, an unsupported schema)."""
        if schema is None:
            raise SourceError(f"{self.path}: topic {channel.topic!r} has no schema")
        deserialize = self._deserializer(schema, channel)  # a bad schema: the topic's
        try:
            decoded = deserialize(message.data)
        except Exception as exc:  # any deserializer, any damage: this message only
            problem = describe_read_error(exc)
            return DecodedMessage(message.log_time, schema.name, None, problem)
        return DecodedMessage(message.log_time, schema.name, decoded)

    @contextlib.contextmanager
    def _reading(self, topic: str) -> Iterator[None]:
        """Damage found while reading `topic`'s messages, as one SourceError in our words."""
        try:
            yield
        except DoseqslamError:
            raise
        except Exception as exc:
            raise SourceError(
                f"{self.path}: cannot read the messages of {topic} ({describe_read_error(exc)})"
            ) from exc

    def _lent_records(
        self, topics: str | Sequence[str], start_ns: int | None, end_ns: int | None
    ) -> Iterator[_Record]:
        """`_records` on a handle of their own, lent by the pool and given back when they end
        (or are dropped)."""
        with self._handles.borrowed() as file:
            yield from self._records(file, topics, start_ns, end_ns)

    def _records(
        self,
        file: IO[bytes],
        topics: str | Sequence[str],
        start_ns: int | None,
        end_ns: int | None,
    ) -> Iterator[_Record]:
        if self.indexed:
            assert self._summary is not None
            by_index = indexed_topic_messages(file, self._summary, topics, start_ns, end_ns)
            if by_index is not None:
                return by_index
            seeking = self._reader(file)
            # SeekingReader re-parses the summary section on its first call (tens of ms for the
            # chunk and message indexes of an hour-long log): once per ranged read of the
            # verification stage, more than the frames themselves. The summary was read and
            # checked when the file was opened; hand it over (mcap's reader caches it in
            # `_summary`; should that attribute go, it reads it again, correctly, just slower).
            if getattr(seeking, "_summary", False) is None:
                seeking._summary = self._summary
            return _iter_topic(seeking, topics, start_ns, end_ns, ordered=True)
        # NonSeekingReader with log_time_order=True would sort the whole file in memory. It
        # reads from where the handle stands: a borrowed handle stands where its last read left.
        file.seek(0)
        reader = NonSeekingReader(file, validate_crcs=True, record_size_limit=max(self.size, 1))
        stream = _iter_topic(reader, topics, start_ns, end_ns, ordered=False)
        return in_log_time_order(stream, REORDER_WINDOW)

    def _to_image(self, schema: Schema, channel: Channel, message: Message) -> ImageMessage:
        record = RecordInfo(channel.topic, message.log_time, message.publish_time, message.sequence)
        deserialize = self._deserializer(schema, channel)
        return image_from_payload(schema.name, message.data, deserialize, record)

    def _deserializer(self, schema: Schema, channel: Channel) -> Deserializer:
        key = (schema.id, channel.message_encoding)
        if key not in self._deserializers:
            build = DESERIALIZERS.get((channel.message_encoding, schema.encoding))
            if build is None:
                supported = ", ".join(f"{m}/{s}" for m, s in DESERIALIZERS)
                raise SourceError(
                    f"{self.path}: {channel.topic} uses message encoding "
                    f"{channel.message_encoding!r} with schema encoding {schema.encoding!r}, "
                    f"which is not supported (supported: {supported})"
                )
            try:
                # mcap_ros2's message parser prints its complaint before raising it.
                with contextlib.redirect_stderr(io.StringIO()):
                    self._deserializers[key] = build(schema)
            except Exception as exc:
                raise SourceError(
                    f"{self.path}: cannot parse the {schema.encoding} schema {schema.name} of "
                    f"{channel.topic} ({describe_read_error(exc)})"
                ) from exc
        return self._deserializers[key]

    def close(self) -> None:
        """Close the file; iterators already started keep their handle until they end."""
        self._handles.close()

    def __enter__(self) -> McapSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
