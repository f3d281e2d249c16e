#!/usr/bin/env python3
"""CPU of the place search's SAD windows with the frame vectors in memory or spilled to a file.

36,000 random frame vectors (the 10 Hz hour's count) in a uint8 `FrameStore`, once in memory
and once with `pipeline.frame_spill.FileSpill` (the newest two blocks resident); 2,000 windows
of 300 columns against a 30-frame query, three alternating rounds, `time.process_time`.

    python -m bench.frame_spill
"""

from __future__ import annotations

import time

import numpy as np

from doseqslam_logs.detector.difference import FrameStore, sad_columns
from doseqslam_logs.pipeline.frame_spill import FileSpill

FRAMES, WINDOWS, COLUMNS, QUERIES, ROUNDS = 36_000, 2_000, 300, 30, 3


def main() -> None:
    rng = np.random.default_rng(0)
    vectors = rng.standard_normal((FRAMES, 2048)).astype(np.float32)
    with FileSpill() as spill:
        stores = {
            "memory": FrameStore(2048, "uint8"),
            "spilled": FrameStore(2048, "uint8", spill=spill),
        }
        for store in stores.values():
            for vector in vectors:
                store.append(vector)
        starts = rng.integers(0, FRAMES - QUERIES - COLUMNS, WINDOWS)
        seconds = dict.fromkeys(stores, 0.0)
        for _ in range(ROUNDS):
            for name, store in stores.items():
                queries = store.rows(FRAMES - QUERIES, FRAMES - 1)
                start = time.process_time()
                for first in starts:
                    sad_columns(queries, store, int(first), int(first) + COLUMNS)
                seconds[name] += time.process_time() - start
        for name, store in stores.items():
            per_window = 1e3 * seconds[name] / (ROUNDS * WINDOWS)
            print(f"{name}: {per_window:.3f} ms CPU a window, {store.nbytes / 2**20:.0f} MB held")


if __name__ == "__main__":
    main()
