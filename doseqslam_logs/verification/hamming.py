"""The two nearest binary descriptors of each query descriptor, by Hamming distance.

The ratio test of every checked frame pair needs them, and they are a large share of the
verification's time: OpenCV's `batchDistance` counts bits with a lookup table in its portable
build, where faiss's exact flat binary index uses the processor's popcount, several times faster
(docs/performance.md). Distances are exact integers either way, so the matches the ratio test
keeps are the same, bit for bit, on any machine and with either: a kept match's nearest
neighbour is strictly nearer than the second (d0 < ratio * d1), so no tie decides it, and the
second distance is a value, not an index (tested against OpenCV's). OpenCV's is used when faiss
is not installed.
"""

from __future__ import annotations

import importlib
import threading
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

Descriptors = npt.NDArray[np.uint8]


def _load_faiss() -> Any:
    try:
        return importlib.import_module("faiss")
    except ImportError:  # pragma: no cover - faiss is a dependency; OpenCV stands in for it
        return None


_faiss: Any = _load_faiss()
_threads = threading.local()


def two_nearest(
    queries: Descriptors, database: Descriptors
) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.int64]]:
    """(distances, indices), each (len(queries), 2): the nearest and second nearest row of
    `database` (at least 2 rows) for each row of `queries`, uint8 rows of equal width."""
    if _faiss is None or queries.shape[1] % 8:  # faiss: whole 64-bit words (ORB, BRISK)
        return opencv_two_nearest(queries, database)
    if not getattr(_threads, "single", False):
        # OpenMP would run each search on every core, against the verification's own threads
        # (one pair per thread): one OpenMP thread per calling thread (the setting is the
        # thread's own).
        _faiss.omp_set_num_threads(1)
        _threads.single = True
    index = _faiss.IndexBinaryFlat(8 * database.shape[1])
    index.add(np.ascontiguousarray(database))
    distances, indices = index.search(np.ascontiguousarray(queries), 2)
    return np.asarray(distances, np.int32), np.asarray(indices, np.int64)


def opencv_two_nearest(
    queries: Descriptors, database: Descriptors
) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.int64]]:
    """`two_nearest` by OpenCV's brute force (BFMatcher's knnMatch kernel)."""
    distances, indices = cv2.batchDistance(
        queries, database, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=2
    )
    return np.asarray(distances, np.int32), np.asarray(indices, np.int64)
