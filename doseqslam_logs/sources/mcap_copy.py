"""Copying an MCAP file record by record (`copy_mcap`), and reading its profile."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from ..errors import SourceError
from . import chunk_limits  # noqa: F401 - the input's chunks are copied within the cap
from .copying import Copied, CopyHooks, guarded_reads, reading_errors


def input_records(path: Path) -> Iterator[object]:
    """The records of an MCAP file to copy, read errors as SourceError (`guarded_reads`).

    CRCs are checked: a corrupt chunk of any topic must fail the copy (or be left to
    --recover), never be written out again under a fresh, valid CRC.
    """
    with reading_errors(path):
        stream = path.open("rb")
    with stream:
        yield from guarded_reads(path, StreamReader(stream, validate_crcs=True).records)


def read_mcap_profile(path: Path) -> str:
    """The profile of the MCAP file at `path`."""
    with reading_errors(path), path.open("rb") as stream:
        return mcap_profile_of(path, stream)


def mcap_profile_of(path: Path, stream: BinaryIO) -> str:
    """The profile of the MCAP header at the start of `stream`."""
    with reading_errors(path):
        header = next(iter(StreamReader(stream).records))
    profile = getattr(header, "profile", None)
    if not isinstance(profile, str):
        raise SourceError(f"{path}: the MCAP file does not start with a header record")
    return profile


def copy_mcap(path: Path, writer: Writer, hooks: CopyHooks) -> Copied:
    """Every record of the MCAP file at `path` into `writer`, but the ones `hooks` leaves out.
    Raises SourceError when the input cannot be read."""
    copier = _McapCopier(writer, hooks)
    for record in input_records(path):
        copier.copy_record(record, path)
    copier.copy_unused_schemas()
    return Copied(copier.copied, sorted(set(copier.dropped_channels.values())))


class _McapCopier:
    def __init__(self, writer: Writer, hooks: CopyHooks) -> None:
        self.writer = writer
        self.hooks = hooks
        self.schemas: dict[int, Schema] = {}
        self.schema_ids: dict[int, int] = {}  # input schema id -> output schema id
        self.channel_ids: dict[int, int] = {}  # input channel id -> output channel id
        self.topics: dict[int, str] = {}  # input channel id -> topic, of the copied channels
        self.dropped_channels: dict[int, str] = {}  # input channel id -> topic
        self.dropped_schemas: set[int] = set()  # schemas used by dropped channels
        self.copied = 0

    def copy_record(self, record: object, path: Path) -> None:
        hooks = self.hooks
        if isinstance(record, Schema):
            self.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            self._copy_channel(record, path)
        elif isinstance(record, Message):
            self._copy_message(record, path)
        elif isinstance(record, Attachment) and hooks.keeps_attachment(record.name):
            self.writer.add_attachment(
                record.create_time, record.log_time, record.name, record.media_type, record.data
            )
        elif isinstance(record, Metadata) and hooks.keeps_metadata(record.name):
            self.writer.add_metadata(record.name, record.metadata)
        # Everything else (header, chunks' indexes, statistics, summary) is rebuilt by Writer.

    def _copy_channel(self, channel: Channel, path: Path) -> None:
        if channel.id in self.channel_ids or channel.id in self.dropped_channels:
            return  # repeated in the summary section
        if not self.hooks.keeps_topic(channel.topic):
            self.dropped_channels[channel.id] = channel.topic
            self.dropped_schemas.add(channel.schema_id)
            return
        schema_id = self._output_schema(channel.schema_id, path)
        self.channel_ids[channel.id] = self.writer.register_channel(
            channel.topic, channel.message_encoding, schema_id, dict(channel.metadata)
        )
        self.topics[channel.id] = channel.topic
        self.hooks.channel_copied(
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
        self.hooks.before_message(message.log_time)
        self.writer.add_message(
            channel_id, message.log_time, message.data, message.publish_time, message.sequence
        )
        self.hooks.message_copied(self.topics[message.channel_id], message.log_time, message.data)
        self.copied += 1

    def copy_unused_schemas(self) -> None:
        # Schemas no channel uses are input records too; only the dropped channels' go away.
        for schema_id, schema in self.schemas.items():
            if schema_id not in self.schema_ids and schema_id not in self.dropped_schemas:
                self.schema_ids[schema_id] = self.writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
