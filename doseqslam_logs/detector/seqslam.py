"""The SeqSLAM baseline of the paper, online: fixed-length backward-looking trajectories.

Every frame i >= ds - 1 is a query: the trajectory covers frames i-ds+1 .. i, the database is the
frames at least kappa seconds older than the trajectory's first frame, and the ratio of the best
score to the second best outside +-ds/2 is the decision value (loop when ratio < threshold).
"""

from __future__ import annotations

from array import array
from bisect import bisect_right
from collections import deque
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from .difference import FrameStore, sad_rows
from .doseqslam import PreparedFrame, check_store, default_store
from .enhance import enhance
from .events import Candidate, SequenceDecision
from .params import Parameters
from .preprocess import frame_vector
from .timing import StageTimes
from .trajectory import normalize, trajectory_scores

if TYPE_CHECKING:
    from .segmentation import OrbFeatures

GrayImage = npt.NDArray[np.uint8]
FloatArray = npt.NDArray[np.float32]


class SeqSLAM:
    """Online SeqSLAM (Milford and Wyeth, 2012) with the same preprocessing as DOSeqSLAM."""

    method = "seqslam"
    feature_detector = "none"

    def __init__(self, params: Parameters | None = None, store: FrameStore | None = None) -> None:
        """`store`: as DOSeqSLAM's."""
        self.params = params or Parameters(method="seqslam")
        self._store = (
            default_store(self.params) if store is None else check_store(store, self.params)
        )
        self._timestamps = array("q")
        self._kappa_ns = round(self.params.kappa_s * 1e9)
        # Raw difference rows of the last ds frames, each against every frame old enough for
        # it; a trajectory containing the row needs a prefix of it (its first frame is older).
        self._rows: deque[FloatArray] = deque(maxlen=self.params.seqslam_length)
        self.timings = StageTimes()

    @property
    def frame_count(self) -> int:
        return len(self._timestamps)

    @property
    def memory_bytes(self) -> int:
        rows = sum(r.nbytes for r in self._rows)
        return self._store.nbytes + rows + self._timestamps.itemsize * len(self._timestamps)

    def prepare(self, gray: GrayImage, supplied: OrbFeatures | None = None) -> PreparedFrame:
        """The frame vector (SeqSLAM needs no features: `supplied` is ignored); thread-safe."""
        p = self.params
        with self.timings.stage("preprocess"):
            vector = frame_vector(gray, p.image_width, p.image_height, p.patch_size)
        return PreparedFrame(vector, None)

    def push(self, timestamp_ns: int, gray: GrayImage) -> list[SequenceDecision]:
        """Add the next frame; returns the decision on it as a query.

        Raises ValueError for a timestamp earlier than the previous one.
        """
        return self.push_prepared(timestamp_ns, self.prepare(gray))

    def push_prepared(self, timestamp_ns: int, frame: PreparedFrame) -> list[SequenceDecision]:
        """`push` for a frame already prepared."""
        if self._timestamps and timestamp_ns < self._timestamps[-1]:
            raise ValueError(
                f"timestamps must not decrease: {timestamp_ns} after {self._timestamps[-1]}"
            )
        index = self._store.append(frame.vector)
        self._timestamps.append(timestamp_ns)
        database = self._database_size(index)
        with self.timings.stage("sad"):
            row = sad_rows(self._store.rows(index, index), self._store, database)[0]
        self._rows.append(row)
        return [self._decide(index)]

    def finish(self) -> list[SequenceDecision]:
        """Every frame was decided when pushed."""
        return []

    def _database_size(self, index: int) -> int:
        bound = bisect_right(self._timestamps, self._timestamps[index] - self._kappa_ns)
        return min(bound, index)

    def _decide(self, index: int) -> SequenceDecision:
        ds = self.params.seqslam_length
        first = max(index - ds + 1, 0)
        database = self._database_size(first) if index >= ds - 1 else 0
        undecidable = SequenceDecision(
            sequence_id=index,
            first_index=first,
            last_index=index,
            first_timestamp_ns=self._timestamps[first],
            last_timestamp_ns=self._timestamps[index],
            database_size=database,
            best_start=None,
            best_velocity=None,
            best_score=None,
            second_score=None,
            gamma=1.0,
            gamma_previous=None,
            gamma_next=None,
            f=1.0,
            threshold=self.params.threshold,
            accepted=False,
            candidates=(),
            method=self.method,
        )
        if database == 0:
            return undecidable
        rows = np.stack([row[:database] for row in self._rows])
        enhanced = enhance(rows, self.params.enhancement_window)
        scores = trajectory_scores(enhanced, self.params.velocities)
        norm = normalize(scores.scores, ds // 2, ds // 2)
        if norm is None:
            return undecidable
        match = norm.best_start + int(scores.best_offsets(norm.best_start)[-1])
        candidate = Candidate(
            query_index=index,
            match_index=match,
            query_timestamp_ns=self._timestamps[index],
            match_timestamp_ns=self._timestamps[match],
            difference=float(enhanced[-1, match]),
        )
        return replace(
            undecidable,
            best_start=norm.best_start,
            best_velocity=scores.best_velocity(norm.best_start),
            best_score=norm.best_score,
            second_score=norm.second_score,
            gamma=norm.gamma,
            f=norm.gamma,
            accepted=norm.gamma < self.params.threshold,
            candidates=(candidate,),
        )
