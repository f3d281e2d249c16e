"""The online DOSeqSLAM detector (Tsintotas et al., 2018), as ../shared/spec/algorithm.md reads it.

Frames arrive one at a time. Sequence S_k is queried once S_{k+1} is complete (the exclusion
window needs its length), and decided once gamma_{k+1} exists (the weighted decision, eq. 8).
Only the last few sequences are held; frame vectors are the only per-frame state (and, in
the indexed place search, `place_search.py`, the place index's bounded postings).
"""

from __future__ import annotations

import math
from array import array
from bisect import bisect_right
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from .association import greedy_matches, pair_differences, trajectory_matches
from .difference import FrameStore, sad_rows
from .enhance import enhance
from .events import Alternative, Candidate, SequenceDecision
from .params import Parameters
from .place_search import (
    Exclusion,
    PlaceSearch,
    ScoredWindow,
    binary_descriptors,
    orb_descriptors,
    place_gamma,
    reference_score,
)
from .preprocess import frame_vector
from .segmentation import (
    SMALL_FRAME_SIDE,
    DescriptorSegmenter,
    OrbFeatures,
    Segmenter,
    feature_count,
    make_segmenter,
)
from .timing import StageTimes
from .trajectory import TrajectoryScores, next_best_starts, normalize, trajectory_scores

GrayImage = npt.NDArray[np.uint8]
FloatArray = npt.NDArray[np.float32]
IntArray = npt.NDArray[np.int64]

# Weights of gamma_{k-1}, gamma_k, gamma_{k+1} in the decision (paper eq. 8).
DECISION_WEIGHTS = (1.0, 4.0, 1.0)
# The exclusion window spans this many lengths of the neighbouring sequences (paper eq. 7).
WINDOW_LENGTHS = 2


@dataclass(frozen=True)
class PreparedFrame:
    """What `prepare` computes from one frame alone: safe to compute ahead, in threads."""

    vector: npt.NDArray[np.float32]
    segmentation: Any
    # ORB descriptors for the place index (place_search = "index" only).
    place_descriptors: npt.NDArray[np.uint8] | None = None
    # Segmentation features found in the frame (-1: not counted, as for KLT and SeqSLAM), so
    # that a run can tell when its frames were too poor to segment (pipeline.feature_health).
    feature_count: int = -1


@dataclass(frozen=True)
class QueryResult:
    """What querying one sequence against its database gave."""

    database_size: int
    gamma: float
    best_start: int | None = None
    best_velocity: float | None = None
    best_score: float | None = None
    second_score: float | None = None
    candidates: tuple[Candidate, ...] = ()
    alternatives: tuple[Alternative, ...] = ()


@dataclass
class _Sequence:
    sequence_id: int
    first: int
    last: int
    result: QueryResult | None = None
    decided: bool = False

    @property
    def length(self) -> int:
        return self.last - self.first + 1


def default_store(params: Parameters) -> FrameStore:
    """An in-memory store for the parameters' frame vectors."""
    return FrameStore(params.image_width * params.image_height, params.difference_precision)


def check_store(store: FrameStore, params: Parameters) -> FrameStore:
    """`store` when it is empty and holds the parameters' frame vectors; else ValueError."""
    dimension = params.image_width * params.image_height
    if len(store) or store.dimension != dimension or store.precision != params.difference_precision:
        raise ValueError(
            f"the frame store must be empty, of {dimension} {params.difference_precision} values"
        )
    return store


def weighted_decision(previous: float | None, gamma: float, following: float | None) -> float:
    """f = (gamma_{k-1} + 4 gamma_k + gamma_{k+1}) / 6, renormalized over the gammas that exist."""
    terms = [
        (w, g)
        for w, g in zip(DECISION_WEIGHTS, (previous, gamma, following), strict=False)
        if g is not None
    ]
    return sum(w * g for w, g in terms) / sum(w for w, _ in terms)


class DOSeqSLAM:
    """Online DOSeqSLAM: `push` frames in timestamp order, then `finish`."""

    method = "doseqslam"

    def __init__(
        self,
        params: Parameters | None = None,
        segmenter: Segmenter | None = None,
        store: FrameStore | None = None,
    ) -> None:
        """`segmenter` replaces the one the parameters name (tests fix sequence boundaries);
        `store`, an empty one for the parameters' frame vectors, the in-memory store (the
        pipeline passes one that spills older vectors to a file)."""
        self.params = params or Parameters()
        self._store = (
            default_store(self.params) if store is None else check_store(store, self.params)
        )
        self._timestamps = array("q")
        self._segmenter = segmenter or make_segmenter(self.params)
        self._kappa_ns = round(self.params.kappa_s * 1e9)
        self._open_first: int | None = None
        self._sequences: list[_Sequence] = []
        self._next_id = 0
        self._finished = False
        self.timings = StageTimes()
        self._places = PlaceSearch(self.params) if self.params.place_search == "index" else None

    @property
    def feature_detector(self) -> str:
        """The segmentation detector in use ("auto" resolved)."""
        return self._segmenter.name

    @property
    def frame_count(self) -> int:
        return len(self._timestamps)

    @property
    def held_sequences(self) -> int:
        """Sequences held in memory: the undecided tail and the last decided one."""
        return len(self._sequences)

    @property
    def indexed(self) -> bool:
        """Whether sequences are searched through the place index (place_search = "index")."""
        return self._places is not None

    @property
    def memory_bytes(self) -> int:
        """Bytes held for frame vectors, timestamps and the place index (what grows with the
        log). Frame vectors: 2048 B a frame, 295 MB for a 4-hour 10 Hz log."""
        places = self._places.memory_bytes if self._places is not None else 0
        return self._store.nbytes + self._timestamps.itemsize * len(self._timestamps) + places

    def prepare(self, gray: GrayImage, supplied: OrbFeatures | None = None) -> PreparedFrame:
        """The frame vector and segmentation features; thread-safe, needs no other frame.

        `supplied`: the frame's ORB features that the caller already extracted from the image
        this detector's ORB would see (`feature_image` at feature_image_max_side, enlarged as
        the parameters say), with a budget of at least max_features: an ORB segmentation and
        the place index take those ORB would have kept for max_features instead of extracting
        their own. Ignored by any other segmentation.
        """
        p = self.params
        with self.timings.stage("preprocess"):
            vector = frame_vector(gray, p.image_width, p.image_height, p.patch_size)
        with self.timings.stage("features"):
            if supplied is not None and isinstance(self._segmenter, DescriptorSegmenter):
                features = self._segmenter.supplied(supplied)
            else:
                features = self._segmenter.prepare(gray)
            places = None
            if self._places is not None and self._segmenter.name == "orb":  # reuse them
                places = binary_descriptors(features)
            elif self._places is not None:
                side = p.feature_image_max_side
                below = side if p.feature_image_enlarge else SMALL_FRAME_SIDE
                places = orb_descriptors(gray, p.max_features, side, below)
        return PreparedFrame(vector, features, places, feature_count(features))

    def push(self, timestamp_ns: int, gray: GrayImage) -> list[SequenceDecision]:
        """Add the next frame; returns the decisions this frame made possible.

        Raises ValueError for a timestamp earlier than the previous one or after `finish`.
        """
        return self.push_prepared(timestamp_ns, self.prepare(gray))

    def push_prepared(self, timestamp_ns: int, frame: PreparedFrame) -> list[SequenceDecision]:
        """`push` for a frame already prepared (e.g. by a pool running `prepare` ahead)."""
        if self._finished:
            raise ValueError("push after finish")
        if self._timestamps and timestamp_ns < self._timestamps[-1]:
            raise ValueError(
                f"timestamps must not decrease: {timestamp_ns} after {self._timestamps[-1]}"
            )
        index = self._store.append(frame.vector)
        self._timestamps.append(timestamp_ns)
        if self._places is not None:
            self._places.keep(index, frame.place_descriptors, timestamp_ns)
        with self.timings.stage("segmentation"):
            if self._open_first is not None and self._reached_cap(index):
                self._segmenter.restart(frame.segmentation)
                starts = True
            else:
                starts = self._segmenter.update(frame.segmentation)
        if not starts and self._open_first is not None:
            return []
        if self._open_first is not None:
            self._close_sequence(index - 1)
        self._open_first = index
        return self._advance(final=False)

    def finish(self) -> list[SequenceDecision]:
        """End of stream: close the open sequence and decide every sequence left."""
        if self._finished:
            return []
        self._finished = True
        if self._open_first is not None:
            self._close_sequence(len(self._timestamps) - 1)
            self._open_first = None
        return self._advance(final=True)

    def _reached_cap(self, index: int) -> bool:
        cap = self.params.max_sequence_length
        return cap > 0 and self._open_first is not None and index - self._open_first >= cap

    def _close_sequence(self, last: int) -> None:
        assert self._open_first is not None
        self._sequences.append(_Sequence(self._next_id, self._open_first, last))
        self._next_id += 1

    def _advance(self, final: bool) -> list[SequenceDecision]:
        """Query every sequence whose successor is complete, decide every sequence whose
        successor has been queried, and forget all but the last decided one."""
        seqs = self._sequences
        for k, seq in enumerate(seqs):
            if seq.result is None and (k + 1 < len(seqs) or final):
                before = seqs[k - 1].length if k > 0 else 0
                after = seqs[k + 1].length if k + 1 < len(seqs) else 0
                seq.result = self._query(seq, before, after)
        decisions = []
        for k, seq in enumerate(seqs):
            if seq.decided or seq.result is None:
                continue
            following = seqs[k + 1].result if k + 1 < len(seqs) else None
            if following is None and not final:
                break
            previous = seqs[k - 1].result if k > 0 else None
            decisions.append(self._decide(seq, previous, following))
        last_decided = max((k for k, s in enumerate(seqs) if s.decided), default=-1)
        del seqs[: max(last_decided, 0)]
        return decisions

    def _database_size(self, first: int) -> int:
        """Frames at least kappa seconds older than frame `first` (a prefix of the stream)."""
        return bisect_right(self._timestamps, self._timestamps[first] - self._kappa_ns)

    def _query(self, seq: _Sequence, before: int, after: int) -> QueryResult:
        database = min(self._database_size(seq.first), seq.first)
        if database == 0:
            return QueryResult(database_size=0, gamma=1.0)
        if self._places is not None:
            exclusion = Exclusion(WINDOW_LENGTHS * before, WINDOW_LENGTHS * after)
            return self._query_places(seq, database, exclusion)
        with self.timings.stage("sad"):
            rows = sad_rows(self._store.rows(seq.first, seq.last), self._store, database)
        with self.timings.stage("enhance"):
            enhanced = enhance(rows, self.params.enhancement_window)
        with self.timings.stage("trajectory"):
            scores = trajectory_scores(enhanced, self.params.velocities)
            norm = normalize(scores.scores, WINDOW_LENGTHS * before, WINDOW_LENGTHS * after)
        if norm is None:  # the database is shorter than any trajectory of this sequence
            return QueryResult(database_size=database, gamma=1.0)
        with self.timings.stage("association"):
            matches = self._matches(scores, enhanced, norm.best_start)
            differences = pair_differences(enhanced, matches)
            alternatives = tuple(
                Alternative(
                    start=j,
                    velocity=scores.best_velocity(j),
                    score=float(scores.scores[j]),
                    match_indices=tuple(int(m) for m in self._matches(scores, enhanced, j)),
                )
                for j in next_best_starts(
                    scores.scores,
                    norm.best_start,
                    self.params.alternatives,
                    self.params.alternative_separation,
                )
            )
        candidates = self._candidates(seq, matches, differences)
        return QueryResult(
            database_size=database,
            gamma=norm.gamma,
            best_start=norm.best_start,
            best_velocity=scores.best_velocity(norm.best_start),
            best_score=norm.best_score,
            second_score=norm.second_score,
            candidates=candidates,
            alternatives=alternatives,
        )

    def _query_places(self, seq: _Sequence, database: int, exclusion: Exclusion) -> QueryResult:
        """The indexed place search (place_search.py): the best window's best trajectory, the
        other windows' as alternatives, gamma against the windows' non-matching scores."""
        assert self._places is not None
        with self.timings.stage("places"):
            windows = self._places.windows(seq.first, seq.last, database, exclusion)
        with self.timings.stage("sad"):
            scored = [
                self._places.score(self._store, seq.first, seq.last, w, database) for w in windows
            ]
        found = sorted((w for w in scored if w is not None), key=lambda w: w.best_score)
        if not found:
            return QueryResult(database_size=database, gamma=1.0)
        best = found[0]
        reference = reference_score(found, exclusion)
        with self.timings.stage("association"):
            matches = self._matches(best.scores, best.enhanced, best.best) + best.first
            differences = pair_differences(best.enhanced, matches - best.first)
            alternatives = self._place_alternatives(found)
        return QueryResult(
            database_size=database,
            gamma=place_gamma(best.best_score, reference),
            best_start=best.first + best.best,
            best_velocity=best.scores.best_velocity(best.best),
            best_score=best.best_score,
            second_score=reference,
            candidates=self._candidates(seq, matches, differences),
            alternatives=alternatives,
        )

    def _place_alternatives(self, found: list[ScoredWindow]) -> tuple[Alternative, ...]:
        """The other windows' best starts, then the best window's next-best starts, up to
        `alternatives`."""
        p = self.params
        best = found[0]
        starts = [(w, w.best) for w in found[1:]]
        extra = next_best_starts(
            best.scores.scores, best.best, p.alternatives, p.alternative_separation
        )
        starts += [(best, j) for j in extra]
        return tuple(
            Alternative(
                start=w.first + j,
                velocity=w.scores.best_velocity(j),
                score=float(w.scores.scores[j]),
                match_indices=tuple(
                    int(m) + w.first for m in self._matches(w.scores, w.enhanced, j)
                ),
            )
            for w, j in starts[: p.alternatives]
        )

    def _candidates(
        self, seq: _Sequence, matches: IntArray, differences: FloatArray
    ) -> tuple[Candidate, ...]:
        return tuple(
            Candidate(
                query_index=seq.first + z,
                match_index=int(m),
                query_timestamp_ns=self._timestamps[seq.first + z],
                match_timestamp_ns=self._timestamps[int(m)],
                difference=float(d),
            )
            for z, (m, d) in enumerate(zip(matches, differences, strict=False))
        )

    def _matches(self, scores: TrajectoryScores, enhanced: FloatArray, start: int) -> IntArray:
        """The database frame of each query frame on the trajectory starting at `start`."""
        if self.params.association == "greedy":
            return greedy_matches(enhanced, start, self.params.velocity_max)
        return trajectory_matches(scores, start)

    def _decide(
        self, seq: _Sequence, previous: QueryResult | None, following: QueryResult | None
    ) -> SequenceDecision:
        result = seq.result
        assert result is not None
        g_prev = previous.gamma if previous else None
        g_next = following.gamma if following else None
        f = weighted_decision(g_prev, result.gamma, g_next)
        seq.decided = True
        return SequenceDecision(
            sequence_id=seq.sequence_id,
            first_index=seq.first,
            last_index=seq.last,
            first_timestamp_ns=self._timestamps[seq.first],
            last_timestamp_ns=self._timestamps[seq.last],
            database_size=result.database_size,
            best_start=result.best_start,
            best_velocity=result.best_velocity,
            best_score=result.best_score,
            second_score=result.second_score,
            gamma=result.gamma,
            gamma_previous=g_prev,
            gamma_next=g_next,
            f=f,
            threshold=self.params.threshold,
            accepted=bool(result.candidates) and f < self.params.threshold and math.isfinite(f),
            candidates=result.candidates,
            method=self.method,
            alternatives=result.alternatives,
        )
