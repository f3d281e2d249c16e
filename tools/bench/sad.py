#!/usr/bin/env python3
"""The difference-row kernels and the contrast enhancement, side by side, on one machine.

One query sequence (29 frames, the mean sequence length on the 1-hour log) against a database
of frame vectors (36,000 frames = the whole 1-hour 10 Hz log by default). Every kernel's rows
are checked against the reference before its time is printed. CPU time (process_time) is
reported beside wall time: on a shared machine it is the steadier of the two.

    python -m bench.sad                      # 36,000 frames
    python -m bench.sad --frames 10000 --repeat 3
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable

import cv2
import numpy as np
import numpy.typing as npt

from doseqslam_logs.detector import enhance as enhance_module
from doseqslam_logs.detector.difference import FrameStore, sad_rows

U8 = npt.NDArray[np.uint8]
DIMENSION = 2048
SEQUENCE = 29
SLICE = 1024


def database(frames: int, seed: int = 0) -> U8:
    """Quantized patch-normalized vectors look like this: centred on 128, spread ~16 per sd."""
    rng = np.random.default_rng(seed)
    values = rng.normal(128, 16, (frames, DIMENSION))
    return np.clip(np.rint(values), 0, 255).astype(np.uint8)


def float32_numpy(queries: U8, db: U8) -> npt.NDArray[np.int64]:
    """The first implementation: float32 vectors, NumPy abs-difference and sum (per 4096)."""
    dbf = db.astype(np.float32)
    out = np.empty((len(queries), len(db)), np.int64)
    for row, query in enumerate(queries.astype(np.float32)):
        for s in range(0, len(db), 4096):
            part = dbf[s : s + 4096]
            out[row, s : s + len(part)] = np.abs(part - query).sum(axis=1)
    return out


def int16_numpy(queries: U8, db: U8) -> npt.NDArray[np.int64]:
    """uint8 vectors, widened to int16 per slice, NumPy abs and integer sum."""
    out = np.empty((len(queries), len(db)), np.int64)
    for row, query in enumerate(queries.astype(np.int16)):
        for s in range(0, len(db), SLICE):
            part = db[s : s + SLICE].astype(np.int16)
            out[row, s : s + len(part)] = np.abs(part - query).sum(axis=1, dtype=np.int32)
    return out


def absdiff_whole(queries: U8, db: U8) -> npt.NDArray[np.int64]:
    """cv2.absdiff + cv2.reduce against the whole database at once (one 73 MB temporary)."""
    out = np.empty((len(queries), len(db)), np.int64)
    for row, query in enumerate(queries):
        diff = cv2.absdiff(db, np.tile(query, (len(db), 1)))
        out[row] = cv2.reduce(diff, 1, cv2.REDUCE_SUM, dtype=cv2.CV_32S).ravel()
    return out


def absdiff_sliced(queries: U8, db: U8) -> npt.NDArray[np.int64]:
    """The same in 1024-frame slices, one query row at a time: temporaries stay in cache."""
    out = np.empty((len(queries), len(db)), np.int64)
    for row, query in enumerate(queries):
        tile = np.tile(query, (SLICE, 1))
        for s in range(0, len(db), SLICE):
            part = db[s : s + SLICE]
            diff = cv2.absdiff(part, tile[: len(part)])
            out[row, s : s + len(part)] = cv2.reduce(
                diff, 1, cv2.REDUCE_SUM, dtype=cv2.CV_32S
            ).ravel()
    return out


def absdiff_blocked(queries: U8, db: U8, block: int = 256) -> npt.NDArray[np.int64]:
    """A blocked formulation: each database slice is loaded once for all rows of the
    sequence (the slice stays in cache, but every row needs its own query tile)."""
    out = np.empty((len(queries), len(db)), np.int64)
    tiles = [np.tile(query, (block, 1)) for query in queries]
    for s in range(0, len(db), block):
        part = db[s : s + block]
        for row, tile in enumerate(tiles):
            diff = cv2.absdiff(part, tile[: len(part)])
            out[row, s : s + len(part)] = cv2.reduce(
                diff, 1, cv2.REDUCE_SUM, dtype=cv2.CV_32S
            ).ravel()
    return out


def query_rows_slices(queries: U8, db: U8, slice_frames: int = 32) -> npt.NDArray[np.int64]:
    """The kernel before 2026-12-01: queries as batchDistance's rows, K = a 32-frame database
    slice, scattered back by index."""
    n = len(db)
    distances = np.empty((len(queries), n), np.int32)
    columns = np.empty((len(queries), n), np.int32)
    for start in range(0, n, slice_frames):
        part = db[start : start + slice_frames]
        dist, index = cv2.batchDistance(
            queries, part, cv2.CV_32S, normType=cv2.NORM_L1, K=len(part)
        )
        distances[:, start : start + len(part)] = dist
        columns[:, start : start + len(part)] = index + start
    sums = np.empty((len(queries), n), np.int64)
    np.put_along_axis(sums, columns, distances, axis=1)
    return sums


def library_kernel(db: U8) -> Callable[[U8, U8], npt.NDArray[np.int64]]:
    """What the detector runs: difference.sad_rows on a uint8 FrameStore (built here,
    outside the timed part)."""
    store = FrameStore(DIMENSION, "uint8")
    for vector in db:  # (q - 128) / 16 quantizes back to q exactly
        store.append((vector.astype(np.float32) - 128) / 16)

    def kernel(queries: U8, _: U8) -> npt.NDArray[np.int64]:
        rows = sad_rows(queries, store, len(db))
        return np.rint(rows.astype(np.float64) * 16 * DIMENSION).astype(np.int64)

    return kernel


def norm_per_pair(queries: U8, db: U8, pairs: int = 300) -> tuple[float, bool]:
    """cv2.norm(a, b, NORM_L1) per pair from Python: ms per full row, extrapolated."""
    expected = np.abs(queries[:1].astype(np.int64) - db[:pairs].astype(np.int64)).sum(axis=1)
    start = time.perf_counter()
    got = [cv2.norm(queries[0], db[j], cv2.NORM_L1) for j in range(pairs)]
    per_pair = (time.perf_counter() - start) / pairs
    return per_pair * len(db) * 1e3, bool(np.array_equal(np.array(got, np.int64), expected))


def batch_distance(queries: U8, db: U8) -> str:
    """cv2.batchDistance(NORM_L1, K=0): every distance in one call, if the binding allows."""
    try:
        dist, _ = cv2.batchDistance(queries, db[:100], cv2.CV_32S, normType=cv2.NORM_L1, K=0)
    except cv2.error as exc:
        return "fails: " + str(exc).strip().splitlines()[-1].split(") ", 1)[-1]
    return f"works ({dist.shape})"


def bandwidth_floor(queries: U8, db: U8) -> float:
    """cv2.norm(NORM_L1) over the database: one read of it, ms per row."""
    start = time.perf_counter()
    for _ in queries[:5]:
        cv2.norm(db, cv2.NORM_L1)
    return (time.perf_counter() - start) / 5 * 1e3


def timed(
    kernel: Callable[[U8, U8], npt.NDArray[np.int64]], queries: U8, db: U8, repeat: int
) -> tuple[npt.NDArray[np.int64] | None, float, float]:
    """The kernel's rows (None when `repeat` is 0) and its best wall and CPU ms per row."""
    best_wall = best_cpu = float("inf")
    out = None
    for _ in range(repeat):
        wall, cpu = time.perf_counter(), time.process_time()
        out = kernel(queries, db)
        best_wall = min(best_wall, time.perf_counter() - wall)
        best_cpu = min(best_cpu, time.process_time() - cpu)
    return out, best_wall * 1e3 / len(queries), best_cpu * 1e3 / len(queries)


def enhancement_rows(frames: int, chunk: int, repeat: int) -> tuple[float, npt.NDArray[np.float32]]:
    rng = np.random.default_rng(1)
    sums = rng.integers(20_000, 60_000, (SEQUENCE, frames))
    rows = (sums * (1.0 / (16 * DIMENSION))).astype(np.float32)
    saved = enhance_module.CHUNK_ELEMENTS
    enhance_module.CHUNK_ELEMENTS = chunk
    try:
        best = float("inf")
        for _ in range(repeat):
            cpu = time.process_time()
            out = enhance_module.enhance(rows, 10)
            best = min(best, time.process_time() - cpu)
    finally:
        enhance_module.CHUNK_ELEMENTS = saved
    return best * 1e3 / SEQUENCE, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=36_000)
    parser.add_argument("--repeat", type=int, default=2, help="best of this many runs")
    parser.add_argument(
        "--rows", type=int, default=SEQUENCE, help="query rows (a sequence's length)"
    )
    args = parser.parse_args()
    db = database(args.frames)
    queries = db[1000 : 1000 + args.rows].copy()
    print(
        f"{args.rows} query rows x {args.frames:,} frames x {DIMENSION} bytes; load average "
        f"{os.getloadavg()[0]:.1f}\n"
    )
    print("| kernel | wall ms per row | CPU ms per row | rows identical |")
    print("|---|---|---|---|")
    kernels = [
        ("float32 NumPy `abs(D - q).sum(1)`", float32_numpy),
        ("uint8 -> int16 NumPy, 1024-frame slices", int16_numpy),
        ("uint8 `cv2.absdiff` + `cv2.reduce`, whole database", absdiff_whole),
        ("uint8 `cv2.absdiff` + `cv2.reduce`, 1024-frame slices", absdiff_sliced),
        ("uint8 blocked: 256-frame slice x all rows", absdiff_blocked),
        (
            "`cv2.batchDistance(NORM_L1, K=32)`, the queries x each 32-frame slice, scattered "
            "back by index (the kernel before 2026-12-01)",
            query_rows_slices,
        ),
        (
            "`difference.sad_rows`: up to 48 queries `cv2.batchDistance(NORM_L1, K=group)`, "
            "each 1024-frame chunk x groups of 32 queries; above, the kernel before",
            library_kernel(db),
        ),
    ]
    exact = None
    for name, kernel in kernels:
        out, wall, cpu = timed(kernel, queries, db, args.repeat)
        assert out is not None
        exact = out if exact is None else exact
        print(f"| {name} | {wall:.2f} | {cpu:.2f} | {np.array_equal(out, exact)} |", flush=True)
    per_row, same = norm_per_pair(queries, db)
    print(
        f"| `cv2.norm(a, b, NORM_L1)` per pair from Python (extrapolated) | {per_row:.0f} | "
        f"| {same} |"
    )
    print(f"| `cv2.batchDistance(NORM_L1, K=0)` | {batch_distance(queries, db)} | | |")
    print(
        f"| memory-bandwidth floor: `cv2.norm(D, NORM_L1)`, one read | "
        f"{bandwidth_floor(queries, db):.2f} | | |"
    )
    print("\n| enhancement chunk (elements) | CPU ms per row | output identical |")
    print("|---|---|---|")
    base = None
    for chunk in (1 << 20, 1 << 15):
        ms, enhanced = enhancement_rows(args.frames, chunk, args.repeat)
        base = enhanced if base is None else base
        print(f"| {chunk:,} | {ms:.2f} | {np.array_equal(enhanced, base)} |")


if __name__ == "__main__":
    main()
