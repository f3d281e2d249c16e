"""What every export format provides: options in, text out, one summary line for people; and
what `optimize` is asked (`OptimizeOptions`) and writes (`OPTIMIZED_POSE_TOPIC`, the paths).

Options and their defaults live here, apart from the pose-graph code (SciPy), so that the
command line can show them without importing it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from ..annotations.reader import AnnotatedLog
from ..annotations.records import OUR_TOPIC_PREFIX

# The loop-edge measurement model of docs/export.md: a loop closure says "same place", not how
# far apart the two cameras were, so its translation is weak and its rotation firmer.
DEFAULT_LOOP_TRANSLATION_SIGMA_M = 3.0
DEFAULT_LOOP_ROTATION_SIGMA_DEG = 10.0
# "metric": a loop edge uses the metric pose recorded on its pair, the placeholder
# where none was recorded; "placeholder": the placeholder model for every edge.
LoopModel = Literal["metric", "placeholder"]
LOOP_MODELS: tuple[LoopModel, ...] = ("metric", "placeholder")


@dataclass(frozen=True)
class ExportOptions:
    """Choices of one export; each format reads the ones it needs."""

    include_rejected: bool = False  # csv/jsonl: also the pairs verification rejected or skipped
    odometry_topic: str | None = None  # tum/g2o: the pose topic placed at camera times
    poses_log: Path | None = None  # where that topic lives (default: the annotated log itself)
    poses_log_check: bool = True  # refuse a poses_log that is not the annotated log's source
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


OPTIMIZED_POSE_TOPIC = OUR_TOPIC_PREFIX + "optimized_pose"
# The whole trajectories as one message each (nav_msgs/Path, foxglove.PosesInFrame), which a
# viewer draws as a line: the optimized one and the odometry it was optimized from.
OPTIMIZED_PATH_TOPIC = OUR_TOPIC_PREFIX + "optimized_path"
ODOMETRY_PATH_TOPIC = OUR_TOPIC_PREFIX + "odometry_path"

LoopKernel = Literal["cauchy", "huber", "none"]
LOOP_KERNELS: tuple[LoopKernel, ...] = ("cauchy", "huber", "none")

# Chosen on the generated and committed drives (docs/export.md, "Optimizing the pose graph").
DEFAULT_LOOP_KERNEL: LoopKernel = "cauchy"
DEFAULT_KERNEL_WIDTH = 1.0  # in whitened units (sigmas of the loop edge's Gaussian)
# chi2.ppf(0.99, 6): a right loop edge's squared error stays below it 99 % of the time.
DEFAULT_OUTLIER_BOUND = 16.812


@dataclass(frozen=True)
class OptimizeOptions:
    """How loop edges are weighed and checked."""

    loop_kernel: LoopKernel = DEFAULT_LOOP_KERNEL
    kernel_width: float = DEFAULT_KERNEL_WIDTH  # Cauchy c / Huber k, whitened units
    outlier_check: bool = True  # drop loop edges above outlier_bound and optimize again
    outlier_bound: float = DEFAULT_OUTLIER_BOUND  # on a loop edge's squared Mahalanobis error
    max_iterations: int = 100  # Levenberg-Marquardt, per round
    # The odometry's heading drift and covariance factor from the metric loop edges
    # (odometry_calibration.py); off: the odometry as /odom states it.
    calibrate_odometry: bool = True

    def __post_init__(self) -> None:
        """Raises ValueError for an unknown kernel or a width, bound or count that is not > 0."""
        if self.loop_kernel not in LOOP_KERNELS:
            raise ValueError(f"unknown loop kernel {self.loop_kernel!r}")
        if not (self.kernel_width > 0 and self.outlier_bound > 0 and self.max_iterations > 0):
            raise ValueError("kernel_width, outlier_bound and max_iterations must be > 0")
