"""The detector's decisions as plain message dicts, one per output message.

The dicts carry exactly the fields of the definitions in `schemas/` (`LoopClosure`, `Sequence`),
in the same order, with JSON-friendly values: ints, floats (NaN when missing), bools, strings,
lists, and times as `{"sec": int, "nsec": int}`. The encoders turn them into CDR, ROS 1 or JSON.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ..detector.events import Candidate, SequenceDecision
from ..verification.geometry import Verdict
from ..verification.stage import PairCheck, VerifiedDecision

# sequence id -> its verification; None for a run without verification (--no-verify).
Verifications = Mapping[int, VerifiedDecision] | None

NO_STAMP = -1  # header stamp of a frame whose image message has no header
NANOS_PER_SECOND = 1_000_000_000
OUR_TOPIC_PREFIX = "/doseqslam/"
METADATA_NAME = "doseqslam"  # the metadata record we write (and replace when re-annotating)
# Every frame's log time and header stamp, by frame index (FrameTimes.to_json), so that readers
# of the output can place any frame index in time (ground truth from poses, plots, export).
FRAME_TIMES_ATTACHMENT = "doseqslam/frame_times"
FRAME_TIMES_MEDIA_TYPE = "application/json"


@dataclass(frozen=True)
class MessageType:
    """One of our output message types: its definition files and its topic."""

    name: str  # file stem in schemas/ros1, schemas/ros2 and schemas/json
    topic: str
    rank: int  # order among our messages that share a log time


# A loop closure's `verification`: "accepted", "rejected" (the check refused it), "skipped"
# (left unchecked at a high frame rate: the query stride, or a given-up sequence) or "off"
# (no verification).
ACCEPTED, REJECTED, SKIPPED, OFF = "accepted", "rejected", "skipped", "off"

LOOP_CLOSURE = MessageType("LoopClosure", OUR_TOPIC_PREFIX + "loop_closures", 0)
SEQUENCE = MessageType("Sequence", OUR_TOPIC_PREFIX + "sequences", 1)
MESSAGE_TYPES: tuple[MessageType, ...] = (LOOP_CLOSURE, SEQUENCE)


@dataclass(frozen=True)
class TimedMessage:
    """One output message: its type, its MCAP log time and its fields."""

    type: MessageType
    log_time_ns: int
    index: int  # query index (loop closure) or sequence id: the last sort key
    fields: dict[str, Any]

    @property
    def sort_key(self) -> tuple[int, int, int]:
        return (self.log_time_ns, self.type.rank, self.index)


class FrameTimes:
    """Log time and header stamp of every frame the detector used, by frame index.

    Two int64 arrays, so memory stays linear in the number of frames; a header stamp of
    `NO_STAMP` (-1) means the image message had no header.
    """

    def __init__(self, log_times_ns: npt.ArrayLike, header_stamps_ns: npt.ArrayLike) -> None:
        """Raises ValueError when the arrays are not 1-D, differ in length or hold bad times."""
        self.log_times_ns: npt.NDArray[np.int64] = np.asarray(log_times_ns, dtype=np.int64)
        self.header_stamps_ns: npt.NDArray[np.int64] = np.asarray(header_stamps_ns, dtype=np.int64)
        if self.log_times_ns.ndim != 1 or self.log_times_ns.shape != self.header_stamps_ns.shape:
            raise ValueError("log times and header stamps must be 1-D arrays of equal length")
        if (self.log_times_ns < 0).any() or (self.header_stamps_ns < NO_STAMP).any():
            raise ValueError("log times must be >= 0 and header stamps >= -1 (none)")

    @classmethod
    def from_pairs(cls, pairs: Iterable[tuple[int, int | None]]) -> FrameTimes:
        """From (log time, header stamp or None) per frame, in frame order."""
        log_times: list[int] = []
        stamps: list[int] = []
        for log_time, stamp in pairs:
            log_times.append(log_time)
            stamps.append(NO_STAMP if stamp is None else stamp)
        return cls(log_times, stamps)

    def __len__(self) -> int:
        return int(self.log_times_ns.shape[0])

    def to_json(self) -> bytes:
        """{"log_time_ns": [...], "header_stamp_ns": [...]} (-1: no header), compact."""
        document = {
            "log_time_ns": self.log_times_ns.tolist(),
            "header_stamp_ns": self.header_stamps_ns.tolist(),
        }
        return json.dumps(document, separators=(",", ":")).encode()

    @classmethod
    def from_json(cls, data: bytes) -> FrameTimes:
        """Raises ValueError for text that `to_json` did not write."""
        try:
            document = json.loads(data)
            return cls(document["log_time_ns"], document["header_stamp_ns"])
        except (TypeError, KeyError, json.JSONDecodeError) as exc:
            raise ValueError(f"not a frame-times document ({exc})") from exc

    def log_time(self, index: int) -> int:
        """Raises ValueError for an index outside the frames."""
        return int(self.log_times_ns[self._check(index)])

    def stamp(self, index: int) -> int | None:
        """The header stamp, or None when the frame's image had none."""
        stamp = int(self.header_stamps_ns[self._check(index)])
        return None if stamp == NO_STAMP else stamp

    def _check(self, index: int) -> int:
        if not 0 <= index < len(self):
            raise ValueError(f"frame index {index} outside the {len(self)} frames with times")
        return index


def time_dict(time_ns: int) -> dict[str, int]:
    """A nanosecond time as {"sec", "nsec"}: JSON numbers stay far below 2^53."""
    sec, nsec = divmod(time_ns, NANOS_PER_SECOND)
    return {"sec": sec, "nsec": nsec}


def optional_float(value: float | None) -> float:
    """None becomes NaN, the documented "missing" value of every float field."""
    return math.nan if value is None else float(value)


def loop_closure_messages(
    decisions: Iterable[SequenceDecision],
    frame_times: FrameTimes,
    method: str,
    parameters_hash: str,
    verifications: Verifications = None,
) -> list[TimedMessage]:
    """One `LoopClosure` message per pair of an accepted decision, with the query's log time.

    With `verifications`, each pair carries its check (rejected pairs included, marked so).

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
            fields = {
                **_loop_closure_fields(
                    decision, pair, match_bounds, frame_times, method, parameters_hash
                ),
                **_verification_fields(pair, check, frame_times),
                **_proposal_fields(decision, z, check),
            }
            log_time = frame_times.log_time(pair.query_index)
            messages.append(TimedMessage(LOOP_CLOSURE, log_time, pair.query_index, fields))
    return messages


def _checks(decision: SequenceDecision, verifications: Verifications) -> Sequence[PairCheck | None]:
    if verifications is None:
        return [None] * len(decision.loop_closures)
    verified = verifications.get(decision.sequence_id)
    if verified is None or len(verified.checks) != len(decision.loop_closures):
        raise ValueError(f"sequence {decision.sequence_id} has no verification of its pairs")
    return verified.checks


_MODEL_NAMES = {"F": "fundamental", "E": "essential"}


def _verification_fields(
    pair: Candidate, check: PairCheck | None, frame_times: FrameTimes
) -> dict[str, Any]:
    refined = pair.match_index if check is None else check.refined_match_index
    frame = _frame_fields("refined_match", refined, frame_times)
    if check is None:
        return {
            "verification": OFF,
            "inliers": -1,
            "tentative_matches": -1,
            "verification_model": "",
            "rejection_reason": "",
            **frame,
            **_pose_fields(None, None, None),
        }
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
        **frame,
        **_pose_fields(*_accepted_pose(verdict)),
    }


def _accepted_pose(verdict: Verdict) -> tuple[Any, Any, Any]:
    """The relative pose of an accepted pair only: a pair rejected after its fit (rotation
    limit, bracketing) says why in its reason, not with a pose a consumer might use."""
    if not verdict.accepted:
        return None, None, None
    return verdict.rotation_xyzw, verdict.rotation_deg, verdict.translation_direction


def _proposal_fields(decision: SequenceDecision, z: int, check: PairCheck | None) -> dict[str, Any]:
    """Which trajectory's match the check accepted: 0 the detector's, k its k-th next best."""
    proposal = 0 if check is None or not check.accepted else check.proposal
    match = decision.loop_closures[z].match_index
    if proposal:
        match = decision.alternatives[proposal - 1].match_indices[z]
    return {"proposal": proposal, "proposal_match_index": match}


def _pose_fields(
    rotation: Sequence[float] | None, degrees: float | None, direction: Sequence[float] | None
) -> dict[str, Any]:
    known = rotation is not None and direction is not None
    return {
        "has_relative_pose": known,
        "rotation_xyzw": [float(v) for v in rotation] if rotation else [math.nan] * 4,
        "rotation_deg": optional_float(degrees),
        "translation_direction": [float(v) for v in direction] if direction else [math.nan] * 3,
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
        fields = {
            **_sequence_fields(decision, frame_times, method, parameters_hash),
            **_sequence_verification(decision, verifications),
        }
        log_time = frame_times.log_time(decision.last_index)
        messages.append(TimedMessage(SEQUENCE, log_time, decision.sequence_id, fields))
    return messages


def _sequence_verification(
    decision: SequenceDecision, verifications: Verifications
) -> dict[str, Any]:
    if verifications is None:
        return {"verification": OFF, "verified_pairs": 0, "accepted_pairs": 0, "max_inliers": 0}
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


def _frame_fields(prefix: str, index: int, frame_times: FrameTimes) -> dict[str, Any]:
    stamp = frame_times.stamp(index)
    return {
        f"{prefix}_index": index,
        f"{prefix}_log_time": time_dict(frame_times.log_time(index)),
        f"{prefix}_stamp": time_dict(0 if stamp is None else stamp),
        f"{prefix}_has_stamp": stamp is not None,
    }


def _decision_values(decision: SequenceDecision) -> dict[str, Any]:
    return {
        "gamma": float(decision.gamma),
        "gamma_previous": optional_float(decision.gamma_previous),
        "gamma_next": optional_float(decision.gamma_next),
        "f": float(decision.f),
        "threshold": float(decision.threshold),
    }


def _loop_closure_fields(
    decision: SequenceDecision,
    pair: Candidate,
    match_bounds: tuple[int, int],
    frame_times: FrameTimes,
    method: str,
    parameters_hash: str,
) -> dict[str, Any]:
    return {
        **_frame_fields("query", pair.query_index, frame_times),
        **_frame_fields("match", pair.match_index, frame_times),
        "difference": float(pair.difference),
        "sequence_id": decision.sequence_id,
        "sequence_first_index": decision.first_index,
        "sequence_last_index": decision.last_index,
        "match_first_index": match_bounds[0],
        "match_last_index": match_bounds[1],
        **_decision_values(decision),
        "method": method,
        "parameters_hash": parameters_hash,
    }


def _sequence_fields(
    decision: SequenceDecision, frame_times: FrameTimes, method: str, parameters_hash: str
) -> dict[str, Any]:
    candidates: Sequence[Candidate] = decision.candidates
    has_candidate = decision.best_start is not None
    return {
        "sequence_id": decision.sequence_id,
        "first_index": decision.first_index,
        "last_index": decision.last_index,
        "first_log_time": time_dict(frame_times.log_time(decision.first_index)),
        "last_log_time": time_dict(frame_times.log_time(decision.last_index)),
        "first_timestamp": time_dict(decision.first_timestamp_ns),
        "last_timestamp": time_dict(decision.last_timestamp_ns),
        "database_size": decision.database_size,
        "has_candidate": has_candidate,
        "best_start": decision.best_start if decision.best_start is not None else -1,
        "best_velocity": optional_float(decision.best_velocity),
        "best_score": optional_float(decision.best_score),
        "second_score": optional_float(decision.second_score),
        **_decision_values(decision),
        "accepted": decision.accepted,
        "candidate_query_indices": [c.query_index for c in candidates],
        "candidate_match_indices": [c.match_index for c in candidates],
        "candidate_differences": [float(c.difference) for c in candidates],
        "method": method,
        "parameters_hash": parameters_hash,
    }
