"""Loop closures of an annotated log as flat rows, and the time the detector gave each frame.

Rows have the same columns for every log: fields a log lacks (logs annotated without geometric
verification, or before it existed) are None, so a csv header never depends on the input.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from ..annotations.reader import AnnotatedLog
from ..annotations.records import (
    NO_METRIC,
    NOT_RECORDED,
    REJECTED,
    SKIPPED,
    FrameRef,
    LoopClosureRecord,
)
from ..errors import SourceError

ROTATION_COLUMNS = ("rotation_qx", "rotation_qy", "rotation_qz", "rotation_qw")
DIRECTION_COLUMNS = ("translation_dx", "translation_dy", "translation_dz")
METRIC_TRANSLATION_COLUMNS = ("metric_tx", "metric_ty", "metric_tz")
METRIC_ROTATION_COLUMNS = ("metric_qx", "metric_qy", "metric_qz", "metric_qw")
# Square roots of the covariance's diagonal (m, rad); None where unconstrained or absent.
METRIC_SIGMA_COLUMNS = (
    "metric_sigma_x",
    "metric_sigma_y",
    "metric_sigma_z",
    "metric_sigma_rx",
    "metric_sigma_ry",
    "metric_sigma_rz",
)

COLUMNS = (
    "query_index",
    "query_time_ns",  # the detector's time of the frame: header stamp, else log time
    "query_log_time_ns",
    "match_index",  # the detector's match, before any refinement
    "match_time_ns",
    "match_log_time_ns",
    "difference",
    "f",
    "threshold",
    "sequence_id",
    "method",
    "parameters_hash",
    "verification",  # "accepted" | "rejected" | "skipped" | "off"; None: not recorded
    "inliers",
    "refined_match_index",
    "refined_match_time_ns",
    "refined_match_log_time_ns",
    # Verification's relative pose (X_match = R X_query + t in camera coordinates): R as a
    # quaternion, and the unit direction of t (its scale is unknown).
    *ROTATION_COLUMNS,
    *DIRECTION_COLUMNS,
    # The metric relative pose (same convention, t in metres; docs/export.md): the method
    # ("depth_pnp" | "odometry_pnp" | "rotation_only"; "" none; None: not recorded), t
    # (None for rotation_only), R, sigmas, PnP inliers, RMS residual (px), and why a better
    # method was not used.
    "metric_method",
    *METRIC_TRANSLATION_COLUMNS,
    *METRIC_ROTATION_COLUMNS,
    *METRIC_SIGMA_COLUMNS,
    "metric_inliers",
    "metric_residual_px",
    "metric_reason",
)


def uses_header_stamps(log: AnnotatedLog) -> bool:
    """Whether the detector ran on header stamps (the default) rather than log times."""
    return log.metadata.time_source != "log"


def frame_time_ns(log: AnnotatedLog, frame: FrameRef) -> int:
    """The detector's time of a frame of a loop closure (query, match or refined match)."""
    return frame.time_ns if uses_header_stamps(log) else frame.log_time_ns


def frame_times_ns(log: AnnotatedLog) -> npt.NDArray[np.int64]:
    """The detector's time of every frame, by frame index.

    Raises SourceError for logs annotated before frame times were recorded.
    """
    times = log.detector_times_ns()
    if times is None:
        raise SourceError(
            f"{log.path}: holds no frame times (annotated by an older version); annotate it again"
        )
    return times


def selected_loop_closures(log: AnnotatedLog, include_rejected: bool) -> list[LoopClosureRecord]:
    """The reported loop closures, or with `include_rejected` every pair decided on (those on
    /doseqslam/candidates too)."""
    return list(log.loop_closures if include_rejected else log.reported_loop_closures)


def verification_count(log: AnnotatedLog, verdict: str) -> int:
    """Pairs decided on (reported or not) whose `verification` is `verdict`."""
    return sum(1 for lc in log.loop_closures if lc.verification == verdict)


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _verification_fields(log: AnnotatedLog, lc: LoopClosureRecord) -> dict[str, Any]:
    if lc.verification == NOT_RECORDED:
        names = ("verification", "inliers", "refined_match_index", "refined_match_time_ns")
        empty = dict.fromkeys((*names, "refined_match_log_time_ns"))
        return {**empty, **_spread(ROTATION_COLUMNS, None), **_spread(DIRECTION_COLUMNS, None)}
    refined = lc.matched
    return {
        "verification": lc.verification,
        "inliers": lc.inliers,
        "refined_match_index": refined.index,
        "refined_match_time_ns": frame_time_ns(log, refined),
        "refined_match_log_time_ns": refined.log_time_ns,
        **_spread(ROTATION_COLUMNS, lc.rotation_xyzw if lc.has_relative_pose else None),
        **_spread(DIRECTION_COLUMNS, lc.translation_direction if lc.has_relative_pose else None),
    }


def _metric_fields(lc: LoopClosureRecord) -> dict[str, Any]:
    """The metric columns; None in each for a pair with nothing recorded (older logs, pairs
    that are not accepted); the method "" and its reason for an accepted pair without one."""
    if lc.metric_method == NO_METRIC and not lc.metric_reason:
        names = ("metric_method", "metric_inliers", "metric_residual_px", "metric_reason")
        columns = (*METRIC_TRANSLATION_COLUMNS, *METRIC_ROTATION_COLUMNS, *METRIC_SIGMA_COLUMNS)
        return dict.fromkeys((*names, *columns))
    variances = np.diagonal(lc.metric_covariance_matrix())
    sigmas = [math.sqrt(v) if math.isfinite(v) and v >= 0 else None for v in variances]
    return {
        "metric_method": lc.metric_method,
        **_spread_finite(METRIC_TRANSLATION_COLUMNS, lc.metric_translation),
        **_spread_finite(METRIC_ROTATION_COLUMNS, lc.metric_rotation_xyzw),
        **dict(zip(METRIC_SIGMA_COLUMNS, sigmas, strict=True)),
        "metric_inliers": lc.metric_inliers if lc.metric_method else None,
        "metric_residual_px": _finite(lc.metric_residual_px),
        "metric_reason": lc.metric_reason,
    }


def _spread_finite(names: tuple[str, ...], values: tuple[float, ...]) -> dict[str, Any]:
    finite = len(values) == len(names) and all(math.isfinite(v) for v in values)
    return _spread(names, values if finite else None)


def _spread(names: tuple[str, ...], values: tuple[float, ...] | None) -> dict[str, Any]:
    """A vector field as one column per component; None in each when absent or malformed."""
    if values is None or len(values) != len(names):
        return dict.fromkeys(names)
    return {name: float(value) for name, value in zip(names, values, strict=True)}


def loop_closure_row(log: AnnotatedLog, lc: LoopClosureRecord) -> dict[str, Any]:
    """One pair as a flat dict with exactly COLUMNS as keys (None where the log has no value)."""
    row: dict[str, Any] = {
        "query_index": lc.query.index,
        "query_time_ns": frame_time_ns(log, lc.query),
        "query_log_time_ns": lc.query.log_time_ns,
        "match_index": lc.match.index,
        "match_time_ns": frame_time_ns(log, lc.match),
        "match_log_time_ns": lc.match.log_time_ns,
        "difference": _finite(lc.difference),
        "f": _finite(lc.f),
        "threshold": _finite(lc.threshold),
        "sequence_id": lc.sequence_id,
        "method": lc.method,
        "parameters_hash": lc.parameters_hash,
        **_verification_fields(log, lc),
        **_metric_fields(lc),
    }
    return {column: row[column] for column in COLUMNS}


def loops_summary(log: AnnotatedLog, written: int, include_rejected: bool) -> str:
    rejected, skipped = verification_count(log, REJECTED), verification_count(log, SKIPPED)
    if include_rejected or not (rejected or skipped):
        return f"{written} loop closures"
    left_out = [f"{rejected} rejected by verification"] if rejected else []
    left_out += [f"{skipped} not checked (high frame rate)"] if skipped else []
    return f"{written} loop closures ({', '.join(left_out)} left out)"
