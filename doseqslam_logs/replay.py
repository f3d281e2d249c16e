"""The replay pipeline: frames -> detector -> decisions, with progress and counts."""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

from .detector import Detector, PreparedFrame, SequenceDecision
from .frames import Frame

ProgressCallback = Callable[[int], None]


@dataclass
class ReplayResult:
    """Every decision of a run, in the order the detector made them, and what it cost."""

    decisions: list[SequenceDecision] = field(default_factory=list)
    frames: int = 0
    wall_time_s: float = 0.0
    feature_detector: str = ""
    peak_detector_bytes: int = 0

    @property
    def loop_closures(self) -> int:
        return sum(len(d.loop_closures) for d in self.decisions)

    @property
    def frames_per_second(self) -> float:
        return self.frames / self.wall_time_s if self.wall_time_s > 0 else 0.0


def prepared_frames(
    frames: Iterable[Frame], detector: Detector, workers: int
) -> Iterator[tuple[Frame, PreparedFrame]]:
    """Frames with `detector.prepare` applied, in order; with workers > 1 a thread pool runs
    prepare ahead (OpenCV releases the GIL, so the second core works while the detector
    queries). At most 2 x workers frames are in flight, so memory stays bounded."""
    if workers <= 1:
        for frame in frames:
            yield frame, detector.prepare(frame.image)
        return
    with ThreadPoolExecutor(workers, thread_name_prefix="prepare") as pool:
        pending: deque[tuple[Frame, Future[PreparedFrame]]] = deque()
        for frame in frames:
            pending.append((frame, pool.submit(detector.prepare, frame.image)))
            if len(pending) >= 2 * workers:
                done, future = pending.popleft()
                yield done, future.result()
        while pending:
            done, future = pending.popleft()
            yield done, future.result()


def replay(
    frames: Iterable[Frame],
    detector: Detector,
    progress: ProgressCallback | None = None,
    workers: int = 1,
) -> ReplayResult:
    """Push every frame in order, then flush; `progress(frames_done)` after each frame.

    The decisions do not depend on `workers` (prepare is a pure function of the frame).
    """
    result = ReplayResult(feature_detector=detector.feature_detector)
    start = time.perf_counter()
    for frame, prepared in prepared_frames(frames, detector, workers):
        result.decisions += detector.push_prepared(frame.timestamp_ns, prepared)
        result.frames += 1
        if progress is not None:
            progress(result.frames)
    result.decisions += detector.finish()
    result.wall_time_s = time.perf_counter() - start
    result.peak_detector_bytes = detector.memory_bytes
    return result
