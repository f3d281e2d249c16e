"""What our channels hold, as typed records: the one definition shared by writer and readers.

`LoopClosureRecord` and `SequenceRecord` carry the fields of the definitions in `schemas/`
(`LoopClosure`, `Sequence`), in the same order; `to_message` gives the plain form the encoders
take (times as `{"sec": int, "nsec": int}`, arrays as lists, NaN for a missing float) and
`from_message` reads it back, filling the fields that logs annotated by older versions lack;
a float that is absent or null reads as NaN (the JSON profile omits NaN, older versions wrote
null).
`RunMetadata` is the `doseqslam` metadata record and `FrameTimes` the frame-times attachment.
`annotations.writer` builds the records from the detector's decisions; `annotations.reader`
reads them from a file.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

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
NOT_RECORDED = ""  # the field is absent: the log was annotated before it existed
# Not loop closures: the pairs verification refused or left unchecked.
NOT_REPORTED = frozenset({REJECTED, SKIPPED})

LOOP_CLOSURE = MessageType("LoopClosure", OUR_TOPIC_PREFIX + "loop_closures", 0)
SEQUENCE = MessageType("Sequence", OUR_TOPIC_PREFIX + "sequences", 1)
# The pairs the run decided on but does not report (NOT_REPORTED), as LoopClosure messages on
# their own topic: a consumer of /doseqslam/loop_closures takes every message for a loop.
# Ranked as the loop closures, so that the two topics together keep one order.
CANDIDATE = MessageType("LoopClosure", OUR_TOPIC_PREFIX + "candidates", 0)
# In the order the writer registers their channels (the candidates' after the sequences', so
# that the first two keep their ids).
MESSAGE_TYPES: tuple[MessageType, ...] = (LOOP_CLOSURE, SEQUENCE, CANDIDATE)
# The topics that hold LoopClosure messages: outputs of versions that wrote every pair on
# /doseqslam/loop_closures read back the same.
LOOP_CLOSURE_TOPICS = (LOOP_CLOSURE.topic, CANDIDATE.topic)


@dataclass(frozen=True)
class TimedMessage:
    """One output message: its record and its MCAP log time."""

    record: LoopClosureRecord | SequenceRecord
    log_time_ns: int

    @property
    def type(self) -> MessageType:
        return self.record.message_type

    @property
    def index(self) -> int:
        """Query index (loop closure) or sequence id: the last sort key."""
        record = self.record
        return record.query.index if isinstance(record, LoopClosureRecord) else record.sequence_id

    @property
    def fields(self) -> dict[str, Any]:
        """The message in the encoders' plain form."""
        return self.record.to_message()

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

    def detector_times_ns(self, time_source: str) -> npt.NDArray[np.int64]:
        """The time the detector gave each frame (pipeline.decode.frame_time): the header
        stamp, or the log time for a frame without one or stamped 0, or with `time_source`
        "log"."""
        stamps = self.header_stamps_ns
        if time_source == "log":
            stamps = np.full_like(stamps, NO_STAMP)
        times: npt.NDArray[np.int64] = np.where(stamps > 0, stamps, self.log_times_ns)
        return times.astype(np.int64)

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


def time_ns(value: Mapping[str, Any]) -> int:
    """A {"sec", "nsec"} message time as nanoseconds."""
    return int(value["sec"]) * NANOS_PER_SECOND + int(value["nsec"])


def optional_float(value: Any) -> float:
    """None becomes NaN, the documented "missing" value of every float field (JSON-profile
    logs annotated before the schemas dropped type arrays wrote NaN as null)."""
    return math.nan if value is None else float(value)


def float_field(message: Mapping[str, Any], name: str) -> float:
    """A float field; NaN when absent (the JSON profile omits NaN: it is not JSON)."""
    return optional_float(message.get(name))


def _floats(values: Iterable[Any]) -> tuple[float, ...]:
    floats = tuple(optional_float(v) for v in values)
    if all(math.isnan(v) for v in floats):  # most records have no pose: one shared tuple
        return _ALL_NAN.get(len(floats), floats)
    return floats


def _text(value: Any) -> str:
    """A string field: the few values repeated over every record share one object."""
    return sys.intern(str(value))


def _ints(values: Iterable[Any]) -> tuple[int, ...]:
    return tuple(int(v) for v in values)


@dataclass(frozen=True, slots=True)  # slots: an 8-hour log reads 290,000 records
class FrameRef:
    """One frame as our messages name it: its index, its image message's log time and its
    header stamp (None when the image had no header)."""

    index: int
    log_time_ns: int
    stamp_ns: int | None

    @property
    def time_ns(self) -> int:
        """The time the detector used with header time: the header stamp, or the log time
        when there is none or it is 0 (as `FrameTimes.detector_times_ns`)."""
        return self.stamp_ns if self.stamp_ns else self.log_time_ns

    @classmethod
    def of(cls, index: int, frame_times: FrameTimes) -> FrameRef:
        """Raises ValueError for an index outside the frames."""
        return cls(index, frame_times.log_time(index), frame_times.stamp(index))

    def message_fields(self, prefix: str) -> dict[str, Any]:
        return {
            f"{prefix}_index": self.index,
            f"{prefix}_log_time": time_dict(self.log_time_ns),
            f"{prefix}_stamp": time_dict(0 if self.stamp_ns is None else self.stamp_ns),
            f"{prefix}_has_stamp": self.stamp_ns is not None,
        }

    @classmethod
    def from_message(cls, message: Mapping[str, Any], prefix: str) -> FrameRef:
        stamp = time_ns(message[f"{prefix}_stamp"]) if message[f"{prefix}_has_stamp"] else None
        return cls(int(message[f"{prefix}_index"]), time_ns(message[f"{prefix}_log_time"]), stamp)


NAN4 = (math.nan,) * 4
NAN3 = (math.nan,) * 3
NAN36 = (math.nan,) * 36
_ALL_NAN = {3: NAN3, 4: NAN4, 36: NAN36}
# A loop closure's `metric_method` (schemas/*/LoopClosure; "" none, or not recorded).
DEPTH_PNP, ODOMETRY_PNP, ROTATION_ONLY, NO_METRIC = "depth_pnp", "odometry_pnp", "rotation_only", ""


@dataclass(frozen=True, slots=True)
class LoopClosureRecord:
    """One LoopClosure message (schemas/*/LoopClosure: what each field means): on
    /doseqslam/loop_closures when the run reports it, else on /doseqslam/candidates.

    Fields that verification appended read as "not recorded" (`verification` ==
    NOT_RECORDED, the refined match equal to the match) from logs annotated before them.
    """

    query: FrameRef
    match: FrameRef
    difference: float
    sequence_id: int
    sequence_first_index: int
    sequence_last_index: int
    match_first_index: int
    match_last_index: int
    gamma: float
    gamma_previous: float
    gamma_next: float
    f: float
    threshold: float
    method: str
    parameters_hash: str
    verification: str = NOT_RECORDED
    inliers: int = -1
    tentative_matches: int = -1
    verification_model: str = ""
    rejection_reason: str = ""
    refined_match: FrameRef | None = None  # None: the match (set so by __post_init__)
    has_relative_pose: bool = False
    rotation_xyzw: tuple[float, ...] = NAN4
    rotation_deg: float = math.nan
    translation_direction: tuple[float, ...] = NAN3
    proposal: int = 0
    proposal_match_index: int = -1  # -1: the match's index (set so by __post_init__)
    metric_method: str = NO_METRIC
    metric_translation: tuple[float, ...] = NAN3
    metric_rotation_xyzw: tuple[float, ...] = NAN4
    metric_covariance: tuple[float, ...] = NAN36  # 6x6 row-major; +inf: unconstrained
    metric_inliers: int = -1
    metric_residual_px: float = math.nan
    metric_reason: str = ""

    def __post_init__(self) -> None:
        if self.refined_match is None:
            object.__setattr__(self, "refined_match", self.match)
        if self.proposal_match_index < 0:
            object.__setattr__(self, "proposal_match_index", self.match.index)

    @property
    def reported(self) -> bool:
        """A loop closure of the run: not rejected nor skipped by verification (a log
        annotated without verification, or before it existed, reports every pair)."""
        return self.verification not in NOT_REPORTED

    @property
    def message_type(self) -> MessageType:
        """Where the record is written: its topic follows `reported`."""
        return LOOP_CLOSURE if self.reported else CANDIDATE

    @property
    def matched(self) -> FrameRef:
        """The match a pose graph should use: the refined one."""
        assert self.refined_match is not None  # __post_init__
        return self.refined_match

    @property
    def has_metric_translation(self) -> bool:
        """A metric pose with its translation (depth or odometry PnP), not rotation only."""
        return self.metric_method in (DEPTH_PNP, ODOMETRY_PNP)

    def metric_covariance_matrix(self) -> npt.NDArray[np.float64]:
        """`metric_covariance` as the 6x6 matrix (NaN without a metric pose)."""
        return np.asarray(self.metric_covariance, np.float64).reshape(6, 6)

    def to_message(self) -> dict[str, Any]:
        return {
            **self.query.message_fields("query"),
            **self.match.message_fields("match"),
            "difference": self.difference,
            "sequence_id": self.sequence_id,
            "sequence_first_index": self.sequence_first_index,
            "sequence_last_index": self.sequence_last_index,
            "match_first_index": self.match_first_index,
            "match_last_index": self.match_last_index,
            "gamma": self.gamma,
            "gamma_previous": self.gamma_previous,
            "gamma_next": self.gamma_next,
            "f": self.f,
            "threshold": self.threshold,
            "method": self.method,
            "parameters_hash": self.parameters_hash,
            "verification": self.verification,
            "inliers": self.inliers,
            "tentative_matches": self.tentative_matches,
            "verification_model": self.verification_model,
            "rejection_reason": self.rejection_reason,
            **self.matched.message_fields("refined_match"),
            "has_relative_pose": self.has_relative_pose,
            "rotation_xyzw": list(self.rotation_xyzw),
            "rotation_deg": self.rotation_deg,
            "translation_direction": list(self.translation_direction),
            "proposal": self.proposal,
            "proposal_match_index": self.proposal_match_index,
            "metric_method": self.metric_method,
            "metric_translation": list(self.metric_translation),
            "metric_rotation_xyzw": list(self.metric_rotation_xyzw),
            "metric_covariance": list(self.metric_covariance),
            "metric_inliers": self.metric_inliers,
            "metric_residual_px": self.metric_residual_px,
            "metric_reason": self.metric_reason,
        }

    @classmethod
    def from_message(
        cls, message: Mapping[str, Any], frame_times: FrameTimes | None = None
    ) -> LoopClosureRecord:
        """Raises KeyError, TypeError or ValueError for a message that lacks the fields every
        version wrote or holds values of the wrong kind. `frame_times` places a refined match
        that a log recorded without its times (annotated between two versions)."""
        get = message.get
        return cls(
            query=FrameRef.from_message(message, "query"),
            match=FrameRef.from_message(message, "match"),
            difference=float_field(message, "difference"),
            sequence_id=int(message["sequence_id"]),
            sequence_first_index=int(message["sequence_first_index"]),
            sequence_last_index=int(message["sequence_last_index"]),
            match_first_index=int(message["match_first_index"]),
            match_last_index=int(message["match_last_index"]),
            gamma=float_field(message, "gamma"),
            gamma_previous=float_field(message, "gamma_previous"),
            gamma_next=float_field(message, "gamma_next"),
            f=float_field(message, "f"),
            threshold=float_field(message, "threshold"),
            method=_text(message["method"]),
            parameters_hash=_text(message["parameters_hash"]),
            verification=_text(get("verification", NOT_RECORDED)),
            inliers=int(get("inliers", -1)),
            tentative_matches=int(get("tentative_matches", -1)),
            verification_model=_text(get("verification_model", "")),
            rejection_reason=_text(get("rejection_reason", "")),
            refined_match=_refined_match(message, frame_times),
            has_relative_pose=bool(get("has_relative_pose", False)),
            rotation_xyzw=_floats(get("rotation_xyzw", NAN4)),
            rotation_deg=optional_float(get("rotation_deg", math.nan)),
            translation_direction=_floats(get("translation_direction", NAN3)),
            proposal=int(get("proposal", 0)),
            proposal_match_index=int(get("proposal_match_index", -1)),
            metric_method=_text(get("metric_method", NO_METRIC)),
            metric_translation=_floats(get("metric_translation", NAN3)),
            metric_rotation_xyzw=_floats(get("metric_rotation_xyzw", NAN4)),
            metric_covariance=_floats(get("metric_covariance", NAN36)),
            metric_inliers=int(get("metric_inliers", -1)),
            metric_residual_px=optional_float(get("metric_residual_px", math.nan)),
            metric_reason=_text(get("metric_reason", "")),
        )


def _refined_match(message: Mapping[str, Any], frame_times: FrameTimes | None) -> FrameRef | None:
    if "refined_match_log_time" in message:
        return FrameRef.from_message(message, "refined_match")
    if "refined_match_index" in message and frame_times is not None:
        return FrameRef.of(int(message["refined_match_index"]), frame_times)
    return None  # the match


@dataclass(frozen=True)
class SequenceRecord:
    """One message of /doseqslam/sequences (schemas/*/Sequence: what each field means).

    Times are nanoseconds; floats are NaN when missing. The verification fields read as
    `verification` == NOT_RECORDED and zeros from logs annotated before they existed.
    """

    message_type: ClassVar[MessageType] = SEQUENCE

    sequence_id: int
    first_index: int
    last_index: int
    first_log_time_ns: int
    last_log_time_ns: int
    first_timestamp_ns: int
    last_timestamp_ns: int
    database_size: int
    has_candidate: bool
    best_start: int  # -1 without a candidate
    best_velocity: float
    best_score: float
    second_score: float
    gamma: float
    gamma_previous: float
    gamma_next: float
    f: float
    threshold: float
    accepted: bool
    candidate_query_indices: tuple[int, ...]
    candidate_match_indices: tuple[int, ...]
    candidate_differences: tuple[float, ...]
    method: str
    parameters_hash: str
    verification: str = NOT_RECORDED  # "on", "off", or not recorded
    verified_pairs: int = 0
    accepted_pairs: int = 0
    max_inliers: int = 0

    def to_message(self) -> dict[str, Any]:
        return {
            "sequence_id": self.sequence_id,
            "first_index": self.first_index,
            "last_index": self.last_index,
            "first_log_time": time_dict(self.first_log_time_ns),
            "last_log_time": time_dict(self.last_log_time_ns),
            "first_timestamp": time_dict(self.first_timestamp_ns),
            "last_timestamp": time_dict(self.last_timestamp_ns),
            "database_size": self.database_size,
            "has_candidate": self.has_candidate,
            "best_start": self.best_start,
            "best_velocity": self.best_velocity,
            "best_score": self.best_score,
            "second_score": self.second_score,
            "gamma": self.gamma,
            "gamma_previous": self.gamma_previous,
            "gamma_next": self.gamma_next,
            "f": self.f,
            "threshold": self.threshold,
            "accepted": self.accepted,
            "candidate_query_indices": list(self.candidate_query_indices),
            "candidate_match_indices": list(self.candidate_match_indices),
            "candidate_differences": list(self.candidate_differences),
            "method": self.method,
            "parameters_hash": self.parameters_hash,
            "verification": self.verification,
            "verified_pairs": self.verified_pairs,
            "accepted_pairs": self.accepted_pairs,
            "max_inliers": self.max_inliers,
        }

    @classmethod
    def from_message(cls, message: Mapping[str, Any]) -> SequenceRecord:
        """Raises KeyError, TypeError or ValueError for a message that lacks the fields every
        version wrote or holds values of the wrong kind."""
        get = message.get
        return cls(
            sequence_id=int(message["sequence_id"]),
            first_index=int(message["first_index"]),
            last_index=int(message["last_index"]),
            first_log_time_ns=time_ns(message["first_log_time"]),
            last_log_time_ns=time_ns(message["last_log_time"]),
            first_timestamp_ns=time_ns(message["first_timestamp"]),
            last_timestamp_ns=time_ns(message["last_timestamp"]),
            database_size=int(message["database_size"]),
            has_candidate=bool(message["has_candidate"]),
            best_start=int(message["best_start"]),
            best_velocity=float_field(message, "best_velocity"),
            best_score=float_field(message, "best_score"),
            second_score=float_field(message, "second_score"),
            gamma=float_field(message, "gamma"),
            gamma_previous=float_field(message, "gamma_previous"),
            gamma_next=float_field(message, "gamma_next"),
            f=float_field(message, "f"),
            threshold=float_field(message, "threshold"),
            accepted=bool(message["accepted"]),
            candidate_query_indices=_ints(message["candidate_query_indices"]),
            candidate_match_indices=_ints(message["candidate_match_indices"]),
            candidate_differences=_candidate_differences(message),
            method=str(message["method"]),
            parameters_hash=str(message["parameters_hash"]),
            verification=str(get("verification", NOT_RECORDED)),
            verified_pairs=int(get("verified_pairs", 0)),
            accepted_pairs=int(get("accepted_pairs", 0)),
            max_inliers=int(get("max_inliers", 0)),
        )


def _candidate_differences(message: Mapping[str, Any]) -> tuple[float, ...]:
    """NaN for every candidate when the JSON profile omitted the array (it held a NaN)."""
    if "candidate_differences" in message:
        return _floats(message["candidate_differences"])
    return (math.nan,) * len(message["candidate_query_indices"])


def _optional_int(text: str) -> int | None:
    return int(text) if text else None


@dataclass(frozen=True)
class RunMetadata:
    """The `doseqslam` metadata record: what the run was given and what it did, nothing that
    varies between runs. Entries are strings in the file; JSON-valued ones are kept as their
    text (so a record reads back and writes out the same bytes) with parsed properties.

    The verification entries are written only when `verification` is "on". `recorded` is the
    record as read, every key included (also those of other versions), for diffs and reports;
    it is empty for a record built by the pipeline.
    """

    tool_version: str
    method: str
    parameters_json: str  # "parameters": canonical JSON of every detector parameter
    parameters_hash: str
    feature_detector: str
    source_file: str
    source_sha256: str
    image_topic: str
    time_source: str  # "header" or "log"
    start_ns: int | None
    end_ns: int | None
    on_error: str
    image_messages: int
    frames_used: int
    frames_skipped: int
    frames_skipped_by_reason_json: str
    first_skipped_by_reason_json: str
    log_time_fallbacks: int
    clock_jumps: int
    first_clock_jump: str
    recovered_json: str  # "" unless --recover salvaged the input
    verification: str  # "on" or "off"
    sequences: int
    loop_closures: int  # reported: the accepted pairs with verification on
    verification_parameters_json: str = ""
    verification_hash: str = ""
    intrinsics_json: str = ""  # [fx, fy, cx, cy], "" without intrinsics
    intrinsics_source: str = ""
    verified_pairs: int = 0
    accepted_pairs: int = 0
    # What the log's index or statistics promised for the topic ("" / None: no such record,
    # or a time range was asked for), and messages of undeclared topics (never readable).
    image_messages_promised: int | None = None
    image_messages_promised_by: str = ""
    unattributed_messages: int = 0
    # pipeline.feature_health's measurements and warnings, only when the frames were too poor
    # in features to segment or verify ("": a healthy run, or a version before it existed).
    feature_poor_json: str = ""
    # The pose topic the run took as the robot's odometry (sources.poses.run_pose_topic), which
    # export and optimize default to ("": none, or a version before it was recorded).
    odometry_topic: str = ""
    tool: str = "doseqslam-logs"
    recorded: Mapping[str, str] = field(default_factory=dict, compare=False, repr=False)

    # entry key -> field name, in the order the entries are written
    _KEYS: ClassVar[tuple[tuple[str, str], ...]] = (
        ("tool", "tool"),
        ("tool_version", "tool_version"),
        ("method", "method"),
        ("parameters", "parameters_json"),
        ("parameters_hash", "parameters_hash"),
        ("feature_detector", "feature_detector"),
        ("source_file", "source_file"),
        ("source_sha256", "source_sha256"),
        ("image_topic", "image_topic"),
        ("odometry_topic", "odometry_topic"),
        ("time_source", "time_source"),
        ("start_ns", "start_ns"),
        ("end_ns", "end_ns"),
        ("on_error", "on_error"),
        ("image_messages", "image_messages"),
        ("image_messages_promised", "image_messages_promised"),
        ("image_messages_promised_by", "image_messages_promised_by"),
        ("unattributed_messages", "unattributed_messages"),
        ("frames_used", "frames_used"),
        ("frames_skipped", "frames_skipped"),
        ("frames_skipped_by_reason", "frames_skipped_by_reason_json"),
        ("first_skipped_by_reason", "first_skipped_by_reason_json"),
        ("log_time_fallbacks", "log_time_fallbacks"),
        ("clock_jumps", "clock_jumps"),
        ("first_clock_jump", "first_clock_jump"),
        ("recovered", "recovered_json"),
        ("verification", "verification"),
        ("sequences", "sequences"),
        ("loop_closures", "loop_closures"),
    )
    _VERIFICATION_KEYS: ClassVar[tuple[tuple[str, str], ...]] = (
        ("verification_parameters", "verification_parameters_json"),
        ("verification_hash", "verification_hash"),
        ("intrinsics", "intrinsics_json"),
        ("intrinsics_source", "intrinsics_source"),
        ("verified_pairs", "verified_pairs"),
        ("accepted_pairs", "accepted_pairs"),
    )
    # Written only when not empty, so that a healthy run's record keeps its bytes.
    _WHEN_SET_KEYS: ClassVar[tuple[tuple[str, str], ...]] = (("feature_poor", "feature_poor_json"),)
    _OPTIONAL_INTS: ClassVar[frozenset[str]] = frozenset(
        {"start_ns", "end_ns", "image_messages_promised"}
    )

    @property
    def parameters(self) -> dict[str, Any]:
        """The detector parameters as recorded ({} when absent)."""
        return dict(json.loads(self.parameters_json)) if self.parameters_json else {}

    @property
    def feature_poor(self) -> dict[str, Any]:
        """The feature-poor warning's figures ({} when the run was not feature-poor)."""
        return dict(json.loads(self.feature_poor_json)) if self.feature_poor_json else {}

    @property
    def intrinsics(self) -> tuple[float, ...] | None:
        return _floats(json.loads(self.intrinsics_json)) if self.intrinsics_json else None

    def to_entries(self) -> dict[str, str]:
        """The record as written: strings, in a fixed order."""
        keys = self._KEYS + (self._VERIFICATION_KEYS if self.verification == "on" else ())
        keys += tuple((key, name) for key, name in self._WHEN_SET_KEYS if getattr(self, name))
        return {key: self._text(name) for key, name in keys}

    def _text(self, name: str) -> str:
        value = getattr(self, name)
        return "" if value is None else str(value)

    @classmethod
    def from_entries(cls, entries: Mapping[str, str]) -> RunMetadata:
        """A record as read; entries that a version did not write take their defaults
        ("", 0, None; verification "off"). Raises ValueError for a count that is not a number."""
        values: dict[str, Any] = {}
        for key, name in cls._KEYS + cls._VERIFICATION_KEYS + cls._WHEN_SET_KEYS:
            text = entries.get(key, "")
            kind = cls.__dataclass_fields__[name].type
            if name in cls._OPTIONAL_INTS:
                values[name] = _optional_int(text)
            elif kind == "int":
                values[name] = int(text) if text else 0
            else:
                values[name] = text
        values["verification"] = values["verification"] or OFF
        values["tool"] = values["tool"] or "doseqslam-logs"
        return cls(**values, recorded=dict(entries))
