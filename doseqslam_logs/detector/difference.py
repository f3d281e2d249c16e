"""Frame vectors kept in fixed-size blocks, and SAD difference rows against them (paper eq. 1).

Blocks are never reallocated, so memory grows linearly with the number of frames (no doubling
overshoot), and difference rows are computed one cache-sized slice of the database at a time.

Vectors are stored as float32, or quantized to uint8 (`difference_precision = "uint8"`): a
patch-normalized value z lies within +-sqrt(63) < 127/16 for 8x8 patches, so
q = round(16 z) + 128 holds it without clipping, at a step of 1/16 standard deviation. The
uint8 path computes integer sums with OpenCV's SIMD L1 kernel (`sad_sums_uint8`): 4x less
memory than float32 and about 30x faster than float32 NumPy (tools/bench/sad.py measures every
kernel side by side).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Literal, Protocol

import cv2
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float32]
Precision = Literal["uint8", "float32"]

QUANTIZATION_SCALE = 16.0
QUANTIZATION_ZERO = 128
# The uint8 kernel's two layouts (`sad_sums_uint8`): up to SHORT_QUERIES queries, groups of
# QUERY_GROUP of them (64 KB, kept in the CPU's cache) against DATABASE_CHUNK frames per call;
# more queries, all of them against SLICE_FRAMES frames (a 64 KB slice) per call.
SHORT_QUERIES = 48
QUERY_GROUP = 32
DATABASE_CHUNK = 1024
SLICE_FRAMES = 32


def quantize(vector: FloatArray) -> npt.NDArray[np.uint8]:
    """round(16 z) + 128, clipped to 0..255 (no clipping happens for 8x8 patches)."""
    q = np.rint(vector * QUANTIZATION_SCALE) + QUANTIZATION_ZERO
    quantized: npt.NDArray[np.uint8] = np.clip(q, 0, 255).astype(np.uint8)
    return quantized


class ByteSpill(Protocol):
    """Where a `FrameStore` puts its older blocks: bytes written once at an offset and read
    back (pipeline.frame_spill keeps them in an unlinked temporary file; the detector core
    does no file I/O of its own)."""

    def write(self, offset: int, data: memoryview) -> None:
        """Keep `data` at `offset` (each offset is written once)."""

    def read_into(self, offset: int, out: memoryview) -> None:
        """Fill `out` with the bytes written from `offset` on."""


class FrameStore:
    """Append-only storage of equal-length frame vectors.

    With a `spill`, only the newest `resident_blocks` full blocks (and the one being filled)
    stay in memory; older blocks are written to the spill and read back when a search looks
    at them, so the store's memory stays flat however long the log (the indexed place search
    reads a few windows per sequence). The values read are the values stored.
    """

    def __init__(
        self,
        dimension: int,
        precision: Precision = "float32",
        block_frames: int = 4096,
        spill: ByteSpill | None = None,
        resident_blocks: int = 2,
    ) -> None:
        self.dimension = dimension
        self.precision = precision
        self.dtype = np.uint8 if precision == "uint8" else np.float32
        self.block_frames = block_frames
        self.spill = spill
        self.resident_blocks = resident_blocks
        self._blocks: list[npt.NDArray[np.generic] | None] = []  # None: in the spill
        self._count = 0

    def __len__(self) -> int:
        return self._count

    @property
    def block_bytes(self) -> int:
        return self.block_frames * self.dimension * self._itemsize

    @property
    def _itemsize(self) -> int:
        return int(np.dtype(self.dtype).itemsize)

    def append(self, vector: FloatArray) -> int:
        """Store one vector (quantized if the store is uint8); returns its index."""
        offset = self._count % self.block_frames
        if offset == 0:
            self._spill_old_blocks()
            self._blocks.append(np.empty((self.block_frames, self.dimension), self.dtype))
        block = self._blocks[-1]
        assert block is not None  # the newest block is never spilled
        block[offset] = quantize(vector) if self.precision == "uint8" else vector
        self._count += 1
        return self._count - 1

    def _spill_old_blocks(self) -> None:
        """Before a new block: full blocks beyond the newest `resident_blocks` go to the spill."""
        if self.spill is None:
            return
        for number in range(len(self._blocks) - self.resident_blocks):
            block = self._blocks[number]
            if block is not None:
                self.spill.write(number * self.block_bytes, block.data.cast("B"))
                self._blocks[number] = None

    def _block_rows(self, number: int, offset: int, take: int) -> npt.NDArray[np.generic]:
        """Rows offset .. offset+take-1 of block `number`: a view, or read from the spill."""
        block = self._blocks[number]
        if block is not None:
            return block[offset : offset + take]
        assert self.spill is not None
        row_bytes = self.dimension * self._itemsize
        start = number * self.block_bytes + offset * row_bytes
        rows = np.empty((take, self.dimension), self.dtype)
        self.spill.read_into(start, rows.data.cast("B"))
        return rows

    def rows(self, first: int, last: int) -> npt.NDArray[np.generic]:
        """Stored vectors first..last inclusive as one (n, dimension) array (a copy)."""
        out = np.empty((last - first + 1, self.dimension), self.dtype)
        row = 0
        for part in self.span(first, last + 1):
            out[row : row + len(part)] = part
            row += len(part)
        return out

    def blocks(self, count: int) -> list[npt.NDArray[np.generic]]:
        """The first `count` stored vectors, block by block (views of the blocks in memory)."""
        return self.span(0, count)

    def span(self, first: int, stop: int) -> list[npt.NDArray[np.generic]]:
        """Stored vectors first .. stop-1, block by block (views of the blocks in memory)."""
        views = []
        index = first
        while index < stop:
            block, offset = divmod(index, self.block_frames)
            take = min(self.block_frames - offset, stop - index)
            views.append(self._block_rows(block, offset, take))
            index += take
        return views

    @property
    def nbytes(self) -> int:
        """Bytes of the blocks in memory."""
        return sum(b.nbytes for b in self._blocks if b is not None)

    @property
    def spilled_bytes(self) -> int:
        return sum(self.block_bytes for b in self._blocks if b is None)


def sad_rows(queries: npt.NDArray[np.generic], store: FrameStore, database_size: int) -> FloatArray:
    """D[q, j] = mean |queries[q] - store[j]| for j < database_size (paper eq. 1).

    `queries` are stored vectors (`store.rows`). Returns a (len(queries), database_size)
    float32 array in the units of the patch-normalized values.
    """
    if store.precision == "uint8":
        return _sad_rows_uint8(queries, store, database_size)
    return _sad_rows_float32(queries, store, database_size)


def sad_columns(
    queries: npt.NDArray[np.generic], store: FrameStore, first: int, stop: int
) -> FloatArray:
    """`sad_rows` restricted to the database columns first .. stop-1: D[q, j - first].

    The same kernels on the same values, so each cell equals the full row's (the place
    search computes only windows around proposed places).
    """
    blocks = store.span(first, stop)
    if store.precision == "uint8":
        sums = sad_sums_uint8(np.ascontiguousarray(queries, dtype=np.uint8), blocks)
        scale = 1.0 / (QUANTIZATION_SCALE * store.dimension)
        return (sums * scale).astype(np.float32)
    return _sad_float32(queries, blocks, store.dimension)


def _sad_rows_float32(queries: npt.NDArray[np.generic], store: FrameStore, n: int) -> FloatArray:
    return _sad_float32(queries, store.blocks(n), store.dimension)


def _sad_float32(
    queries: npt.NDArray[np.generic], blocks: list[npt.NDArray[np.generic]], dimension: int
) -> FloatArray:
    n = sum(len(block) for block in blocks)
    out = np.empty((len(queries), n), np.float32)
    scale = np.float32(1.0 / dimension)
    start = 0
    for block in blocks:
        stop = start + len(block)
        for row, query in enumerate(queries):
            out[row, start:stop] = np.abs(block - query).sum(axis=1, dtype=np.float32) * scale
        start = stop
    return out


def _sad_rows_uint8(queries: npt.NDArray[np.generic], store: FrameStore, n: int) -> FloatArray:
    sums = sad_sums_uint8(np.ascontiguousarray(queries, dtype=np.uint8), store.blocks(n))
    scale = 1.0 / (QUANTIZATION_SCALE * store.dimension)
    return (sums * scale).astype(np.float32)


def sad_sums_uint8(
    queries: npt.NDArray[np.uint8],
    blocks: list[npt.NDArray[np.generic]],
    group: int = QUERY_GROUP,
    chunk: int = DATABASE_CHUNK,
) -> npt.NDArray[np.int32]:
    """Integer sums of absolute differences, queries x every frame of the blocks in order.

    `cv2.batchDistance(NORM_L1)` computes them with OpenCV's SIMD L1 kernel, but its Python
    binding refuses K = 0 ("every distance, no neighbour indices"). With K = the number of
    columns it returns every distance of each row, sorted, with the column of each: scattering
    them back by index gives the plain sums. Up to `SHORT_QUERIES` queries, the database frames
    are the rows and the queries (one group of at most `group`, in cache) the columns, `chunk`
    frames per call; longer sequences take the queries as rows and `SLICE_FRAMES`-frame slices
    of the database as columns, so the database streams past once for all of them. The first
    layout keeps a query group in cache and costs less CPU on short sequences, but it streams
    the database once per group, so it loses on long ones.
    """
    if len(queries) <= SHORT_QUERIES:
        return _sums_database_rows(queries, blocks, group, chunk)
    return _sums_query_rows(queries, blocks)


def _slices(
    blocks: list[npt.NDArray[np.generic]], frames: int
) -> Iterator[tuple[int, npt.NDArray[np.uint8]]]:
    """The database in order, at most `frames` frames at a time (never across a block's end),
    each slice with the index of its first frame."""
    start = 0
    for block in blocks:
        for first in range(0, len(block), frames):
            part = np.asarray(block[first : first + frames], dtype=np.uint8)
            yield start, part
            start += len(part)


def _sums_database_rows(
    queries: npt.NDArray[np.uint8], blocks: list[npt.NDArray[np.generic]], group: int, chunk: int
) -> npt.NDArray[np.int32]:
    n = sum(len(block) for block in blocks)
    sums = np.empty((n, len(queries)), np.int32)
    for first_query in range(0, len(queries), group):
        members = np.ascontiguousarray(queries[first_query : first_query + group])
        columns = slice(first_query, first_query + len(members))
        for start, part in _slices(blocks, chunk):
            dist, index = cv2.batchDistance(
                part, members, cv2.CV_32S, normType=cv2.NORM_L1, K=len(members)
            )
            order = np.asarray(index, dtype=np.intp)
            np.put_along_axis(sums[start : start + len(part), columns], order, dist, axis=1)
    return np.ascontiguousarray(sums.T)


def _sums_query_rows(
    queries: npt.NDArray[np.uint8], blocks: list[npt.NDArray[np.generic]]
) -> npt.NDArray[np.int32]:
    n = sum(len(block) for block in blocks)
    distances = np.empty((len(queries), n), np.int32)
    columns = np.empty((len(queries), n), np.int32)
    for start, part in _slices(blocks, SLICE_FRAMES):
        stop = start + len(part)
        dist, index = cv2.batchDistance(
            queries, part, cv2.CV_32S, normType=cv2.NORM_L1, K=len(part)
        )
        distances[:, start:stop] = dist
        columns[:, start:stop] = index + start
    sums = np.empty((len(queries), n), np.int32)
    np.put_along_axis(sums, columns, distances, axis=1)
    return sums
