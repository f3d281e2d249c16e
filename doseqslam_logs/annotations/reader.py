"""Reading an annotated log back: our channels as plain dicts, and the `doseqslam` metadata.

Messages are decoded with the definitions embedded in the file (any profile we write: ROS 2
CDR, ROS 1, JSON), so logs annotated by other versions of the tool read back too. The plain
form is the one the writers take: times as {"sec", "nsec"}, arrays as lists.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Schema

from ..errors import SourceError
from ..sources.mcap_source import DESERIALIZERS
from .records import (
    FRAME_TIMES_ATTACHMENT,
    LOOP_CLOSURE,
    METADATA_NAME,
    REJECTED,
    SEQUENCE,
    SKIPPED,
    FrameTimes,
)

TOPICS = (LOOP_CLOSURE.topic, SEQUENCE.topic)

NOT_REPORTED = frozenset({REJECTED, SKIPPED})


@dataclass
class AnnotatedLog:
    """Our messages in log-time order, and the run's metadata record."""

    path: Path
    loop_closures: list[dict[str, Any]] = field(default_factory=list)
    sequences: list[dict[str, Any]] = field(default_factory=list)
    metadata: dict[str, str] = field(default_factory=dict)
    # Log time and header stamp of every frame by index (None: annotated before 0.2).
    frame_times: FrameTimes | None = None

    @property
    def reported_loop_closures(self) -> list[dict[str, Any]]:
        """The loop closures the run reports: all but those geometric verification rejected
        or skipped.

        Rejected and skipped pairs stay on the channel (verification == "rejected" or
        "skipped") for evaluation and diffs; logs annotated without verification (or before it
        existed) report every pair.
        """
        return [lc for lc in self.loop_closures if lc.get("verification") not in NOT_REPORTED]

    @property
    def parameters(self) -> dict[str, Any]:
        """The detector parameters recorded in the metadata ({} when absent)."""
        text = self.metadata.get("parameters")
        return dict(json.loads(text)) if text else {}


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

    Raises SourceError when the file cannot be read or holds no `doseqslam` metadata.
    """
    log = AnnotatedLog(Path(path))
    try:
        with log.path.open("rb") as stream:
            reader = make_reader(stream)
            decoders: dict[int, Any] = {}  # by schema id, for this file
            for schema, channel, message in _our_messages(reader):
                if schema.id not in decoders:
                    decoders[schema.id] = _decoder(schema, channel.message_encoding)
                decoded = plain(decoders[schema.id](message.data))
                target = log.loop_closures if channel.topic == LOOP_CLOSURE.topic else log.sequences
                target.append(decoded)
            for record in reader.iter_metadata():
                if record.name == METADATA_NAME:
                    log.metadata = dict(record.metadata)
            for attachment in reader.iter_attachments():
                if attachment.name == FRAME_TIMES_ATTACHMENT:
                    log.frame_times = FrameTimes.from_json(attachment.data)
    except (OSError, McapError, ValueError, KeyError) as exc:
        raise SourceError(f"{path}: cannot read the annotations ({exc})") from exc
    if not log.metadata:
        raise SourceError(f"{path}: not annotated by doseqslam-logs (no '{METADATA_NAME}' record)")
    return log


def _our_messages(reader: Any) -> Iterator[tuple[Schema, Any, Any]]:
    yield from reader.iter_messages(topics=list(TOPICS), log_time_order=True)


def _decoder(schema: Schema, message_encoding: str) -> Any:
    """The sources' deserializer for this schema (the definition embedded in the file)."""
    make = DESERIALIZERS.get((message_encoding, schema.encoding))
    if make is None:
        raise ValueError(f"no decoder for {message_encoding}/{schema.encoding}")
    return make(schema)
