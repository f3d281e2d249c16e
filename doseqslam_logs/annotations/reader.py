"""Reading an annotated log back: our channels and metadata as the typed records of `records`.

Messages are decoded with the definitions embedded in the file (any profile we write: ROS 2
CDR, ROS 1, JSON), so logs annotated by other versions of the tool read back too: fields a
version did not write take the records' "not recorded" values.
"""

from __future__ import annotations

import contextlib
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
import numpy.typing as npt
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Attachment, Metadata, Schema
from mcap.stream_reader import StreamReader

from ..errors import SourceError
from ..sources import refuse_stream
from ..sources.mcap_source import DESERIALIZERS, describe_read_error, is_complete
from .records import (
    FRAME_TIMES_ATTACHMENT,
    LOOP_CLOSURE_TOPICS,
    METADATA_NAME,
    SEQUENCE,
    FrameTimes,
    LoopClosureRecord,
    RunMetadata,
    SequenceRecord,
)

TOPICS = (*LOOP_CLOSURE_TOPICS, SEQUENCE.topic)


@dataclass(frozen=True)
class AnnotatedLog:
    """Our messages in log-time order, and the run's metadata record.

    `loop_closures` holds every LoopClosure message, reported or not, from both of their
    topics (or, in outputs of versions that wrote them all there, from /doseqslam/loop_closures
    alone): the same records whichever layout the file has.
    """

    path: Path
    metadata: RunMetadata
    loop_closures: tuple[LoopClosureRecord, ...] = ()
    sequences: tuple[SequenceRecord, ...] = ()
    # Log time and header stamp of every frame by index (None: annotated before 0.2).
    frame_times: FrameTimes | None = None

    @property
    def reported_loop_closures(self) -> list[LoopClosureRecord]:
        """The loop closures the run reports: all but those geometric verification rejected
        or skipped.

        Rejected and skipped pairs (verification == "rejected" or "skipped", on
        /doseqslam/candidates) stay in `loop_closures` for evaluation and diffs; logs annotated
        without verification (or before it existed) report every pair.
        """
        return [lc for lc in self.loop_closures if lc.reported]

    @property
    def parameters(self) -> dict[str, Any]:
        """The detector parameters recorded in the metadata ({} when absent)."""
        return self.metadata.parameters

    def detector_times_ns(self) -> npt.NDArray[np.int64] | None:
        """The time the detector gave every frame, by index (`FrameTimes.detector_times_ns`
        with the run's time source). None for logs annotated before frame times were
        recorded."""
        if self.frame_times is None:
            return None
        return self.frame_times.detector_times_ns(self.metadata.time_source)


def plain(value: Any) -> Any:
    """rosbags / mcap_ros2 / JSON message objects -> dicts, lists and numbers."""
    if isinstance(value, (str, bytes, bool, int, float)) or value is None:
        return value
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (list, tuple)):
        return [plain(item) for item in value]
    if isinstance(value, dict):
        return {key: plain(item) for key, item in value.items()}
    names = _field_names(value)
    if set(names) in ({"sec", "nanosec"}, {"sec", "nsec"}):
        nanos = value.nanosec if hasattr(value, "nanosec") else value.nsec
        return {"sec": int(value.sec), "nsec": int(nanos)}
    return {name: plain(getattr(value, name)) for name in names}


def _records_of_ours(
    metadata: Iterable[object], attachments: Iterable[object]
) -> tuple[dict[str, str], FrameTimes | None]:
    """Our metadata entries ({} without the record) and frame times (None without them)."""
    entries = next(
        (dict(m.metadata) for m in metadata if isinstance(m, Metadata) and m.name == METADATA_NAME),
        {},
    )
    frame_times = next(
        (
            FrameTimes.from_json(a.data)
            for a in attachments
            if isinstance(a, Attachment) and a.name == FRAME_TIMES_ATTACHMENT
        ),
        None,
    )
    return entries, frame_times


def _ours_of(
    stream: IO[bytes], reader: Any, attachments: bool
) -> tuple[dict[str, str], FrameTimes | None]:
    """`_records_of_ours` of the file, through its summary's indexes, else (a summary without
    metadata index, rewritten by another tool) from the data section, where the record still
    is; frame times only with `attachments`."""
    found = reader.iter_attachments() if attachments else ()
    entries, frame_times = _records_of_ours(reader.iter_metadata(), found)
    if not entries:
        stream.seek(0)
        records = list(_metadata_and_attachments(stream))
        entries, frame_times = _records_of_ours(records, records if attachments else ())
    return entries, frame_times


def _metadata_and_attachments(stream: IO[bytes]) -> Iterator[Metadata | Attachment]:
    """The Metadata and Attachment records of the file, read in one pass from its start."""
    for record in StreamReader(stream).records:
        if isinstance(record, (Metadata, Attachment)):
            yield record


def _problem(file: Path, exc: BaseException) -> str:
    """What is wrong, in words: a file cut short says so."""
    with contextlib.suppress(OSError), file.open("rb") as stream:
        if not is_complete(stream):
            return "truncated MCAP file: it ends without a footer (written or copied cut short?)"
    return describe_read_error(exc)


def _field_names(value: Any) -> list[str]:
    fields = getattr(value, "__dataclass_fields__", None)
    if fields is not None:
        return [name for name in fields if name != "__msgtype__"]
    slots = getattr(type(value), "__slots__", None)
    if slots:
        return [name for name in slots if not name.startswith("_")]
    return [name for name in vars(value) if not name.startswith("_")]


def read_annotations(path: str | Path) -> AnnotatedLog:
    """Our channels and metadata from an annotated MCAP (or a sidecar).

    Raises SourceError when the file cannot be read, holds no `doseqslam` metadata, or holds
    a message of ours that lacks the fields every version wrote.
    """
    file = Path(path)
    refuse_stream(file)
    closures: list[tuple[int, _Closure]] = []  # (log time, record): two topics to merge
    sequences: list[dict[str, Any]] = []
    try:
        with file.open("rb") as stream:
            reader = make_reader(stream)
            decoders: dict[int, Any] = {}  # by schema id, for this file
            for schema, channel, message in _our_messages(reader):
                if schema.id not in decoders:
                    decoders[schema.id] = _decoder(schema, channel.message_encoding)
                decoded = plain(decoders[schema.id](message.data))
                if channel.topic in LOOP_CLOSURE_TOPICS:
                    closures.append((message.log_time, _closure(path, decoded)))
                else:
                    sequences.append(decoded)
            entries, frame_times = _ours_of(stream, reader, attachments=True)
    except (OSError, McapError, ValueError, KeyError, struct.error) as exc:
        raise SourceError(f"{path}: cannot read the annotations ({_problem(file, exc)})") from exc
    if not entries:
        raise SourceError(f"{path}: not annotated by doseqslam-logs (no '{METADATA_NAME}' record)")
    try:
        return AnnotatedLog(
            file,
            RunMetadata.from_entries(entries),
            _loop_closures(closures, frame_times),
            tuple(SequenceRecord.from_message(m) for m in sequences),
            frame_times,
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise _unusable(path, exc) from exc


_Closure = LoopClosureRecord | dict[str, Any]


def _unusable(path: str | Path, exc: BaseException) -> SourceError:
    """A message of ours that lacks the fields every version wrote, or holds the wrong kind."""
    return SourceError(f"{path}: unusable message on our channels ({exc!r})")


def _closure(path: str | Path, message: dict[str, Any]) -> _Closure:
    """The record, made as its message is read so that the messages are not all held at once;
    the message itself when it needs the frame times, read after the messages (a log annotated
    between two versions: a refined match without its times).

    Raises SourceError for a message that lacks the fields every version wrote.
    """
    if "refined_match_index" in message and "refined_match_log_time" not in message:
        return message
    try:
        return LoopClosureRecord.from_message(message)
    except (KeyError, TypeError, ValueError) as exc:
        raise _unusable(path, exc) from exc


def _loop_closures(
    messages: list[tuple[int, _Closure]], frame_times: FrameTimes | None
) -> tuple[LoopClosureRecord, ...]:
    """The LoopClosure messages of both topics as one list, in the order the writer wrote
    them (`TimedMessage.sort_key`: log time, then query index), whatever order equal log times
    were read in."""
    records = [
        (
            t,
            m
            if isinstance(m, LoopClosureRecord)
            else LoopClosureRecord.from_message(m, frame_times),
        )
        for t, m in messages
    ]
    records.sort(key=lambda item: (item[0], item[1].query.index))
    return tuple(record for _, record in records)


def _our_messages(reader: Any) -> Iterator[tuple[Schema, Any, Any]]:
    yield from reader.iter_messages(topics=list(TOPICS), log_time_order=True)


def _decoder(schema: Schema, message_encoding: str) -> Any:
    """The sources' deserializer for this schema (the definition embedded in the file)."""
    make = DESERIALIZERS.get((message_encoding, schema.encoding))
    if make is None:
        raise ValueError(f"no decoder for {message_encoding}/{schema.encoding}")
    return make(schema)


def read_run_metadata(path: str | Path) -> RunMetadata | None:
    """The `doseqslam` metadata record of an MCAP file (None when it has none, or is not an
    MCAP file that can be read): what `info` says of a run, without reading its messages."""
    file = Path(path)
    try:
        with file.open("rb") as stream:
            entries, _ = _ours_of(stream, make_reader(stream), attachments=False)
        return RunMetadata.from_entries(entries) if entries else None
    except (OSError, McapError, ValueError, KeyError, TypeError, struct.error):
        return None
