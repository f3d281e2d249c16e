"""How an output MCAP's chunks are written (`--compression`, `--chunk-size`).

Apart from the writers (`mcap_writer`, `pose_topic`), which import the records and the
geometric checks, so that the command line can show the choices and defaults without them.
"""

from __future__ import annotations

from dataclasses import dataclass

from mcap.writer import CompressionType

CHUNK_SIZE = 1024 * 1024  # the default; with the compression, part of the output's bytes
COMPRESSIONS = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}


@dataclass(frozen=True)
class OutputFormat:
    """How the output's chunks are written (`--compression`, `--chunk-size`, as `mcap` has)."""

    compression: str = "zstd"  # a key of COMPRESSIONS
    chunk_size: int = CHUNK_SIZE  # bytes of messages per chunk, before compression

    def __post_init__(self) -> None:
        """Raises ValueError for an unknown compression or a chunk size below 1."""
        if self.compression not in COMPRESSIONS:
            raise ValueError(f"unknown compression {self.compression!r}")
        if self.chunk_size < 1:
            raise ValueError(f"the chunk size must be >= 1, got {self.chunk_size}")
