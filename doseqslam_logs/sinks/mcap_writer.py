"""Write the annotated MCAP: every record of the input, plus our loop-closure channels.

Inputs are MCAP files of any profile, ROS 1 bags and rosbag2 bags (sqlite3 or MCAP storage).
The input is streamed record by record (memory bounded by one chunk), its records are copied
unchanged, and our messages are interleaved by log time. Our channels use the encoding of the
input's profile (see `encoders`). The output appears atomically (see `atomic`) and is
byte-identical for the same input and annotations.
"""

from __future__ import annotations

import contextlib
import os
from collections import Counter
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, Literal, Protocol, TypeVar

import zstandard
from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import Writer
from rosbags.interfaces import Connection, ConnectionExtRosbag1, MessageDefinitionFormat
from rosbags.rosbag1 import Reader as Ros1Reader
from rosbags.rosbag2 import Reader as Ros2Reader
from rosbags.rosbag2.metadata import dump_qos_v8
from rosbags.rosbag2.reader import DirectoryReader
from rosbags.rosbag2.storage_mcap import McapReader as Ros2McapStorage
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from .. import __version__
from ..annotations.records import (
    FRAME_TIMES_ATTACHMENT,
    FRAME_TIMES_MEDIA_TYPE,
    MESSAGE_TYPES,
    METADATA_NAME,
    OUR_TOPIC_PREFIX,
    FrameTimes,
    MessageType,
    TimedMessage,
)
from ..annotations.writer import (
    MetricPoses,
    Verifications,
    loop_closure_messages,
    sequence_messages,
)
from ..detector.events import SequenceDecision
from ..errors import DoseqslamError, OutputError, SourceError
from ..sources import (
    chunk_limits,  # noqa: F401 - the input's chunks are copied within the cap
    refuse_stream,
)
from ..sources.base import MCAP_MAGIC, ROS1_MAGIC, SQLITE_MAGIC, Source
from .atomic import atomic_output
from .encoders import MessageEncoder, encoder_for_profile
from .message_spool import SpooledMessages, in_order
from .output_format import COMPRESSIONS, OutputFormat
from .visual_encoders import visual_encoder_for_profile
from .visualization import Visualization, VisualWriter

LIBRARY = f"doseqslam-logs/{__version__}"

InputKind = Literal["mcap", "ros1-bag", "rosbag2"]
T = TypeVar("T")


@dataclass(frozen=True)
class Annotations:
    """What to add to the log: our messages (any order; the writer sorts them) and metadata."""

    messages: Sequence[TimedMessage]
    metadata: Mapping[str, str]  # the `doseqslam` metadata record: version, parameters, ...
    frame_times: FrameTimes | None = None  # written as the FRAME_TIMES_ATTACHMENT
    visualization: Visualization | None = None  # None: no visualization channels

    def __post_init__(self) -> None:
        """Raises TypeError when the metadata is not a mapping of strings to strings."""
        items = self.metadata.items()
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in items):
            raise TypeError(f"the {METADATA_NAME} metadata must map strings to strings")

    @classmethod
    def from_decisions(
        cls,
        decisions: Sequence[SequenceDecision],
        frame_times: FrameTimes,
        method: str,
        parameters_hash: str,
        metadata: Mapping[str, str],
        verifications: Verifications = None,
        metric: MetricPoses = None,
        spool: bool = False,
    ) -> Annotations:
        """Loop-closure and sequence messages for these `SequenceDecision`s (and their
        verification and metric poses, None when it was off). With `spool`, the messages are
        kept in a temporary file until written (`SpooledMessages`: memory flat in their
        number); `close` removes it.

        Raises ValueError when a decision names a frame outside `frame_times`.
        """
        v = verifications

        def one_at_a_time() -> Iterator[TimedMessage]:  # the order of the lists as a whole
            hash_ = parameters_hash
            for decision in decisions:
                yield from loop_closure_messages([decision], frame_times, method, hash_, v, metric)
            for decision in decisions:
                yield from sequence_messages([decision], frame_times, method, hash_, v)

        messages = SpooledMessages(one_at_a_time()) if spool else list(one_at_a_time())
        return cls(messages, metadata, frame_times)

    def close(self) -> None:
        """Removes the messages' temporary file, if they are spooled (`from_decisions`)."""
        if isinstance(self.messages, SpooledMessages):
            self.messages.close()


@dataclass(frozen=True)
class InputLog:
    """What `detect_input` found: the kind of log, the path to read and the MCAP profile."""

    kind: InputKind
    path: Path  # for a rosbag2 folder holding one plain MCAP file: that file
    profile: str


@dataclass
class WriteSummary:
    """What `write_annotated_mcap` wrote."""

    output_path: Path
    input_kind: InputKind
    profile: str
    copied_messages: int = 0  # input messages copied (0 for a sidecar)
    written: dict[str, int] = field(default_factory=dict)  # our messages per topic
    replaced_topics: list[str] = field(default_factory=list)  # input /doseqslam/ channels
    visualized: dict[str, int] = field(default_factory=dict)  # visualization messages per topic


class _Storage(Protocol):
    """The part of a rosbags storage reader (sqlite3, MCAP) used here."""

    connections: list[Connection]

    def messages(
        self,
        connections: Collection[Connection],
        start: int | None = None,
        stop: int | None = None,
    ) -> Iterator[tuple[Connection, int, bytes]]: ...


def detect_input(input_path: str | os.PathLike[str]) -> InputLog:
    """The kind of log at `input_path`, from its magic bytes (or being a rosbag2 folder).

    Raises SourceError when the path is missing, unreadable or not a supported log.
    """
    path = Path(input_path)
    refuse_stream(path)
    if path.is_dir():
        return _detect_rosbag2_folder(path)
    try:
        with path.open("rb") as stream:
            head = stream.read(len(SQLITE_MAGIC))
            if head.startswith(MCAP_MAGIC):  # its profile from the same open: one open, not two
                stream.seek(0)
                return InputLog("mcap", path, _mcap_profile_of(path, stream))
    except OSError as exc:  # the profile's read errors are SourceErrors (reading_errors)
        raise SourceError(f"{path}: cannot open the log: {exc.strerror or exc}") from exc
    if head.startswith(ROS1_MAGIC):
        return InputLog("ros1-bag", path, "ros1")
    if head.startswith(SQLITE_MAGIC):
        has_metadata = (path.parent / "metadata.yaml").is_file()
        return InputLog("rosbag2", path.parent if has_metadata else path, "ros2")
    raise SourceError(f"{path}: not an MCAP file, ROS 1 bag or rosbag2 bag")


def _detect_rosbag2_folder(path: Path) -> InputLog:
    if not (path / "metadata.yaml").is_file():
        raise SourceError(f"{path}: a folder without metadata.yaml is not a rosbag2 bag")
    with _open_bag(path, Ros2Reader) as reader:
        storage = reader.storage
        if (
            isinstance(storage, DirectoryReader)
            and not reader.compression_mode
            and len(storage.storages) == 1
            and isinstance(storage.storages[0], Ros2McapStorage)
        ):
            # One plain MCAP file: copy it at the MCAP level, which keeps every record.
            mcap_path = Path(str(storage.storages[0].path))
            return InputLog("mcap", mcap_path, _read_mcap_profile(mcap_path))
    return InputLog("rosbag2", path, "ros2")


def mcap_profile(input_path: str | os.PathLike[str]) -> str:
    """The MCAP profile of the output for this input: the MCAP header's profile, "ros1" for a
    ROS 1 bag, "ros2" for a rosbag2 bag. Raises SourceError when the input is not a log."""
    return detect_input(input_path).profile


def _read_mcap_profile(path: Path) -> str:
    with reading_errors(path), path.open("rb") as stream:
        return _mcap_profile_of(path, stream)


def _mcap_profile_of(path: Path, stream: BinaryIO) -> str:
    """The profile of the MCAP header at the start of `stream`."""
    with reading_errors(path):
        header = next(iter(StreamReader(stream).records))
    profile = getattr(header, "profile", None)
    if not isinstance(profile, str):
        raise SourceError(f"{path}: the MCAP file does not start with a header record")
    return profile


class reading_errors:
    """Context manager: failures while reading the input become one-line SourceErrors."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __enter__(self) -> None:
        return None

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, _: Any) -> None:
        if exc is None or isinstance(exc, DoseqslamError) or not isinstance(exc, Exception):
            return
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SourceError(f"{self.path}: cannot read the log: {message}") from exc


class _Openable(Protocol):
    def open(self) -> None: ...

    def close(self) -> None: ...


R = TypeVar("R", bound=_Openable)


@contextlib.contextmanager
def _open_bag(path: Path, factory: Callable[[Path], R]) -> Iterator[R]:
    """An open rosbags reader; only opening it counts as reading (SourceError)."""
    with reading_errors(path):
        reader = factory(path)
        reader.open()
    try:
        yield reader
    finally:
        with contextlib.suppress(Exception):
            reader.close()


def guarded_reads(path: Path, items: Iterable[T]) -> Iterator[T]:
    """`items`, with any failure while producing them raised as SourceError."""
    iterator = iter(items)
    while True:
        with reading_errors(path):
            try:
                item = next(iterator)
            except StopIteration:
                return
        yield item


def input_records(path: Path) -> Iterator[object]:
    """The records of an MCAP file to copy, read errors as SourceError (`guarded_reads`).

    CRCs are checked: a corrupt chunk of any topic must fail the copy (or be left to
    --recover), never be written out again under a fresh, valid CRC.
    """
    with reading_errors(path):
        stream = path.open("rb")
    with stream:
        yield from guarded_reads(path, StreamReader(stream, validate_crcs=True).records)


def refuse_same_file(input_path: Path, output_path: Path) -> None:
    """Raises OutputError when writing `output_path` would overwrite the input log or write
    into the input bag's folder."""
    if input_path.is_dir() and output_path.resolve().is_relative_to(input_path.resolve()):
        raise OutputError(f"{output_path}: the output would be written inside the input bag")
    if output_path.exists() and os.path.samefile(input_path, output_path):
        raise OutputError(f"{output_path}: the output would overwrite the input log")


class _Annotator:
    """Writes our channels and messages into the output, interleaved by log time."""

    def __init__(
        self,
        writer: Writer,
        encoder: MessageEncoder,
        messages: Sequence[TimedMessage],
        visuals: VisualWriter | None = None,
    ):
        self.writer = writer
        self.visuals = visuals
        self.encoder = encoder
        # Sorting by (log time, type, index) fixes the order whatever order the caller used.
        self.pending = in_order(messages)
        self.next: TimedMessage | None = next(self.pending, None)
        self.channel_ids: dict[str, int] = {}
        self.written: Counter[str] = Counter()

    def write_until(self, log_time_ns: int | None) -> None:
        """Writes our messages with log time <= log_time_ns (all of them for None)."""
        if self.visuals is not None:
            self.visuals.write_until(log_time_ns)
        while self.next is not None:
            if log_time_ns is not None and self.next.log_time_ns > log_time_ns:
                return
            self._write(self.next)
            self.next = next(self.pending, None)

    def input_channel(
        self, topic: str, encoding: str, schema_id: int, metadata: dict[str, str]
    ) -> None:
        """Called for each input channel copied (the visualization reuses the camera's)."""
        if self.visuals is not None:
            self.visuals.input_channel(topic, encoding, schema_id, metadata)

    def visualized(self) -> dict[str, int]:
        """Writes the rest of the visualization; its messages per topic."""
        return {} if self.visuals is None else self.visuals.finish()

    def finish(self, metadata: Mapping[str, str], frame_times: FrameTimes | None) -> dict[str, int]:
        """Writes the rest of our messages, the frame times and the `doseqslam` metadata."""
        self.write_until(None)
        self._register_channels()  # our channels exist even without a single message
        if frame_times is not None:
            last = int(frame_times.log_times_ns[-1]) if len(frame_times) else 0
            self.writer.add_attachment(
                0, last, FRAME_TIMES_ATTACHMENT, FRAME_TIMES_MEDIA_TYPE, frame_times.to_json()
            )
        self.writer.add_metadata(METADATA_NAME, dict(metadata))
        return {t.topic: self.written[t.topic] for t in MESSAGE_TYPES}

    def _write(self, message: TimedMessage) -> None:
        self._register_channels()
        data = self.encoder.encode(message.type, message.fields)
        channel_id = self.channel_ids[message.type.topic]
        # Our messages have no publisher: publish time = log time; sequence numbers per topic.
        sequence = self.written[message.type.topic]
        self.writer.add_message(
            channel_id, message.log_time_ns, data, message.log_time_ns, sequence & 0xFFFFFFFF
        )
        self.written[message.type.topic] += 1

    def _register_channels(self) -> None:
        # Registered lazily, just before our first message, so the input's schema and channel
        # ids keep their numbering in outputs where the input's records come first.
        if self.channel_ids:
            return
        for message_type in MESSAGE_TYPES:
            self.channel_ids[message_type.topic] = self._register(message_type)

    def _register(self, message_type: MessageType) -> int:
        encoder = self.encoder
        schema_id = self.writer.register_schema(
            encoder.schema_name(message_type),
            encoder.schema_encoding,
            encoder.schema_data(message_type),
        )
        return self.writer.register_channel(
            message_type.topic,
            encoder.message_encoding,
            schema_id,
            encoder.channel_metadata(message_type),
        )


class _McapCopier:
    """Copies an MCAP file's records into the output, dropping our previous annotations."""

    def __init__(self, writer: Writer, annotator: _Annotator) -> None:
        self.writer = writer
        self.annotator = annotator
        self.schemas: dict[int, Schema] = {}
        self.schema_ids: dict[int, int] = {}  # input schema id -> output schema id
        self.channel_ids: dict[int, int] = {}  # input channel id -> output channel id
        self.dropped_channels: dict[int, str] = {}  # input channel id -> topic
        self.dropped_schemas: set[int] = set()  # schemas used by dropped channels
        self.copied = 0

    def copy(self, path: Path) -> None:
        """Raises SourceError when the input cannot be read."""
        for record in input_records(path):
            self._copy_record(record, path)
        self._copy_unused_schemas()

    def _copy_record(self, record: object, path: Path) -> None:
        if isinstance(record, Schema):
            self.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            self._copy_channel(record, path)
        elif isinstance(record, Message):
            self._copy_message(record, path)
        elif isinstance(record, Attachment) and record.name != FRAME_TIMES_ATTACHMENT:
            self.writer.add_attachment(
                record.create_time, record.log_time, record.name, record.media_type, record.data
            )
        elif isinstance(record, Metadata) and record.name != METADATA_NAME:
            self.writer.add_metadata(record.name, record.metadata)
        # Everything else (header, chunks' indexes, statistics, summary) is rebuilt by Writer.

    def _copy_channel(self, channel: Channel, path: Path) -> None:
        if channel.id in self.channel_ids or channel.id in self.dropped_channels:
            return  # repeated in the summary section
        if channel.topic.startswith(OUR_TOPIC_PREFIX):
            self.dropped_channels[channel.id] = channel.topic
            self.dropped_schemas.add(channel.schema_id)
            return
        schema_id = self._output_schema(channel.schema_id, path)
        self.channel_ids[channel.id] = self.writer.register_channel(
            channel.topic, channel.message_encoding, schema_id, dict(channel.metadata)
        )
        self.annotator.input_channel(
            channel.topic, channel.message_encoding, schema_id, dict(channel.metadata)
        )

    def _output_schema(self, schema_id: int, path: Path) -> int:
        if schema_id == 0:  # a channel without schema
            return 0
        if schema_id not in self.schema_ids:
            schema = self.schemas.get(schema_id)
            if schema is None:
                raise SourceError(f"{path}: a channel refers to the unknown schema {schema_id}")
            self.schema_ids[schema_id] = self.writer.register_schema(
                schema.name, schema.encoding, schema.data
            )
        return self.schema_ids[schema_id]

    def _copy_message(self, message: Message, path: Path) -> None:
        channel_id = self.channel_ids.get(message.channel_id)
        if channel_id is None:
            if message.channel_id in self.dropped_channels:
                return
            raise SourceError(f"{path}: a message refers to the unknown channel")
        self.annotator.write_until(message.log_time)
        self.writer.add_message(
            channel_id, message.log_time, message.data, message.publish_time, message.sequence
        )
        self.copied += 1

    def _copy_unused_schemas(self) -> None:
        # Schemas no channel uses are input records too; only our old annotations' go away.
        for schema_id, schema in self.schemas.items():
            if schema_id not in self.schema_ids and schema_id not in self.dropped_schemas:
                self.schema_ids[schema_id] = self.writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )


def _ros1_schema_name(msgtype: str) -> str:
    """rosbags spells every type the ROS 2 way; ROS 1 has no `/msg/` part."""
    package, _, name = msgtype.rpartition("/")
    return f"{package.removesuffix('/msg')}/{name}"


def _ros1_channel_metadata(connection: Connection) -> dict[str, str]:
    metadata = {"md5sum": connection.digest}
    ext = connection.ext
    if isinstance(ext, ConnectionExtRosbag1):
        if ext.callerid is not None:
            metadata["callerid"] = ext.callerid
        if ext.latching is not None:
            metadata["latching"] = "true" if ext.latching else "false"  # the ros1 profile's form
    return metadata


class _BagCopier:
    """Copies the messages of a ROS 1 or rosbag2 bag (via rosbags) with their raw bytes."""

    def __init__(self, writer: Writer, annotator: _Annotator) -> None:
        self.writer = writer
        self.annotator = annotator
        self.schema_ids: dict[tuple[str, str, bytes], int] = {}
        self.channel_ids: dict[Any, int] = {}
        self.dropped: set[str] = set()
        self.copied = 0

    def schema(self, name: str, encoding: str, data: bytes) -> int:
        key = (name, encoding, data)
        if key not in self.schema_ids:
            self.schema_ids[key] = self.writer.register_schema(name, encoding, data)
        return self.schema_ids[key]

    def channel(
        self, key: Any, topic: str, encoding: str, schema_id: int, metadata: dict[str, str]
    ) -> None:
        if topic.startswith(OUR_TOPIC_PREFIX):
            self.dropped.add(topic)
        elif key not in self.channel_ids:
            self.channel_ids[key] = self.writer.register_channel(
                topic, encoding, schema_id, metadata
            )
            self.annotator.input_channel(topic, encoding, schema_id, metadata)

    def message(self, key: Any, timestamp: int, data: bytes) -> None:
        channel_id = self.channel_ids.get(key)
        if channel_id is None:
            return  # one of our previous channels
        self.annotator.write_until(timestamp)
        # Bags record one time per message: it is both the log and the publish time.
        self.writer.add_message(channel_id, timestamp, bytes(data), timestamp, 0)
        self.copied += 1

    def copy_ros1(self, path: Path) -> None:
        """Raises SourceError when the bag cannot be read."""
        with _open_bag(path, Ros1Reader) as reader:
            for conn in sorted(reader.connections, key=lambda c: c.id):
                data = conn.msgdef.data.encode()
                schema_id = self.schema(_ros1_schema_name(conn.msgtype), "ros1msg", data)
                self.channel(conn.id, conn.topic, "ros1", schema_id, _ros1_channel_metadata(conn))
            for conn, timestamp, raw in guarded_reads(path, reader.messages()):
                self.message(conn.id, timestamp, raw)

    def copy_rosbag2(self, path: Path) -> None:
        """Raises SourceError when the bag cannot be read."""
        with _open_bag(path, Ros2Reader) as reader:
            definitions = _Ros2Definitions(reader)
            storages = _storages(reader)
            keys: dict[tuple[int, int], tuple[str, ...]] = {}
            for number, storage in enumerate(storages):
                for conn in storage.connections:
                    keys[number, conn.id] = self._rosbag2_channel(conn, definitions)
            decompress = _message_decompressor(reader.compression_mode)
            for number, storage in enumerate(storages):
                messages = storage.messages(storage.connections)
                for conn, timestamp, raw in guarded_reads(path, messages):
                    self.message(keys[number, conn.id], timestamp, decompress(raw))

    def _rosbag2_channel(self, conn: Connection, definitions: _Ros2Definitions) -> tuple[str, ...]:
        """Registers the connection's channel and returns its key: the same for the same
        channel in every storage file of a split bag."""
        encoding, data = definitions.get(conn)
        schema_id = self.schema(conn.msgtype, encoding, data)
        qos_profiles = list(getattr(conn.ext, "offered_qos_profiles", []))
        qos = dump_qos_v8(qos_profiles) if qos_profiles else ""
        message_encoding = getattr(conn.ext, "serialization_format", "cdr")
        metadata = {"offered_qos_profiles": qos} if qos else {}
        key = (conn.topic, conn.msgtype, message_encoding, qos)
        self.channel(key, conn.topic, message_encoding, schema_id, metadata)
        return key


def _storages(reader: Ros2Reader) -> list[_Storage]:
    # The storage files are read one by one: rosbags 0.11's folder reader yields no message
    # at all for a topic whose QoS in metadata.yaml differs from the one in the storage file.
    storage = reader.storage
    if isinstance(storage, DirectoryReader):
        return list(storage.storages)
    return [storage]


def _message_decompressor(mode: str | None) -> Callable[[bytes], bytes]:
    if mode != "message":
        return lambda raw: raw
    decompressor = zstandard.ZstdDecompressor()
    # Frames may not record their size; a stream reader does not need it.
    return lambda raw: decompressor.decompressobj().decompress(raw)


class _Ros2Definitions:
    """Message definitions of a rosbag2 bag, generated from rosbags' types when missing."""

    def __init__(self, reader: Ros2Reader) -> None:
        self.by_type = {
            c.msgtype: c.msgdef
            for c in reader.connections
            if c.msgdef.format != MessageDefinitionFormat.NONE
        }
        self.distro = reader.ros_distro
        self._typestore: Typestore | None = None

    def get(self, conn: Connection) -> tuple[str, bytes]:
        """(schema encoding, data); encoding "" and no data when no definition is known."""
        msgdef = conn.msgdef
        if msgdef.format == MessageDefinitionFormat.NONE:
            msgdef = self.by_type.get(conn.msgtype, msgdef)
        if msgdef.format == MessageDefinitionFormat.MSG:
            return "ros2msg", msgdef.data.encode()
        if msgdef.format == MessageDefinitionFormat.IDL:
            return "ros2idl", msgdef.data.encode()
        return self._generate(conn.msgtype)

    def _generate(self, msgtype: str) -> tuple[str, bytes]:
        typestore = self._store()
        if msgtype not in typestore.fielddefs:
            return "", b""  # unknown type: the channel keeps its type name, without definition
        text, _ = typestore.generate_msgdef(msgtype, ros_version=2)
        return "ros2msg", text.encode()

    def _store(self) -> Typestore:
        if self._typestore is None:
            try:
                store = Stores(f"ros2_{self.distro}")
            except ValueError:
                store = Stores.LATEST
            self._typestore = get_typestore(store)
        return self._typestore


def _copy_input(log: InputLog, writer: Writer, annotator: _Annotator) -> tuple[int, list[str]]:
    """Copies the input's records; returns (messages copied, topics of dropped channels)."""
    if log.kind == "mcap":
        copier = _McapCopier(writer, annotator)
        copier.copy(log.path)
        return copier.copied, sorted(set(copier.dropped_channels.values()))
    bag = _BagCopier(writer, annotator)
    if log.kind == "ros1-bag":
        bag.copy_ros1(log.path)
    else:
        bag.copy_rosbag2(log.path)
    return bag.copied, sorted(bag.dropped)


def _write(
    stream: BinaryIO,
    log: InputLog,
    annotations: Annotations,
    sidecar: bool,
    summary: WriteSummary,
    output_format: OutputFormat,
    source: Source | None,
) -> None:
    compression = COMPRESSIONS[output_format.compression]
    writer = Writer(stream, chunk_size=output_format.chunk_size, compression=compression)
    writer.start(profile=log.profile, library=LIBRARY)
    visuals = None
    if annotations.visualization is not None and not sidecar:
        encoder = visual_encoder_for_profile(log.profile)
        reads = log.path if source is None else source
        visuals = VisualWriter(writer, encoder, reads, annotations.visualization)
    annotator = _Annotator(writer, encoder_for_profile(log.profile), annotations.messages, visuals)
    if not sidecar:
        summary.copied_messages, summary.replaced_topics = _copy_input(log, writer, annotator)
    summary.visualized = annotator.visualized()
    summary.written = annotator.finish(annotations.metadata, annotations.frame_times)
    writer.finish()  # type: ignore[no-untyped-call]  # mcap leaves it unannotated


def write_annotated_mcap(
    input_path: str | os.PathLike[str],
    output_path: str | os.PathLike[str],
    annotations: Annotations,
    *,
    sidecar: bool = False,
    output_format: OutputFormat | None = None,
    source: Source | None = None,
) -> WriteSummary:
    """Writes `output_path`: the input log's records unchanged plus our channels and metadata
    (only ours and the metadata with `sidecar=True`).

    The input is opened read-only and streamed; the match images of the visualization are
    read through `source` (the run's open input) when given, else through the input opened
    again. The output is written to a temporary file beside it and renamed into place only
    when complete.
    Raises SourceError when the input cannot be read, OutputError when the output cannot be
    written (also when a message does not fit its schema) or would overwrite the input.
    """
    given, output = Path(input_path), Path(output_path)
    log = detect_input(given)
    refuse_same_file(given, output)
    refuse_same_file(log.path, output)
    summary = WriteSummary(output, log.kind, log.profile)
    with atomic_output(output) as stream:
        chunks = output_format or OutputFormat()
        _write(stream, log, annotations, sidecar, summary, chunks, source)
    return summary
