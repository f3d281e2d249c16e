"""Indexed place search (`Parameters.place_search = "index"`): windows, not rows.

The paper compares each query sequence with every older frame, so a query costs O(log length)
and, on a route driven lap after lap, the second-best trajectory is another visit of the same
place: gamma = best / second best tends to 1 and the revisit is rejected. Here:

1. Proposing. Every frame's ORB descriptors (the segmentation's own when it is ORB) go to a
   `PlaceIndex`, each frame once it belongs to the database of the sequence being queried
   (frames within kappa of the query are never in the index: at 10 Hz their postings, the
   newest, would fill the index's per-word posting cap and hide the older visits). A few
   frames of the sequence (`place_queries`, evenly spread) query it; each result at frame f
   for query frame z votes for the trajectory start f - z. Starts within `place_margin` + the
   sequence's length of each other form one island (a visit), scored by its votes' sum; the
   `place_count` best visits are the places.
2. Scoring. Each place becomes a window of database columns: every start its votes allow at
   velocities velocity_min .. velocity_max, +- (place_margin + the exclusion window), and the
   trajectory's length after the last start. SAD, enhancement and trajectory scores are
   computed in the window only (`sad_columns`); the enhancement is computed on the window
   padded by epsilon / 2 and cropped, so every cell kept equals the full row's. Cost per
   sequence: place_count windows of O(margin + length) columns, whatever the log's length.
3. Deciding. gamma = best score / the median of the windows' non-matching scores (every
   finite score outside each window's own exclusion window around its own best start). A
   place seen k times has k windows, and each visit's good trajectories are excluded from the
   reference: a revisit is not penalized for having been seen before. The median is robust to
   the few near-matches (neighbouring frames) left in a window. The candidates are the
   best-scoring visit's trajectory; the other places' best trajectories, then next-best starts
   in the best window, are the alternatives the verification stage tries.

Memory. The index is bounded per frame (`place_index.memory_bound`); the descriptors of the
frames not yet in the index (the last kappa seconds: 400 frames at 10 Hz and kappa = 40 s,
about 6 MB at 500 ORB features) are held until they are added.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from .difference import FrameStore, sad_columns
from .enhance import enhance
from .params import Parameters
from .place_index import PlaceIndex, PlaceIndexParams
from .segmentation import SMALL_FRAME_SIDE, create_detector, feature_image
from .trajectory import TrajectoryScores, trajectory_scores

Descriptors = npt.NDArray[np.uint8]
FloatArray = npt.NDArray[np.float32]
GrayImage = npt.NDArray[np.uint8]

# Index results asked per query frame, per place proposed.
RESULTS_PER_PLACE = 2

_orb = threading.local()


def orb_descriptors(
    gray: GrayImage, max_features: int, max_side: int, enlarge_below: int = SMALL_FRAME_SIDE
) -> Descriptors | None:
    """ORB descriptors of the frame shrunk to `max_side`, frames under `enlarge_below`
    enlarged to it (`feature_image`), for a segmentation that is not ORB (thread-safe: one
    ORB per thread)."""
    detector = getattr(_orb, "detector", None)
    if detector is None or getattr(_orb, "features", None) != max_features:
        detector = _orb.detector = create_detector("orb", max_features)[0]
        _orb.features = max_features
    _, descriptors = detector.detectAndCompute(feature_image(gray, max_side, enlarge_below), None)
    return None if descriptors is None or len(descriptors) == 0 else np.asarray(descriptors)


def binary_descriptors(segmentation: Any) -> Descriptors | None:
    """The segmentation's descriptors when they are ORB's (uint8 rows of 32 bytes)."""
    descriptors = getattr(segmentation, "descriptors", None)
    if descriptors is None or descriptors.dtype != np.uint8 or descriptors.shape[1:] != (32,):
        return None
    return np.asarray(descriptors)


@dataclass(frozen=True)
class Window:
    """Database columns first .. stop-1 around one proposed place, with its index votes."""

    first: int
    stop: int
    votes: float


@dataclass(frozen=True)
class ScoredWindow:
    """A window's trajectory scores (starts relative to `first`) and its best start."""

    first: int
    enhanced: FloatArray
    scores: TrajectoryScores
    best: int  # relative start of the lowest score

    @property
    def best_score(self) -> float:
        return float(self.scores.scores[self.best])


@dataclass(frozen=True)
class Exclusion:
    """Frames excluded on either side of a best start (the paper's eq. 7 window)."""

    before: int
    after: int


class PlaceSearch:
    """The place index and the descriptors of the frames waiting to join it."""

    def __init__(self, params: Parameters, index: PlaceIndexParams | None = None) -> None:
        self.params = params
        self.index = PlaceIndex(index)
        # (frame, descriptors, joins the index): every frame's, for the sequence's queries.
        self._waiting: deque[tuple[int, Descriptors | None, bool]] = deque()
        self._interval_ns = round(params.place_index_interval_s * 1e9)
        self._last_indexed_ns: int | None = None

    def keep(self, frame_index: int, descriptors: Descriptors | None, timestamp_ns: int) -> None:
        """Hold a frame's descriptors until the frame enters a queried database; it will join
        the index when it is a keyframe: `place_index_interval_s` after the last one."""
        keyframe = (
            self._last_indexed_ns is None
            or timestamp_ns - self._last_indexed_ns >= self._interval_ns
        )
        if keyframe:
            self._last_indexed_ns = timestamp_ns
        self._waiting.append((frame_index, descriptors, keyframe))

    def _index_before(self, database: int) -> None:
        while self._waiting and self._waiting[0][0] < database:
            frame, descriptors, keyframe = self._waiting.popleft()
            if keyframe and descriptors is not None and len(descriptors):
                self.index.add(frame, descriptors)

    def _descriptors(self, frame: int) -> Descriptors | None:
        first = self._waiting[0][0] if self._waiting else frame + 1
        if frame < first:
            return None
        held_frame, descriptors, _ = self._waiting[frame - first]
        assert held_frame == frame
        return descriptors

    @property
    def memory_bytes(self) -> int:
        held = sum(d.nbytes for _, d, _ in self._waiting if d is not None)
        return self.index.memory_bytes + held

    def windows(self, first: int, last: int, database: int, exclusion: Exclusion) -> list[Window]:
        """The windows of the `place_count` best-voted places of frames first..last, among the
        database's frames (< database); overlapping windows are merged."""
        self._index_before(database)
        p = self.params
        length = last - first + 1
        picks = np.unique(np.rint(np.linspace(0, length - 1, min(p.place_queries, length))))
        votes: list[tuple[int, int, float]] = []  # (z, frame, score)
        for z in picks.astype(int):
            descriptors = self._descriptors(first + int(z))
            if descriptors is None:
                continue
            k = RESULTS_PER_PLACE * p.place_count
            votes.extend((int(z), f, s) for f, s in self.index.query(descriptors, database, k))
        islands = _islands(votes, p.place_margin + length)[: p.place_count]
        reach = round(p.velocity_max * (length - 1))
        pad = p.place_margin + max(exclusion.before, exclusion.after)
        spans = []
        for island in islands:
            low = min(f - math.ceil(p.velocity_max * z) for z, f, _ in island)
            high = max(f - math.floor(p.velocity_min * z) for z, f, _ in island)
            spans.append(
                Window(
                    max(0, low - pad),
                    min(database, high + pad + reach + 1),
                    sum(s for _, _, s in island),
                )
            )
        return _merged([w for w in spans if w.stop > w.first])

    def score(
        self, store: FrameStore, first: int, last: int, window: Window, database: int
    ) -> ScoredWindow | None:
        """Trajectory scores of frames first..last in the window (None: no trajectory fits).
        The padding stops at the database's ends, as the full row's enhancement does."""
        p = self.params
        half = p.enhancement_window // 2
        padded = (max(0, window.first - half), min(database, window.stop + half))
        rows = sad_columns(store.rows(first, last), store, *padded)
        enhanced = enhance(rows, p.enhancement_window)
        crop = np.ascontiguousarray(enhanced[:, window.first - padded[0] : window.stop - padded[0]])
        scores = trajectory_scores(crop, p.velocities)
        if not np.isfinite(scores.scores).any():
            return None
        return ScoredWindow(window.first, crop, scores, int(np.argmin(scores.scores)))


def _islands(votes: list[tuple[int, int, float]], gap: int) -> list[list[tuple[int, int, float]]]:
    """Votes grouped by trajectory start (frame - z), starts within `gap` in one island; best
    island (highest vote sum, then the newest) first."""
    ordered = sorted(votes, key=lambda v: (v[1] - v[0], v[1]))
    islands: list[list[tuple[int, int, float]]] = []
    for vote in ordered:
        if islands and vote[1] - vote[0] - (islands[-1][-1][1] - islands[-1][-1][0]) <= gap:
            islands[-1].append(vote)
        else:
            islands.append([vote])
    return sorted(islands, key=lambda i: (-sum(s for _, _, s in i), -i[-1][1]))


def _merged(windows: list[Window]) -> list[Window]:
    """Overlapping windows as one (votes summed), most voted first."""
    merged: list[Window] = []
    for w in sorted(windows, key=lambda w: w.first):
        if merged and w.first < merged[-1].stop:
            last = merged[-1]
            merged[-1] = Window(last.first, max(last.stop, w.stop), last.votes + w.votes)
        else:
            merged.append(w)
    return sorted(merged, key=lambda w: (-w.votes, w.first))


def reference_score(windows: list[ScoredWindow], exclusion: Exclusion) -> float | None:
    """The median of the windows' finite scores outside each one's exclusion window around its
    own best start: what a non-matching trajectory scores here (None: no such score)."""
    pool = []
    for w in windows:
        outside = np.isfinite(w.scores.scores)
        outside[max(w.best - exclusion.before, 0) : w.best + exclusion.after + 1] = False
        pool.append(w.scores.scores[outside])
    values = np.concatenate(pool) if pool else np.zeros(0, np.float32)
    return float(np.median(values)) if len(values) else None


def place_gamma(best: float, reference: float | None) -> float:
    """best / reference, in [0, 1]; 1.0 (no confidence) without a positive reference."""
    if reference is None or not reference > 0:
        return 1.0
    gamma = best / reference
    return min(gamma, 1.0) if math.isfinite(gamma) else 1.0
