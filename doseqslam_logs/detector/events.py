"""What the detector decides: one `SequenceDecision` per sequence, accepted or not."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Candidate:
    """One query frame and the database frame that image-to-image association gave it."""

    query_index: int  # frame index in push order (0-based)
    match_index: int
    query_timestamp_ns: int
    match_timestamp_ns: int
    difference: float  # enhanced difference D^[query, match] (lower is more similar)


@dataclass(frozen=True)
class Alternative:
    """A next-best trajectory of a sequence: another start j, with the match it gives each
    query frame (what the verification stage tries when the detector's own match fails)."""

    start: int
    velocity: float
    score: float  # S_do[start], >= the decision's best_score
    match_indices: tuple[int, ...]  # one per candidate, in candidate order


@dataclass(frozen=True)
class SequenceDecision:
    """The decision on one sequence (DOSeqSLAM) or one query frame's trajectory (SeqSLAM).

    Kept for every sequence, accepted or not, so that precision-recall curves can be swept over
    the recorded `f` values without re-running the detector. `candidates` is empty when the
    sequence had no database (nothing old enough) and so could not be a loop closure.
    """

    sequence_id: int
    first_index: int
    last_index: int
    first_timestamp_ns: int
    last_timestamp_ns: int
    database_size: int  # frames that were old enough to be searched
    best_start: int | None  # j*: database frame where the best trajectory starts
    best_velocity: float | None
    best_score: float | None  # S_do[j*]
    # Full search: the lowest score outside the exclusion window. Indexed place search: the
    # median of the windows' non-matching scores (detector/place_search.py), gamma's reference.
    second_score: float | None
    gamma: float  # best / second (1.0 when there is no candidate)
    gamma_previous: float | None
    gamma_next: float | None
    f: float  # the weighted decision value (eq. 8), lower is more confident
    threshold: float
    accepted: bool  # f < threshold and a candidate exists
    candidates: tuple[Candidate, ...]
    method: str  # "doseqslam" or "seqslam"
    # The next-best distinct starts, best first (Parameters.alternatives; empty by default).
    alternatives: tuple[Alternative, ...] = ()

    @property
    def length(self) -> int:
        return self.last_index - self.first_index + 1

    @property
    def loop_closures(self) -> tuple[Candidate, ...]:
        """The pairs this decision reports as loop closures (none when rejected)."""
        return self.candidates if self.accepted else ()
