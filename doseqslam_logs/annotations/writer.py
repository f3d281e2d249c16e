"""The detector's decisions (and their verification) as our output records, one per message.

One `LoopClosureRecord` per pair of an accepted decision, at the query's log time, and one
`SequenceRecord` per decision, at the log time of its last frame. The MCAP sink encodes them
(`sinks.mcap_writer`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from ..detector.events import Candidate, SequenceDecision
from ..verification.geometry import Verdict
from ..verification.metric_pose import MetricPose
from ..verification.stage import CONTINUED, PairCheck, VerifiedDecision
from .records import (
    ACCEPTED,
    NAN3,
    NAN4,
    NO_METRIC,
    OFF,
    REJECTED,
    SKIPPED,
    FrameRef,
    FrameTimes,
    LoopClosureRecord,
    SequenceRecord,
    TimedMessage,
    optional_float,
)

# sequence id -> its verification; None for a run without verification (--no-verify).
Verifications = Mapping[int, VerifiedDecision] | None
# (sequence id, pair number in its decision) -> the accepted pair's metric pose, or why it has
# none; None for a run without them (--no-verify).
MetricPoses = Mapping[tuple[int, int], MetricPose | str] | None

_MODEL_NAMES = {"F": "fundamental", "E": "essential"}


def loop_closure_messages(
    decisions: Iterable[SequenceDecision],
    frame_times: FrameTimes,
    method: str,
    parameters_hash: str,
    verifications: Verifications = None,
    metric: MetricPoses = None,
) -> list[TimedMessage]:
    """One `LoopClosure` message per pair of an accepted decision, with the query's log time.

    With `verifications`, each pair carries its check (rejected pairs included, marked so);
    with `metric`, each accepted pair its metric pose (or why it has none).

    Raises ValueError when a decision names a frame outside `frame_times` or another method,
    or a decision has no verification in `verifications`.
    """
    messages: list[TimedMessage] = []
    for decision in decisions:
        _check_method(decision, method)
        pairs = decision.loop_closures
        if not pairs:
            continue
        checks = _checks(decision, verifications)
        match_bounds = (min(p.match_index for p in pairs), max(p.match_index for p in pairs))
        for z, (pair, check) in enumerate(zip(pairs, checks, strict=True)):
            record = LoopClosureRecord(
                **_pair_values(decision, pair, match_bounds, frame_times, parameters_hash),
                **_verification_values(pair, check, frame_times),
                **_proposal_values(decision, z, check),
                **_metric_values(None if metric is None else metric.get((decision.sequence_id, z))),
            )
            messages.append(TimedMessage(record, record.query.log_time_ns))
    return messages


def _checks(decision: SequenceDecision, verifications: Verifications) -> Sequence[PairCheck | None]:
    if verifications is None:
        return [None] * len(decision.loop_closures)
    verified = verifications.get(decision.sequence_id)
    if verified is None or len(verified.checks) != len(decision.loop_closures):
        raise ValueError(f"sequence {decision.sequence_id} has no verification of its pairs")
    return verified.checks


def _pair_values(
    decision: SequenceDecision,
    pair: Candidate,
    match_bounds: tuple[int, int],
    frame_times: FrameTimes,
    parameters_hash: str,
) -> dict[str, Any]:
    return {
        "query": FrameRef.of(pair.query_index, frame_times),
        "match": FrameRef.of(pair.match_index, frame_times),
        "difference": float(pair.difference),
        "sequence_id": decision.sequence_id,
        "sequence_first_index": decision.first_index,
        "sequence_last_index": decision.last_index,
        "match_first_index": match_bounds[0],
        "match_last_index": match_bounds[1],
        **_decision_values(decision),
        "method": decision.method,
        "parameters_hash": parameters_hash,
    }


def _verification_values(
    pair: Candidate, check: PairCheck | None, frame_times: FrameTimes
) -> dict[str, Any]:
    refined = pair.match_index if check is None else check.refined_match_index
    frame = FrameRef.of(refined, frame_times)
    if check is None:
        return {"verification": OFF, "refined_match": frame}
    verdict = check.verdict
    if check.skipped:  # not checked: no counts to record
        status, inliers, tentative = SKIPPED, -1, -1
    else:
        status = ACCEPTED if verdict.accepted else REJECTED
        inliers, tentative = verdict.inliers, verdict.matches_tested
    return {
        "verification": status,
        "inliers": inliers,
        "tentative_matches": tentative,
        "verification_model": _MODEL_NAMES[verdict.model],
        "rejection_reason": "" if verdict.accepted else verdict.reason,
        "refined_match": frame,
        **_pose_values(verdict),
    }


def _pose_values(verdict: Verdict) -> dict[str, Any]:
    """The relative pose of an accepted pair only: a pair rejected after its fit (rotation
    limit, bracketing) says why in its reason, not with a pose a consumer might use."""
    if not verdict.accepted:
        return {}
    rotation, direction = verdict.rotation_xyzw, verdict.translation_direction
    return {
        "has_relative_pose": rotation is not None and direction is not None,
        "rotation_xyzw": tuple(float(v) for v in rotation) if rotation else NAN4,
        "rotation_deg": optional_float(verdict.rotation_deg),
        "translation_direction": tuple(float(v) for v in direction) if direction else NAN3,
    }


def _proposal_values(decision: SequenceDecision, z: int, check: PairCheck | None) -> dict[str, Any]:
    """Which trajectory's match the check accepted: 0 the detector's, k its k-th next best,
    CONTINUED the previous sequence's place (`verification.stage.Hint`)."""
    proposal = 0 if check is None or not check.accepted else check.proposal
    match = decision.loop_closures[z].match_index
    if check is not None and proposal == CONTINUED:
        match = check.continued_match
    elif proposal:
        match = decision.alternatives[proposal - 1].match_indices[z]
    return {"proposal": proposal, "proposal_match_index": match}


def _metric_values(metric: MetricPose | str | None) -> dict[str, Any]:
    """The metric fields of a pair: its pose, or "none" and why (a string); nothing (the
    "not recorded" values) for a pair without an entry (not accepted, or --no-verify)."""
    if metric is None:
        return {}
    if isinstance(metric, str):
        return {"metric_method": NO_METRIC, "metric_reason": metric}
    translation = metric.translation
    return {
        "metric_method": metric.method,
        "metric_translation": NAN3 if translation is None else tuple(float(v) for v in translation),
        "metric_rotation_xyzw": tuple(float(v) for v in metric.rotation_xyzw),
        "metric_covariance": tuple(float(v) for v in metric.covariance.reshape(36)),
        "metric_inliers": int(metric.inliers),
        "metric_residual_px": float(metric.rms_px),
        "metric_reason": metric.reason,
    }


def sequence_messages(
    decisions: Iterable[SequenceDecision],
    frame_times: FrameTimes,
    method: str,
    parameters_hash: str,
    verifications: Verifications = None,
) -> list[TimedMessage]:
    """One `Sequence` message per decision, with the log time of the sequence's last frame.

    Raises ValueError when a decision names a frame outside `frame_times` or another method.
    """
    messages: list[TimedMessage] = []
    for decision in decisions:
        _check_method(decision, method)
        record = SequenceRecord(
            **_sequence_values(decision, frame_times, parameters_hash),
            **_sequence_verification(decision, verifications),
        )
        messages.append(TimedMessage(record, record.last_log_time_ns))
    return messages


def _sequence_verification(
    decision: SequenceDecision, verifications: Verifications
) -> dict[str, Any]:
    if verifications is None:
        return {"verification": OFF}
    verified = verifications.get(decision.sequence_id)
    checks = () if verified is None else verified.checks
    return {
        "verification": "on",
        "verified_pairs": len(checks),
        "accepted_pairs": sum(check.accepted for check in checks),
        "max_inliers": max((check.verdict.inliers for check in checks), default=0),
    }


def _check_method(decision: SequenceDecision, method: str) -> None:
    if decision.method != method:
        raise ValueError(
            f"sequence {decision.sequence_id} was decided by {decision.method!r}, not {method!r}"
        )


def _decision_values(decision: SequenceDecision) -> dict[str, Any]:
    return {
        "gamma": float(decision.gamma),
        "gamma_previous": optional_float(decision.gamma_previous),
        "gamma_next": optional_float(decision.gamma_next),
        "f": float(decision.f),
        "threshold": float(decision.threshold),
    }


def _sequence_values(
    decision: SequenceDecision, frame_times: FrameTimes, parameters_hash: str
) -> dict[str, Any]:
    candidates: Sequence[Candidate] = decision.candidates
    return {
        "sequence_id": decision.sequence_id,
        "first_index": decision.first_index,
        "last_index": decision.last_index,
        "first_log_time_ns": frame_times.log_time(decision.first_index),
        "last_log_time_ns": frame_times.log_time(decision.last_index),
        "first_timestamp_ns": decision.first_timestamp_ns,
        "last_timestamp_ns": decision.last_timestamp_ns,
        "database_size": decision.database_size,
        "has_candidate": decision.best_start is not None,
        "best_start": decision.best_start if decision.best_start is not None else -1,
        "best_velocity": optional_float(decision.best_velocity),
        "best_score": optional_float(decision.best_score),
        "second_score": optional_float(decision.second_score),
        **_decision_values(decision),
        "accepted": decision.accepted,
        "candidate_query_indices": tuple(c.query_index for c in candidates),
        "candidate_match_indices": tuple(c.match_index for c in candidates),
        "candidate_differences": tuple(float(c.difference) for c in candidates),
        "method": decision.method,
        "parameters_hash": parameters_hash,
    }
