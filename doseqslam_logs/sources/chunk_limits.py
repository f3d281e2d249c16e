"""A cap on what one MCAP chunk may decompress to, checked before it is decompressed.

A chunk's compressed bytes are bounded by the file, but what they decompress to is not: a few kB
of zstd can claim (and really hold) gigabytes. The mcap library decompresses a chunk whole, and
its zstd path even trusts the zstd frame's own content size over the chunk's
`uncompressed_size`. Every chunk this package reads goes through `chunk_data_stream`:

* a chunk that claims more than `MAX_CHUNK_BYTES` uncompressed is refused before any byte is
  decompressed (`ChunkTooLargeError`);
* a chunk is decompressed into at most its claimed size plus one byte, so one that holds more
  than it claims is refused too, without the rest being produced.

A chunk whose size field is wrong is refused there, by the readers of a plain run: they have
nowhere to say that a chunk lied, and reading it anyway would change a run's results silently.
`annotate --recover` reads it with `stream_chunk_records`, which trusts no size field (its
recovery report counts the chunk), so the cap bounds memory there, not what is kept.

`install()` puts `chunk_data_stream` in place of the library's `get_chunk_data_stream`, which
every one of its readers (StreamReader, SeekingReader, NonSeekingReader, `breakup_chunk`) calls
by its module-global name: there is no other hook, and a reader that bypassed the cap would
undo it for the whole package.
"""

from __future__ import annotations

import io
import zlib
from collections.abc import Iterator

import mcap.stream_reader
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError, UnsupportedCompressionError
from mcap.records import Chunk
from mcap.stream_reader import CRCValidationError

# The largest uncompressed chunk read (1 GiB). Writers cut chunks at about 1 MiB (mcap's Python
# and Go writers, rosbag2's default 768 KiB) and a chunk only outgrows that by one message
# larger than the chunk size: a raw image at the pixel cap is 201 MB (8192 x 8192 bgr8).
MAX_CHUNK_BYTES = 1 << 30
# What `stream_chunk_records` decompresses at a time while it measures a chunk.
_BLOCK_BYTES = 1 << 20


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


def stream_chunk_records(chunk: Chunk, validate_crc: bool = False) -> bytes:
    """The chunk's records whatever its `uncompressed_size` says: an uncompressed chunk's data
    as it is, a compressed one's as a streaming decompressor reads them.

    A first pass measures them (length and CRC) a block at a time and stops just past the cap,
    so that neither a lying claim nor a bomb is ever allocated; only records that fit the cap
    and pass the CRC check (when asked, and the chunk has one) are decompressed again, into a
    buffer of their true size.

    Raises ChunkTooLargeError (more than the cap), CRCValidationError, or what the
    decompressor raises for data it cannot read.
    """
    size, crc = _measure(chunk.compression, chunk.data)
    if size > MAX_CHUNK_BYTES:
        raise ChunkTooLargeError(
            f"a chunk holds more than the cap of {MAX_CHUNK_BYTES} bytes uncompressed"
        )
    if validate_crc and chunk.uncompressed_crc not in (0, crc):
        raise CRCValidationError(expected=chunk.uncompressed_crc, actual=crc, record=chunk)
    data = decompress_at_most(chunk.compression, chunk.data, size + 1)
    if len(data) != size:  # the decompressor is deterministic: only a bug gets here
        raise McapError(f"a chunk decompressed to {size} bytes, then to {len(data)}")
    return data


def _measure(compression: str, data: bytes) -> tuple[int, int]:
    """The length and CRC of what `data` decompresses to, up to just past the cap."""
    size, crc = 0, 0
    for block in _blocks(compression, data):
        size, crc = size + len(block), zlib.crc32(block, crc)
        if size > MAX_CHUNK_BYTES:
            break
    return size, crc


def _blocks(compression: str, data: bytes) -> Iterator[bytes]:
    """`data` decompressed, a block of at most `_BLOCK_BYTES` at a time (a frame cut short
    ends where the decompressor stops, as in `decompress_at_most`)."""
    if compression == "":
        yield data
    elif compression == "zstd":
        import zstandard

        reader = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data))
        while block := reader.read(_BLOCK_BYTES):
            yield block
    elif compression == "lz4":
        import lz4.frame

        decompressor = lz4.frame.LZ4FrameDecompressor()
        yield decompressor.decompress(data, max_length=_BLOCK_BYTES)
        while not (decompressor.eof or decompressor.needs_input):
            yield decompressor.decompress(b"", max_length=_BLOCK_BYTES)
    else:
        raise UnsupportedCompressionError(compression)


def chunk_data_stream(chunk: Chunk, validate_crc: bool = False) -> tuple[ReadDataStream, int]:
    """`mcap.stream_reader.get_chunk_data_stream` with the cap: same signature and result."""
    data = chunk_records(chunk, validate_crc)
    return ReadDataStream(io.BytesIO(data)), len(data)


def install() -> None:
    """Make the mcap library's readers decompress chunks through `chunk_data_stream`."""
    mcap.stream_reader.get_chunk_data_stream = chunk_data_stream


install()
