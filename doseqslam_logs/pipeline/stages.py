"""The stages of a run and who hears them (`StageObserver`): a module of its own, free of the
run's heavy imports, so that the command line's progress can be one without loading them."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ..detector import Detector

# The stages of a run, as `annotate_log(stage=...)` announces them when each begins.
STAGES = ("replay", "verify", "metric", "write")
StageCallback = Callable[[str], None]


class StageObserver:
    """Hears a run's stages: the command's progress, the batch workers, the memory probe
    (tools/bench/memory_stages.py) and the tests watch a run through one of these. Each method
    does nothing here; a subclass overrides the ones it needs."""

    def started(self, stage: str) -> None:
        """`stage`, one of STAGES, begins ("verify" and "metric" only with verification)."""

    def detector_made(self, detector: Detector) -> None:
        """The replay's detector, before its first frame. The run frees it when the replay
        ends: an observer that keeps it must let it go at `finished("replay", ...)`."""

    def finished(self, stage: str, product: object) -> None:
        """A step ended with its product: "replay" a ReplayResult, "verify" a Verification,
        "metric" a MetricEdges, "annotations" the Annotations (our messages, built before the
        write), "write" the WriteSummary."""

    def advanced(self, stage: str, done: int, total: int | None) -> None:
        """How far a stage after the replay is (the replay reports through `progress`):
        "verify" in sequences, "metric" in fits, "write" in input messages copied; `total`
        None when unknown. Called from the stage's threads."""


class _Announcing(StageObserver):
    """`observer`, and `stage(name)` as each stage begins."""

    def __init__(self, stage: StageCallback, observer: StageObserver) -> None:
        self.stage, self.observer = stage, observer

    def started(self, stage: str) -> None:
        self.stage(stage)
        self.observer.started(stage)

    def detector_made(self, detector: Detector) -> None:
        self.observer.detector_made(detector)

    def finished(self, stage: str, product: object) -> None:
        self.observer.finished(stage, product)

    def advanced(self, stage: str, done: int, total: int | None) -> None:
        self.observer.advanced(stage, done, total)


def observer_of(stage: StageCallback | None, observer: StageObserver | None) -> StageObserver:
    """One observer for a run's `stage` callback and `observer` (either may be None)."""
    observer = observer or StageObserver()
    return observer if stage is None else _Announcing(stage, observer)
