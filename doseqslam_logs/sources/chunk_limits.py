"""A cap on what one MCAP chunk may decompress to, checked before it is decompressed.

A chunk's compressed bytes are bounded by the file, but what they decompress to is not: a few kB
of zstd can claim (and really hold) gigabytes. The mcap library decompresses a chunk whole, and
its zstd path even trusts the zstd frame's own content size over the chunk's
`uncompressed_size`. Every chunk this package reads goes through `chunk_data_stream`:

* a chunk that claims more than `MAX_CHUNK_BYTES` uncompressed is refused before any byte is
  decompressed (`ChunkTooLargeError`);
* a chunk is decompressed into at most its claimed size plus one byte, so one that holds more
  than it claims is refused too, without the rest being produced.

`install()` puts `chunk_data_stream` in place of the library's `get_chunk_data_stream`, which
every one of its readers (StreamReader, SeekingReader, NonSeekingReader, `breakup_chunk`) calls
by its module-global name: there is no other hook, and a reader that bypassed the cap would
undo it for the whole package.
"""

from __future__ import annotations

import io
import zlib

import mcap.stream_reader
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError, UnsupportedCompressionError
from mcap.records import Chunk
from mcap.stream_reader import CRCValidationError

# The largest uncompressed chunk read (1 GiB). Writers cut chunks at about 1 MiB (mcap's Python
# and Go writers, rosbag2's default 768 KiB) and a chunk only outgrows that by one message
# larger than the chunk size: a raw image at the pixel cap is 201 MB (8192 x 8192 bgr8).
MAX_CHUNK_BYTES = 1 << 30


class ChunkTooLargeError(McapError):
    """A chunk claims (or holds) more uncompressed bytes than the cap allows."""


def check_chunk_size(claimed: int) -> None:
    """Raises ChunkTooLargeError when a chunk's `uncompressed_size` is over the cap."""
    if claimed > MAX_CHUNK_BYTES:
        raise ChunkTooLargeError(
            f"a chunk claims {claimed} bytes uncompressed, more than the cap of "
            f"{MAX_CHUNK_BYTES} bytes: a decompression bomb or a corrupt size field"
        )


def decompress_at_most(compression: str, data: bytes, limit: int) -> bytes:
    """Up to `limit` bytes of `data` decompressed (lz4 or zstd frames; "" is returned as it
    is). A frame cut short gives what decompresses before the cut, as a streaming reader does."""
    if compression == "zstd":
        return _zstd_at_most(data, limit)
    if compression == "lz4":
        import lz4.frame

        lz4_out: bytes = lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=limit)
        return lz4_out
    if compression == "":
        return data[:limit]
    raise UnsupportedCompressionError(compression)


def _zstd_at_most(data: bytes, limit: int) -> bytes:
    import zstandard

    try:
        # A frame whose header states a size within the limit is decompressed in one call
        # into exactly that size (zstd fails a frame that holds more): much faster than the
        # stream, which matters to the verification stage's re-reads.
        if 0 <= zstandard.frame_content_size(data) < limit:
            whole: bytes = zstandard.decompress(data, max_output_size=limit)
            return whole
    except zstandard.ZstdError:
        pass  # cut short or damaged: the stream gives what decompresses before the damage
    out: bytes = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data)).read(limit)
    return out


def chunk_records(chunk: Chunk, validate_crc: bool = False) -> bytes:
    """The chunk's records, decompressed within the cap and the chunk's own claimed size,
    their CRC checked when asked (and the chunk has one), as the mcap library does."""
    check_chunk_size(chunk.uncompressed_size)
    data = decompress_at_most(chunk.compression, chunk.data, chunk.uncompressed_size + 1)
    if len(data) > chunk.uncompressed_size:
        raise ChunkTooLargeError(
            f"a chunk decompresses to more than the {chunk.uncompressed_size} bytes it claims"
        )
    if validate_crc and chunk.uncompressed_crc != 0:
        actual = zlib.crc32(data)
        if actual != chunk.uncompressed_crc:
            raise CRCValidationError(expected=chunk.uncompressed_crc, actual=actual, record=chunk)
    return data


def chunk_data_stream(chunk: Chunk, validate_crc: bool = False) -> tuple[ReadDataStream, int]:
    """`mcap.stream_reader.get_chunk_data_stream` with the cap: same signature and result."""
    data = chunk_records(chunk, validate_crc)
    return ReadDataStream(io.BytesIO(data)), len(data)


def install() -> None:
    """Make the mcap library's readers decompress chunks through `chunk_data_stream`."""
    mcap.stream_reader.get_chunk_data_stream = chunk_data_stream


install()
