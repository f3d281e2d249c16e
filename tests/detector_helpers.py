"""Helpers shared by the detector and verification tests: scripted segmentation, real frames,
and a detector decision built by hand."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from doseqslam_logs.detector.events import Candidate, SequenceDecision


class ScriptedSegmenter:
    """Starts a sequence exactly at the given frame indices (frame 0 always starts one)."""

    name = "scripted"

    def __init__(self, starts: Iterable[int]) -> None:
        self._starts = set(starts) | {0}
        self._index = -1

    def prepare(self, gray: npt.NDArray[np.uint8]) -> None:
        return None

    def update(self, prepared: None) -> bool:
        self._index += 1
        return self._index in self._starts

    def restart(self, prepared: None) -> None:
        self._index += 1

    def starts_sequence(self, gray: npt.NDArray[np.uint8]) -> bool:
        return self.update(self.prepare(gray))


def noise_frames(count: int, seed: int = 0, shape: tuple[int, int] = (48, 96)) -> list:
    """Distinct random gray frames: no two places look alike."""
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, shape, dtype=np.uint8) for _ in range(count)]


def rtabmap_frames(shared_data: Path) -> list[npt.NDArray[np.uint8]]:
    folder = shared_data / "rtabmap_samples_loop" / "images"
    return [cv2.imread(str(folder / f"{i}.jpg"), cv2.IMREAD_GRAYSCALE) for i in range(1, 85)]


def rtabmap_gt(shared_data: Path) -> npt.NDArray[np.bool_]:
    path = shared_data / "rtabmap_samples_loop" / "samples_GT.bmp"
    return np.asarray(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 0)


def sequence_decision(
    length: int,
    frame_ns: int,
    candidates: int = 0,
    first: int = 100,
    sequence_id: int = 0,
    match: int = 10,
    database_size: int | None = None,
) -> SequenceDecision:
    """A sequence of `length` frames from `first`, its first `candidates` frames matched to
    frames `match`, `match` + 1, ...; accepted when it has candidates. The database ends 10
    frames before the sequence unless `database_size` says otherwise."""
    pairs = tuple(
        Candidate(first + z, match + z, (first + z) * frame_ns, (match + z) * frame_ns, 1.0)
        for z in range(candidates)
    )
    return SequenceDecision(
        sequence_id=sequence_id,
        first_index=first,
        last_index=first + length - 1,
        first_timestamp_ns=first * frame_ns,
        last_timestamp_ns=(first + length - 1) * frame_ns,
        database_size=first - 10 if database_size is None else database_size,
        best_start=match,
        best_velocity=1.0,
        best_score=1.0,
        second_score=2.0,
        gamma=0.5,
        gamma_previous=None,
        gamma_next=None,
        f=0.5,
        threshold=0.99,
        accepted=bool(pairs),
        candidates=pairs,
        method="doseqslam",
    )


class DictSpill:
    """A ByteSpill in a dict, counting what it is asked."""

    def __init__(self) -> None:
        self.chunks: dict[int, bytes] = {}
        self.reads = 0

    def write(self, offset: int, data: memoryview) -> None:
        assert offset not in self.chunks
        self.chunks[offset] = bytes(data)

    def read_into(self, offset: int, out: memoryview) -> None:
        self.reads += 1
        start = max(o for o in self.chunks if o <= offset)
        chunk = self.chunks[start][offset - start :]
        assert len(chunk) >= len(out)  # a read never crosses a block
        out[:] = chunk[: len(out)]
