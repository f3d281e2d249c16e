"""Scoring an annotated log without re-running the detector.

`/doseqslam/sequences` keeps every decided sequence with its candidate pairs and its f, so the
`SequenceDecision`s of the run can be rebuilt from the messages and handed to
`metrics.evaluate`, which sweeps the precision-recall curve exactly as for an in-memory run.

With geometric verification the log also says which pairs survived it: the `verified` evaluation
keeps each sequence but replaces its candidates with its pairs whose `verification` is
"accepted", at their refined match. Only sequences with f below the recorded threshold were
verified, so the verified curve ends at that threshold.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, replace

from ..annotations.reader import AnnotatedLog
from ..annotations.records import ACCEPTED, REJECTED, SKIPPED, FrameTimes, SequenceRecord
from ..detector.events import Candidate, SequenceDecision
from ..errors import GroundTruthError, UsageError
from .groundtruth import LoopTruth
from .metrics import Evaluation, evaluate, format_side_by_side


@dataclass(frozen=True)
class LogEvaluation:
    """The raw figures (every candidate, swept over f) and, for a verified run, the verified
    ones (accepted pairs only); `verified` is None when the log has no verification."""

    raw: Evaluation
    verified: Evaluation | None


def _optional(value: float) -> float | None:
    """NaN is the records' "missing" float; None is the decision's."""
    return None if math.isnan(value) else value


def frame_count(log: AnnotatedLog) -> int:
    """Frames the run used: from the frame times, else the last frame any sequence covers."""
    if log.frame_times is not None:
        return len(log.frame_times)
    return max((s.last_index for s in log.sequences), default=-1) + 1


def recorded_threshold(log: AnnotatedLog) -> float:
    """The run's th: from the parameters in the metadata, else from the sequences."""
    threshold = log.parameters.get("threshold")
    if threshold is None and log.sequences:
        threshold = log.sequences[0].threshold
    if threshold is None:
        raise UsageError(f"{log.path}: the log records no detector threshold")
    return float(threshold)


def has_verification(log: AnnotatedLog) -> bool:
    """True when the run verified its pairs geometrically (even if none was a candidate)."""
    return any(s.verification == "on" for s in log.sequences) or any(
        lc.verification in (ACCEPTED, REJECTED, SKIPPED) for lc in log.loop_closures
    )


def _frame_time(frame_times: FrameTimes | None, index: int) -> int:
    """A frame's log time, or 0 when the log predates frame times (evaluation ignores it)."""
    if frame_times is None or not 0 <= index < len(frame_times):
        return 0
    return frame_times.log_time(index)


def decision_from_sequence(
    message: SequenceRecord,
    candidates: Sequence[Candidate] | None = None,
    frame_times: FrameTimes | None = None,
) -> SequenceDecision:
    """The `SequenceDecision` a Sequence message records; `candidates` replaces its own."""
    if candidates is None:
        pairs = zip(
            message.candidate_query_indices,
            message.candidate_match_indices,
            message.candidate_differences,
            strict=True,
        )
        candidates = [
            Candidate(q, m, _frame_time(frame_times, q), _frame_time(frame_times, m), d)
            for q, m, d in pairs
        ]
    return SequenceDecision(
        sequence_id=message.sequence_id,
        first_index=message.first_index,
        last_index=message.last_index,
        first_timestamp_ns=message.first_timestamp_ns,
        last_timestamp_ns=message.last_timestamp_ns,
        database_size=message.database_size,
        best_start=message.best_start if message.has_candidate else None,
        best_velocity=_optional(message.best_velocity),
        best_score=_optional(message.best_score),
        second_score=_optional(message.second_score),
        gamma=message.gamma,
        gamma_previous=_optional(message.gamma_previous),
        gamma_next=_optional(message.gamma_next),
        f=message.f,
        threshold=message.threshold,
        accepted=message.accepted,
        candidates=tuple(candidates),
        method=message.method,
    )


def raw_decisions(log: AnnotatedLog) -> list[SequenceDecision]:
    """Every decision of the run, with every candidate pair, in the order they were made."""
    return [decision_from_sequence(s, frame_times=log.frame_times) for s in log.sequences]


def verified_decisions(log: AnnotatedLog) -> list[SequenceDecision]:
    """Every decision of the run, its candidates replaced by its geometrically accepted pairs
    (at the refined match); sequences that were not verified keep no candidate."""
    accepted: dict[int, list[Candidate]] = defaultdict(list)
    for lc in log.loop_closures:
        if lc.verification == ACCEPTED:
            match = lc.matched.index
            accepted[lc.sequence_id].append(
                Candidate(
                    lc.query.index,
                    match,
                    lc.query.log_time_ns,
                    _frame_time(log.frame_times, match),
                    lc.difference,
                )
            )
    decisions = []
    for message in log.sequences:
        pairs = accepted.get(message.sequence_id, [])
        decision = decision_from_sequence(message, pairs, log.frame_times)
        decisions.append(replace(decision, accepted=bool(pairs) and decision.accepted))
    return decisions


def check_ground_truth_size(log: AnnotatedLog, gt: LoopTruth) -> None:
    """The ground truth must cover exactly the frames the run used."""
    frames = frame_count(log)
    if gt.n_frames != frames:
        raise GroundTruthError(
            f"{gt.source}: ground truth has {gt.n_frames} frames but {log.path} was annotated "
            f"over {frames} frames"
        )


def evaluate_annotated_log(log: AnnotatedLog, gt: LoopTruth, tolerance: int = 0) -> LogEvaluation:
    """Score the run recorded in `log` against `gt` at its recorded threshold.

    Raises:
        GroundTruthError: the ground truth does not have one row per frame of the run.
        UsageError: tolerance is negative, or the log records no threshold.
    """
    check_ground_truth_size(log, gt)
    threshold = recorded_threshold(log)
    times = log.detector_times_ns()
    raw = evaluate(raw_decisions(log), gt, threshold, tolerance, times)
    verified = None
    if has_verification(log):
        verified = evaluate(verified_decisions(log), gt, threshold, tolerance, times)
    return LogEvaluation(raw, verified)


# -- report -------------------------------------------------------------------------------


def format_log_report(result: LogEvaluation) -> str:
    """The evaluation of an annotated log: shared facts, then raw and verified side by side."""
    return format_side_by_side(result.raw, result.verified, "recorded")
