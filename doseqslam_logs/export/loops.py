"""Loop closures of an annotated log as flat rows, and the time the detector gave each frame.

Rows have the same columns for every log: fields a log lacks (logs annotated without geometric
verification, or before it existed) are None, so a csv header never depends on the input.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from ..annotations.reader import AnnotatedLog
from ..annotations.records import NANOS_PER_SECOND, REJECTED, SKIPPED
from ..errors import SourceError

ROTATION_COLUMNS = ("rotation_qx", "rotation_qy", "rotation_qz", "rotation_qw")
DIRECTION_COLUMNS = ("translation_dx", "translation_dy", "translation_dz")

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
)


def time_ns(value: Mapping[str, Any]) -> int:
    """A {"sec", "nsec"} time as nanoseconds."""
    return int(value["sec"]) * NANOS_PER_SECOND + int(value["nsec"])


def uses_header_stamps(log: AnnotatedLog) -> bool:
    """Whether the detector ran on header stamps (the default) rather than log times."""
    return log.metadata.get("time_source", "header") != "log"


def frame_time_ns(log: AnnotatedLog, loop_closure: Mapping[str, Any], prefix: str) -> int:
    """The detector's time of the `prefix` ("query", "match", "refined_match") frame."""
    if uses_header_stamps(log) and loop_closure.get(f"{prefix}_has_stamp", False):
        return time_ns(loop_closure[f"{prefix}_stamp"])
    return time_ns(loop_closure[f"{prefix}_log_time"])


def frame_times_ns(log: AnnotatedLog) -> npt.NDArray[np.int64]:
    """The detector's time of every frame, by frame index.

    Raises SourceError for logs annotated before frame times were recorded.
    """
    if log.frame_times is None:
        raise SourceError(
            f"{log.path}: holds no frame times (annotated by an older version); annotate it again"
        )
    stamps, log_times = log.frame_times.header_stamps_ns, log.frame_times.log_times_ns
    if not uses_header_stamps(log):
        return np.array(log_times, dtype=np.int64)
    return np.where(stamps >= 0, stamps, log_times).astype(np.int64)


def matched_index(loop_closure: Mapping[str, Any]) -> int:
    """The matched frame of a pair: the refined match when verification recorded one."""
    return int(loop_closure.get("refined_match_index", loop_closure["match_index"]))


def selected_loop_closures(log: AnnotatedLog, include_rejected: bool) -> list[dict[str, Any]]:
    """The reported loop closures, or every pair on the channel with `include_rejected`."""
    return list(log.loop_closures if include_rejected else log.reported_loop_closures)


def verification_count(log: AnnotatedLog, verdict: str) -> int:
    """Loop closures on the channel whose `verification` is `verdict`."""
    return sum(1 for lc in log.loop_closures if lc.get("verification") == verdict)


def _finite(value: Any) -> float | None:
    number = float(value)
    return number if math.isfinite(number) else None


def _verification_fields(log: AnnotatedLog, lc: Mapping[str, Any]) -> dict[str, Any]:
    fields: dict[str, Any] = {
        "verification": lc.get("verification"),
        "inliers": lc.get("inliers"),
        "refined_match_index": lc.get("refined_match_index"),
        "refined_match_time_ns": None,
        "refined_match_log_time_ns": None,
    }
    if "refined_match_log_time" in lc:
        fields["refined_match_time_ns"] = frame_time_ns(log, lc, "refined_match")
        fields["refined_match_log_time_ns"] = time_ns(lc["refined_match_log_time"])
    has_pose = bool(lc.get("has_relative_pose", False))
    rotation = lc.get("rotation_xyzw") if has_pose else None
    direction = lc.get("translation_direction") if has_pose else None
    fields.update(_spread(ROTATION_COLUMNS, rotation))
    fields.update(_spread(DIRECTION_COLUMNS, direction))
    return fields


def _spread(names: tuple[str, ...], values: Any) -> dict[str, Any]:
    """A vector field as one column per component; None in each when absent or malformed."""
    if values is None or len(values) != len(names):
        return dict.fromkeys(names)
    return {name: float(value) for name, value in zip(names, values, strict=True)}


def loop_closure_row(log: AnnotatedLog, lc: Mapping[str, Any]) -> dict[str, Any]:
    """One pair as a flat dict with exactly COLUMNS as keys (None where the log has no value)."""
    row: dict[str, Any] = {
        "query_index": int(lc["query_index"]),
        "query_time_ns": frame_time_ns(log, lc, "query"),
        "query_log_time_ns": time_ns(lc["query_log_time"]),
        "match_index": int(lc["match_index"]),
        "match_time_ns": frame_time_ns(log, lc, "match"),
        "match_log_time_ns": time_ns(lc["match_log_time"]),
        "difference": _finite(lc["difference"]),
        "f": _finite(lc["f"]),
        "threshold": _finite(lc["threshold"]),
        "sequence_id": int(lc["sequence_id"]),
        "method": lc.get("method"),
        "parameters_hash": lc.get("parameters_hash"),
        **_verification_fields(log, lc),
    }
    return {column: row[column] for column in COLUMNS}


def loops_summary(log: AnnotatedLog, written: int, include_rejected: bool) -> str:
    rejected, skipped = verification_count(log, REJECTED), verification_count(log, SKIPPED)
    if include_rejected or not (rejected or skipped):
        return f"{written} loop closures"
    left_out = [f"{rejected} rejected by verification"] if rejected else []
    left_out += [f"{skipped} not checked (high frame rate)"] if skipped else []
    return f"{written} loop closures ({', '.join(left_out)} left out)"
