"""The replay pipeline: frames -> detector -> decisions, with progress and counts."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from .detector import Detector, SequenceDecision
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


def replay(
    frames: Iterable[Frame], detector: Detector, progress: ProgressCallback | None = None
) -> ReplayResult:
    """Push every frame in order, then flush; `progress(frames_done)` after each frame."""
    result = ReplayResult(feature_detector=detector.feature_detector)
    start = time.perf_counter()
    for frame in frames:
        result.decisions += detector.push(frame.timestamp_ns, frame.image)
        result.frames += 1
        if progress is not None:
            progress(result.frames)
    result.decisions += detector.finish()
    result.wall_time_s = time.perf_counter() - start
    result.peak_detector_bytes = detector.memory_bytes
    return result
