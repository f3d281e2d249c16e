"""Ranged reads of some topics of an indexed MCAP file through their message indexes.

mcap's SeekingReader parses every record of every chunk it opens, in Python. The verification
stage re-reads a few frames at a time, from chunks that also hold the log's other topics, and
that parsing, holding the GIL, is a large share of the stage's time. Each chunk's message index
lists the offsets of one channel's messages in it: this reader decompresses the chunk and slices
out only those. It yields the same messages in the same
order as `SeekingReader.iter_messages(topics=topics, log_time_order=True)` (tested), through
mcap's own log-time queue.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator, Sequence
from typing import IO

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, ChunkIndex, Message, Schema
from mcap.summary import Summary

from doseqslam_logs.sources.chunk_limits import chunk_records

try:  # mcap's own log-time queue, so that it reads as SeekingReader
    from mcap._message_queue import make_message_queue
except ImportError:  # pragma: no cover - older mcap: read the chunks whole
    make_message_queue = None  # type: ignore[assignment]

Record = tuple[Schema | None, Channel, Message]
_NO_END = 2**64

_RECORD_HEADER = struct.Struct("<BQ")  # opcode, record length
_MESSAGE_HEADER = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_INDEX_HEADER = struct.Struct("<HI")  # channel id, byte length of the (time, offset) pairs


def indexed_topic_messages(
    file: IO[bytes],
    summary: Summary,
    topics: str | Sequence[str],
    start_ns: int | None,
    end_ns: int | None,
) -> Iterator[Record] | None:
    """The messages of `topics` (one name or several) with log time in [start_ns, end_ns)
    (None: unbounded), or None when a chunk that may hold them has no message index (the
    caller then reads the chunks whole, as it does without mcap's queue)."""
    if make_message_queue is None:
        return None
    start_ns = 0 if start_ns is None else start_ns
    end_ns = _NO_END if end_ns is None else end_ns
    wanted = {topics} if isinstance(topics, str) else set(topics)
    channels = {cid: ch for cid, ch in summary.channels.items() if ch.topic in wanted}
    chunks = [
        chunk
        for chunk in summary.chunk_indexes
        if chunk.message_end_time >= start_ns and chunk.message_start_time < end_ns
    ]
    if any(not chunk.message_index_offsets for chunk in chunks):
        return None
    return _messages(file, summary, channels, chunks, start_ns, end_ns)


def _messages(
    file: IO[bytes],
    summary: Summary,
    channels: dict[int, Channel],
    chunks: list[ChunkIndex],
    start_ns: int,
    end_ns: int,
) -> Iterator[Record]:
    queue = make_message_queue(log_time_order=True, reverse=False)
    for chunk in chunks:
        if any(cid in chunk.message_index_offsets for cid in channels):
            queue.push(chunk)
    while queue:
        item = queue.pop()
        if not isinstance(item, ChunkIndex):
            yield item[0]
            continue
        offsets = sorted(
            offset
            for cid in channels
            if cid in item.message_index_offsets
            for log_time, offset in _index_entries(file, item.message_index_offsets[cid])
            if start_ns <= log_time < end_ns
        )
        if not offsets:
            continue
        data = _chunk_data(file, item)
        for offset in offsets:
            message = _message_at(data, offset)
            channel = channels.get(message.channel_id)
            if channel is None:
                raise McapError(f"the message index points to channel {message.channel_id}")
            schema = summary.schemas.get(channel.schema_id) if channel.schema_id else None
            queue.push(((schema, channel, message), item.chunk_start_offset, offset))


def _index_entries(file: IO[bytes], position: int) -> list[tuple[int, int]]:
    """(log time, offset in the chunk's records) of one MessageIndex record."""
    file.seek(position)
    opcode, length = _RECORD_HEADER.unpack(file.read(_RECORD_HEADER.size))
    body = file.read(length)
    if opcode != Opcode.MESSAGE_INDEX or len(body) != length or length < _INDEX_HEADER.size:
        raise McapError(f"no message index record at offset {position}")
    _, size = _INDEX_HEADER.unpack_from(body)
    pairs = body[_INDEX_HEADER.size : _INDEX_HEADER.size + size]
    if size % 16 or len(pairs) != size:
        raise McapError(f"malformed message index at offset {position}")
    values = struct.unpack(f"<{size // 8}Q", pairs)
    return list(zip(values[::2], values[1::2], strict=True))


def _chunk_data(file: IO[bytes], index: ChunkIndex) -> bytes:
    """The chunk's records, decompressed within the chunk cap and their CRC checked, as the
    SeekingReader does."""
    file.seek(index.chunk_start_offset + _RECORD_HEADER.size)
    chunk = Chunk.read(ReadDataStream(file))
    return chunk_records(chunk, validate_crc=True)


def _message_at(data: bytes, offset: int) -> Message:
    opcode, length = _RECORD_HEADER.unpack_from(data, offset)
    body = offset + _RECORD_HEADER.size
    if opcode != Opcode.MESSAGE or length < _MESSAGE_HEADER.size or body + length > len(data):
        raise McapError(f"no message record at chunk offset {offset}")
    channel_id, sequence, log_time, publish_time = _MESSAGE_HEADER.unpack_from(data, body)
    payload = data[body + _MESSAGE_HEADER.size : body + length]
    return Message(
        channel_id=channel_id,
        log_time=log_time,
        data=payload,
        publish_time=publish_time,
        sequence=sequence,
    )
