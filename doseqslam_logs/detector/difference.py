"""Frame vectors kept in fixed-size blocks, and SAD difference rows against them (paper eq. 1).

Blocks are never reallocated, so memory grows linearly with the number of frames (no doubling
overshoot), and a difference row is computed one block at a time.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float32]


class FrameStore:
    """Append-only storage of equal-length float32 frame vectors."""

    def __init__(self, dimension: int, block_frames: int = 4096) -> None:
        self.dimension = dimension
        self.block_frames = block_frames
        self._blocks: list[FloatArray] = []
        self._count = 0

    def __len__(self) -> int:
        return self._count

    def append(self, vector: FloatArray) -> int:
        """Store one vector; returns its index."""
        offset = self._count % self.block_frames
        if offset == 0:
            self._blocks.append(np.empty((self.block_frames, self.dimension), np.float32))
        self._blocks[-1][offset] = vector
        self._count += 1
        return self._count - 1

    def rows(self, first: int, last: int) -> FloatArray:
        """Vectors first..last inclusive as one (n, dimension) array (a copy)."""
        out = np.empty((last - first + 1, self.dimension), np.float32)
        for row, index in enumerate(range(first, last + 1)):
            out[row] = self.vector(index)
        return out

    def vector(self, index: int) -> FloatArray:
        block, offset = divmod(index, self.block_frames)
        vector: FloatArray = self._blocks[block][offset]
        return vector

    def blocks(self, count: int) -> list[FloatArray]:
        """Views of the first `count` vectors, block by block."""
        views = []
        for start in range(0, count, self.block_frames):
            block = self._blocks[start // self.block_frames]
            views.append(block[: min(self.block_frames, count - start)])
        return views

    @property
    def nbytes(self) -> int:
        return sum(b.nbytes for b in self._blocks)


def sad_rows(queries: FloatArray, store: FrameStore, database_size: int) -> FloatArray:
    """D[q, j] = mean |queries[q] - store[j]| for j < database_size (paper eq. 1).

    Returns a (len(queries), database_size) float32 array. Each database block is read once
    for all query rows, which keeps it in cache while the rows are computed.
    """
    out = np.empty((len(queries), database_size), np.float32)
    scale = np.float32(1.0 / store.dimension)
    start = 0
    for block in store.blocks(database_size):
        stop = start + len(block)
        for row, query in enumerate(queries):
            out[row, start:stop] = np.abs(block - query).sum(axis=1, dtype=np.float32) * scale
        start = stop
    return out
