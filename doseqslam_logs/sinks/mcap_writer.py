"""Write the annotated MCAP: every record of the input, plus our loop-closure channels.

Inputs are the logs of any format in `sources.formats` (MCAP files of any profile, ROS 1 bags,
rosbag2 bags), each copied by its format's copier. The input is streamed record by record
(memory bounded by one chunk), its records are copied unchanged, and our messages are
interleaved by log time. Our channels use the encoding of the input's profile (see `encoders`).
The output appears atomically (see `atomic`) and is byte-identical for the same input and
annotations.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from mcap.writer import Writer

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
from ..errors import OutputError
from ..sources.base import Source
from ..sources.formats import CopyPlan, LogFormat, plan_copy
from .atomic import atomic_output
from .encoders import MessageEncoder, encoder_for_profile
from .message_spool import SpooledMessages, in_order
from .output_format import COMPRESSIONS, OutputFormat
from .visual_encoders import visual_encoder_for_profile
from .visualization import Visualization, VisualWriter

LIBRARY = f"doseqslam-logs/{__version__}"
PROGRESS_EVERY = 64  # input messages copied between two progress calls


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


@dataclass
class WriteSummary:
    """What `write_annotated_mcap` wrote."""

    output_path: Path
    input_kind: str  # the name of the format copied (sources.formats)
    profile: str
    copied_messages: int = 0  # input messages copied (0 for a sidecar)
    written: dict[str, int] = field(default_factory=dict)  # our messages per topic
    replaced_topics: list[str] = field(default_factory=list)  # input /doseqslam/ channels
    visualized: dict[str, int] = field(default_factory=dict)  # visualization messages per topic


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
        progress: Callable[[int], None] | None = None,
    ):
        self.writer = writer
        self.progress = progress
        self.copied = 0  # input messages copied so far
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

    # The copy's hooks (sources.copying.CopyHooks): our channels, attachment and metadata of
    # an earlier run are replaced; ours are written up to each copied message's log time.
    def keeps_topic(self, topic: str) -> bool:
        return not topic.startswith(OUR_TOPIC_PREFIX)

    def keeps_attachment(self, name: str) -> bool:
        return name != FRAME_TIMES_ATTACHMENT

    def keeps_metadata(self, name: str) -> bool:
        return name != METADATA_NAME

    def before_message(self, log_time_ns: int) -> None:
        self.write_until(log_time_ns)
        self.copied += 1
        if self.progress is not None and self.copied % PROGRESS_EVERY == 0:
            self.progress(self.copied)

    def channel_copied(
        self, topic: str, encoding: str, schema_id: int, metadata: dict[str, str]
    ) -> None:
        """Called for each input channel copied (the visualization reuses the camera's)."""
        if self.visuals is not None:
            self.visuals.input_channel(topic, encoding, schema_id, metadata)

    def message_copied(self, topic: str, log_time_ns: int, data: bytes) -> None:
        """Called after each input message copied (the visualization keeps match images)."""
        if self.visuals is not None:
            self.visuals.input_message(topic, log_time_ns, data)

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
        schema_ids: dict[str, int] = {}  # one schema per definition, shared by its topics
        for message_type in MESSAGE_TYPES:
            if message_type.name not in schema_ids:
                schema_ids[message_type.name] = self._register_schema(message_type)
            schema_id = schema_ids[message_type.name]
            self.channel_ids[message_type.topic] = self._register_channel(message_type, schema_id)

    def _register_schema(self, message_type: MessageType) -> int:
        encoder = self.encoder
        schema_id: int = self.writer.register_schema(
            encoder.schema_name(message_type),
            encoder.schema_encoding,
            encoder.schema_data(message_type),
        )
        return schema_id

    def _register_channel(self, message_type: MessageType, schema_id: int) -> int:
        encoder = self.encoder
        return self.writer.register_channel(
            message_type.topic,
            encoder.message_encoding,
            schema_id,
            encoder.channel_metadata(message_type),
        )


def _write(
    stream: BinaryIO,
    log: CopyPlan,
    annotations: Annotations,
    sidecar: bool,
    summary: WriteSummary,
    output_format: OutputFormat,
    source: Source | None,
    progress: Callable[[int], None] | None = None,
) -> None:
    compression = COMPRESSIONS[output_format.compression]
    writer = Writer(stream, chunk_size=output_format.chunk_size, compression=compression)
    writer.start(profile=log.profile, library=LIBRARY)
    visuals = None
    if annotations.visualization is not None and not sidecar:
        encoder = visual_encoder_for_profile(log.profile)
        reads = log.path if source is None else source
        visuals = VisualWriter(writer, encoder, reads, annotations.visualization)
    annotator = _Annotator(
        writer, encoder_for_profile(log.profile), annotations.messages, visuals, progress
    )
    if not sidecar:
        copied = log.copy(log.path, writer, annotator)
        summary.copied_messages, summary.replaced_topics = copied.messages, copied.dropped_topics
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
    log_format: LogFormat | None = None,
    progress: Callable[[int], None] | None = None,
) -> WriteSummary:
    """Writes `output_path`: the input log's records unchanged plus our channels and metadata
    (only ours and the metadata with `sidecar=True`).

    The input is opened read-only and streamed; the match images of the visualization are
    read through `source` (the run's open input) when given, else through the input opened
    again; `log_format`: the input's format when the caller knows it (else it is probed);
    `progress(input messages copied)` every PROGRESS_EVERY messages.
    The output is written to a temporary file beside it and renamed into place only when
    complete.
    Raises SourceError when the input cannot be read, OutputError when the output cannot be
    written (also when a message does not fit its schema) or would overwrite the input.
    """
    given, output = Path(input_path), Path(output_path)
    log = plan_copy(given) if log_format is None else log_format.plan_copy(given)
    refuse_same_file(given, output)
    refuse_same_file(log.path, output)
    summary = WriteSummary(output, log.kind, log.profile)
    with atomic_output(output) as stream:
        chunks = output_format or OutputFormat()
        _write(stream, log, annotations, sidecar, summary, chunks, source, progress)
    return summary
