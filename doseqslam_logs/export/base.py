"""What every export format provides: options in, text out, one summary line for people."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from ..annotations.reader import AnnotatedLog

# The loop-edge measurement model of docs/export.md: a loop closure says "same place", not how
# far apart the two cameras were, so its translation is weak and its rotation firmer.
DEFAULT_LOOP_TRANSLATION_SIGMA_M = 3.0
DEFAULT_LOOP_ROTATION_SIGMA_DEG = 10.0
# "metric": a loop edge uses the metric pose recorded on its pair (issue #20), the placeholder
# where none was recorded; "placeholder": the placeholder model for every edge.
LoopModel = Literal["metric", "placeholder"]
LOOP_MODELS: tuple[LoopModel, ...] = ("metric", "placeholder")


@dataclass(frozen=True)
class ExportOptions:
    """Choices of one export; each format reads the ones it needs."""

    include_rejected: bool = False  # csv/jsonl: also the pairs verification rejected or skipped
    odometry_topic: str | None = None  # tum/g2o: the pose topic placed at camera times
    poses_log: Path | None = None  # where that topic lives (default: the annotated log itself)
    stride: int = 1  # tum/g2o: keep every stride-th frame (plus loop-closure frames)
    loop_translation_sigma_m: float = DEFAULT_LOOP_TRANSLATION_SIGMA_M
    loop_rotation_sigma_deg: float = DEFAULT_LOOP_ROTATION_SIGMA_DEG
    use_verified_rotation: bool = True  # g2o: a verified pair's relative rotation, if recorded
    loop_model: LoopModel = "metric"  # g2o/optimize: loop edges' measurement (LOOP_MODELS)
    # g2o: odometry edges calibrated from the metric loop edges, as `optimize` does by default
    # (export/odometry_calibration.py); off, the odometry as /odom states it.
    calibrate_odometry: bool = False

    @property
    def loop_rotation_sigma_rad(self) -> float:
        return math.radians(self.loop_rotation_sigma_deg)


@dataclass(frozen=True)
class ExportResult:
    """The exported text (in pieces, written in order) and a line saying what it holds."""

    chunks: Iterable[str]
    summary: str


@dataclass(frozen=True)
class Exporter:
    """One output format: `export(log, options)` builds the text.

    `export` raises the package's errors (SourceError, UsageError) for input it cannot use.
    """

    name: str
    help: str
    needs_poses: bool
    export: Callable[[AnnotatedLog, ExportOptions], ExportResult]
