"""Precision, recall and R@P100 of a run's sequence decisions against a ground-truth matrix.

The protocol is the authors' (spec/algorithm.md, "Evaluation protocol"): a reported pair
(query, match) is a true positive when GT[query, match] is 1 (optionally within +-tolerance
frames on the match column), else a false positive; recall = TP / number of GT rows with any 1;
precision = TP / (TP + FP). At a threshold th a decision reports its candidates when f < th.

Two rules beyond the paper, both no-ops on well-formed detector output:
- each query frame counts once: when several decisions hold the same query frame, the one with
  the lowest f (then the earliest in the run) reports it, so TP can never exceed the number of
  GT loop events and recall stays within [0, 1];
- decisions whose f is NaN or infinite are never reported (no finite threshold separates them).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ..detector.events import SequenceDecision
from ..errors import GroundTruthError, UsageError
from .groundtruth import LoopTruth

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_LENGTH_PERCENTILES = (10, 25, 75, 90)
# Window lengths of the revisit coverage, in seconds of the detector's timestamps.
COVERAGE_WINDOWS_S = (1.0, 5.0)
NANOS_PER_SECOND = 1_000_000_000


@dataclass(frozen=True)
class CurvePoint:
    """One point of the precision-recall curve.

    `threshold` reproduces the point: evaluating at it reports exactly these TP and FP.
    """

    threshold: float
    tp: int
    fp: int
    precision: float
    recall: float


@dataclass(frozen=True)
class LengthStats:
    """Distribution of sequence lengths in frames (all 0 when there are no sequences)."""

    min: int
    p10: float
    p25: float
    median: float
    mean: float
    p75: float
    p90: float
    max: int


@dataclass(frozen=True)
class RevisitCoverage:
    """How much of the time spent revisiting got at least one loop closure.

    The run's time is cut into windows of `window_s` seconds (from its first frame). `windows`
    counts those holding a revisit (a frame with a loop event in the ground truth), `covered`
    those of them holding the query frame of a true reported pair. At 10 Hz a revisit lasts
    many frames: frame recall counts each of them, coverage asks whether each second (or
    five) of the revisit was recognized at all, which is what a pose graph needs.
    """

    window_s: float
    windows: int
    covered: int

    @property
    def share(self) -> float:
        """covered / windows (0.0 without a revisit)."""
        return self.covered / self.windows if self.windows else 0.0


@dataclass(frozen=True)
class Evaluation:
    """A run scored against one ground truth at one threshold, plus its whole PR curve.

    `precision` is 1.0 when nothing is reported (no false positives were made); `recall` is 0.0
    when the ground truth has no loop events. `threshold_at_r_p100` is None when no threshold
    reaches 100 % precision with a true positive.
    """

    gt_file: str
    gt_frames: int
    gt_loop_events: int
    gt_transposed: bool
    tolerance: int
    threshold: float
    frames: int
    sequences: int
    lengths: LengthStats
    accepted_sequences: int
    tp: int
    fp: int
    precision: float
    recall: float
    r_p100: float
    threshold_at_r_p100: float | None
    recall_at_p90: float
    curve: tuple[CurvePoint, ...]
    # At th, per window length; () when the frames' times were not given.
    coverage: tuple[RevisitCoverage, ...] = ()

    def recall_at_precision(self, precision: float) -> float:
        """Highest recall among curve points whose precision is >= `precision` (0.0 if none)."""
        return _recall_at_precision(self.curve, precision)

    def to_json_dict(self) -> dict[str, Any]:
        """The evaluation as plain JSON types (dicts, lists, str, int, float, bool, None)."""
        result = asdict(self)
        result["curve"] = [asdict(point) for point in self.curve]
        result["coverage"] = [{**asdict(c), "share": c.share} for c in self.coverage]
        return result


@dataclass(frozen=True)
class _Sweep:
    """Decisions that can report, sorted by f, with cumulative TP/FP after each of them."""

    f: FloatArray
    cum_tp: IntArray
    cum_fp: IntArray
    queries: IntArray  # each reported query frame once, with the rank of its decision
    ranks: IntArray
    true: npt.NDArray[np.bool_]

    def entered(self, threshold: float) -> int:
        """Decisions reported at `threshold`: every one with f < threshold (a prefix)."""
        return int(np.searchsorted(self.f, threshold, side="left"))

    def counts_at(self, threshold: float) -> tuple[int, int, int]:
        """(decisions, TP, FP) reported at `threshold`."""
        entered = self.entered(threshold)
        if entered == 0:
            return 0, 0, 0
        return entered, int(self.cum_tp[entered - 1]), int(self.cum_fp[entered - 1])

    def true_queries_at(self, threshold: float) -> IntArray:
        """The query frames of the true pairs reported at `threshold`."""
        return self.queries[self.true & (self.ranks < self.entered(threshold))]


def evaluate(
    decisions: Sequence[SequenceDecision],
    gt: LoopTruth,
    threshold: float,
    tolerance: int = 0,
    frame_times_ns: npt.ArrayLike | None = None,
) -> Evaluation:
    """Score `decisions` against `gt` at `threshold` and sweep the precision-recall curve.

    The sweep sorts decisions by f once and accumulates TP/FP counts (O(n log n)); decisions
    with equal f enter the curve together. With `frame_times_ns` (the detector's time of
    every frame, by index) the revisit coverage is measured too (`RevisitCoverage`).

    Raises:
        GroundTruthError: a frame index of the run lies outside the ground truth
            ("ground truth has N frames but the run has M").
        UsageError: tolerance is negative or threshold is NaN.
    """
    if tolerance < 0:
        raise UsageError(f"tolerance must be >= 0, got {tolerance}")
    if math.isnan(threshold):
        raise UsageError("threshold must be a number, got NaN")
    _check_frame_count(decisions, gt)
    sweep = _sweep(decisions, gt, tolerance)
    curve = _curve(sweep, gt.n_loop_events)
    accepted, tp, fp = sweep.counts_at(threshold)
    precision, recall = _ratios(tp, fp, gt.n_loop_events)
    best = _best_at_full_precision(curve)
    return Evaluation(
        gt_file=Path(gt.source).name,
        gt_frames=gt.n_frames,
        gt_loop_events=gt.n_loop_events,
        gt_transposed=gt.transposed,
        tolerance=tolerance,
        threshold=float(threshold),
        frames=_frames_decided(decisions),
        sequences=len(decisions),
        lengths=_length_stats(decisions),
        accepted_sequences=accepted,
        tp=tp,
        fp=fp,
        precision=precision,
        recall=recall,
        r_p100=best.recall if best else 0.0,
        threshold_at_r_p100=best.threshold if best else None,
        recall_at_p90=_recall_at_precision(curve, 0.9),
        curve=curve,
        coverage=_coverage(sweep.true_queries_at(threshold), gt, frame_times_ns),
    )


def _coverage(
    found: IntArray, gt: LoopTruth, frame_times_ns: npt.ArrayLike | None
) -> tuple[RevisitCoverage, ...]:
    if frame_times_ns is None:
        return ()
    times = np.asarray(frame_times_ns, dtype=np.int64)
    if times.size == 0:
        return tuple(RevisitCoverage(w, 0, 0) for w in COVERAGE_WINDOWS_S)
    revisits = gt.query_rows()
    revisits = revisits[revisits < times.size]
    found = found[found < times.size]
    result = []
    for window_s in COVERAGE_WINDOWS_S:
        width = round(window_s * NANOS_PER_SECOND)
        holding = np.unique((times[revisits] - times[0]) // width)
        covered = np.intersect1d(holding, (times[found] - times[0]) // width)
        result.append(RevisitCoverage(window_s, int(holding.size), int(covered.size)))
    return tuple(result)


# -- the sweep ----------------------------------------------------------------------------


def _check_frame_count(decisions: Sequence[SequenceDecision], gt: LoopTruth) -> None:
    """A run longer than the ground truth means they do not belong together: say so."""
    indices = [d.last_index for d in decisions]
    indices += [i for d in decisions for c in d.candidates for i in (c.query_index, c.match_index)]
    if not indices:
        return
    lowest, highest = min(indices), max(indices)
    if lowest < 0:
        raise GroundTruthError(f"{gt.source}: the run has a negative frame index ({lowest})")
    if highest >= gt.n_frames:
        raise GroundTruthError(
            f"{gt.source}: ground truth has {gt.n_frames} frames but the run has {highest + 1}"
        )


def _sweep(decisions: Sequence[SequenceDecision], gt: LoopTruth, tolerance: int) -> _Sweep:
    """Sort the reporting decisions by f and count TP/FP cumulatively along that order."""
    f_all = np.array([d.f for d in decisions], dtype=np.float64)
    counts_all = np.array([len(d.candidates) for d in decisions], dtype=np.int64)
    reporting = np.flatnonzero(np.isfinite(f_all) & (counts_all > 0))
    # Stable: equal f keeps run order, which decides who reports a shared query frame.
    order = reporting[np.argsort(f_all[reporting], kind="stable")]
    counts = counts_all[order]
    rank = np.repeat(np.arange(order.size), counts)
    pairs = [(c.query_index, c.match_index) for i in order for c in decisions[i].candidates]
    q, m = np.array(pairs, dtype=np.int64).reshape(-1, 2).T
    # Each query frame counts once, for the first decision (lowest f) that reports it.
    _, first = np.unique(q, return_index=True)
    truth = gt.are_true(q[first], m[first], tolerance)
    tp = np.bincount(rank[first], weights=truth, minlength=order.size)
    fp = np.bincount(rank[first], weights=~truth, minlength=order.size)
    return _Sweep(
        f=f_all[order],
        cum_tp=np.cumsum(tp).astype(np.int64),
        cum_fp=np.cumsum(fp).astype(np.int64),
        queries=q[first],
        ranks=rank[first],
        true=np.asarray(truth, dtype=bool),
    )


def _curve(sweep: _Sweep, loop_events: int) -> tuple[CurvePoint, ...]:
    """One point per distinct f: all decisions with f at most that value have entered."""
    if sweep.f.size == 0:
        return ()
    # Last decision of each run of equal f: equal values enter together.
    ends = np.append(np.flatnonzero(np.diff(sweep.f) != 0), sweep.f.size - 1)
    values: list[float] = sweep.f[ends].tolist()
    thresholds = [_threshold_above(a, b) for a, b in itertools.pairwise(values)]
    thresholds.append(_threshold_above(values[-1], None))
    points = []
    for th, end in zip(thresholds, ends, strict=True):
        tp, fp = int(sweep.cum_tp[end]), int(sweep.cum_fp[end])
        precision, recall = _ratios(tp, fp, loop_events)
        points.append(CurvePoint(th, tp, fp, precision, recall))
    return tuple(points)


def _threshold_above(value: float, next_value: float | None) -> float:
    """A threshold t with value < t <= next_value: the midpoint, or value + 1e-6 at the end."""
    if next_value is None:
        candidate = value + 1e-6
        # For large |f|, 1e-6 can vanish in rounding; step to the next float instead.
        return candidate if candidate > value else math.nextafter(value, math.inf)
    candidate = value + (next_value - value) / 2
    # Adjacent floats: the midpoint rounds onto an end; next_value itself still works (f < t).
    return candidate if value < candidate <= next_value else next_value


def _ratios(tp: int, fp: int, loop_events: int) -> tuple[float, float]:
    """(precision, recall); precision is 1.0 when nothing is reported, recall 0.0 without GT."""
    precision = tp / (tp + fp) if tp + fp else 1.0
    recall = tp / loop_events if loop_events else 0.0
    return precision, recall


def _best_at_full_precision(curve: Sequence[CurvePoint]) -> CurvePoint | None:
    """The point with the highest recall among those with FP = 0 and TP > 0."""
    clean = [p for p in curve if p.fp == 0 and p.tp > 0]
    # Recall never decreases along the curve, so the last clean point is the best.
    return clean[-1] if clean else None


def _recall_at_precision(curve: Sequence[CurvePoint], precision: float) -> float:
    return max((p.recall for p in curve if p.precision >= precision), default=0.0)


# -- run statistics -----------------------------------------------------------------------


def _frames_decided(decisions: Sequence[SequenceDecision]) -> int:
    """Frames covered by at least one decision (union of the [first, last] intervals)."""
    if not decisions:
        return 0
    first = np.array([d.first_index for d in decisions], dtype=np.int64)
    last = np.array([d.last_index for d in decisions], dtype=np.int64)
    order = np.argsort(first, kind="stable")
    first, last = first[order], last[order]
    reach = np.maximum.accumulate(last)
    # A new merged interval starts where a decision begins past everything seen so far.
    starts = np.flatnonzero(np.append(True, first[1:] > reach[:-1]))
    ends = np.maximum.reduceat(last, starts)
    return int(np.sum(np.maximum(ends - first[starts] + 1, 0)))


def _length_stats(decisions: Sequence[SequenceDecision]) -> LengthStats:
    if not decisions:
        return LengthStats(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0)
    lengths = np.array([d.length for d in decisions], dtype=np.int64)
    p10, p25, p75, p90 = (float(v) for v in np.percentile(lengths, _LENGTH_PERCENTILES))
    return LengthStats(
        min=int(lengths.min()),
        p10=p10,
        p25=p25,
        median=float(np.median(lengths)),
        mean=float(lengths.mean()),
        p75=p75,
        p90=p90,
        max=int(lengths.max()),
    )


# -- report -------------------------------------------------------------------------------


def format_report(evaluation: Evaluation) -> str:
    """A human-readable, multi-line report of `evaluation` (no trailing newline)."""
    e, s = evaluation, evaluation.lengths
    r_p100_th = "-" if e.threshold_at_r_p100 is None else f"{e.threshold_at_r_p100:.6g}"
    lines = [
        f"ground truth     : {e.gt_file} ({e.gt_frames} frames, {e.gt_loop_events} loop events"
        f"{', transposed from upper triangular' if e.gt_transposed else ''})",
        f"frames decided   : {e.frames}",
        f"sequences        : {e.sequences} (length min {s.min}, p10 {s.p10:g}, p25 {s.p25:g}, "
        f"median {s.median:g}, mean {s.mean:.2f}, p75 {s.p75:g}, p90 {s.p90:g}, max {s.max})",
        f"threshold th     : {e.threshold:g} (tolerance +-{e.tolerance} frames); "
        f"{e.accepted_sequences} sequences accepted",
        f"reported pairs   : {e.tp + e.fp} (TP {e.tp}, FP {e.fp})",
        f"precision        : {_percent(e.precision)}",
        f"recall           : {_percent(e.recall)} ({e.tp} of {e.gt_loop_events} loop events)",
        f"R@P100           : {_percent(e.r_p100)} at th = {r_p100_th}",
        f"recall at P>=0.9 : {_percent(e.recall_at_p90)}",
        *_coverage_lines(e),
    ]
    if e.frames != e.gt_frames:
        lines.append(
            f"note             : the run decided {e.frames} frames, the ground truth has "
            f"{e.gt_frames}; recall counts every loop event of the ground truth"
        )
    return "\n".join(lines)


def _coverage_cell(c: RevisitCoverage) -> str:
    return f"{_percent(c.share)} ({c.covered} of {c.windows})"


def _coverage_row(c: RevisitCoverage) -> str:
    return f"coverage {c.window_s:g} s"


def _coverage_lines(e: Evaluation) -> list[str]:
    """Revisit coverage at th, one line per window length (none without frame times)."""
    return [
        f"{_coverage_row(c):<17}: {_coverage_cell(c)} windows with a revisit" for c in e.coverage
    ]


def _column(e: Evaluation) -> list[str]:
    """The figures that differ between raw and verified, one cell per report line."""
    th = "-" if e.threshold_at_r_p100 is None else f"{e.threshold_at_r_p100:.6g}"
    return [
        f"{e.tp + e.fp} (TP {e.tp}, FP {e.fp})",
        _percent(e.precision),
        f"{_percent(e.recall)} ({e.tp} of {e.gt_loop_events})",
        f"{_percent(e.r_p100)} at th = {th}",
        _percent(e.recall_at_p90),
        *(_coverage_cell(c) for c in e.coverage),
    ]


_ROWS = ("reported pairs", "precision", "recall", "R@P100", "recall at P>=0.9")


def format_side_by_side(raw: Evaluation, verified: Evaluation | None, threshold_note: str) -> str:
    """Shared facts of a run, then its raw figures (every candidate) and, when it was verified,
    its verified ones (accepted pairs only) side by side (no trailing newline).

    `threshold_note` says where th came from ("recorded" for an annotated log).
    """
    s = raw.lengths
    lines = [
        f"ground truth     : {raw.gt_file} ({raw.gt_frames} frames, {raw.gt_loop_events} loop "
        f"events{', transposed from upper triangular' if raw.gt_transposed else ''})",
        f"frames decided   : {raw.frames}",
        f"sequences        : {raw.sequences} (length min {s.min}, median {s.median:g}, "
        f"mean {s.mean:.2f}, max {s.max})",
        f"threshold th     : {raw.threshold:g} ({threshold_note}; tolerance +-{raw.tolerance} "
        f"frames); {raw.accepted_sequences} sequences below it",
    ]
    columns = [_column(raw)] + ([_column(verified)] if verified is not None else [])
    width = max(len(cell) for cell in columns[0]) + 3
    if verified is not None:
        lines.append(f"{'':17}  {'raw (all candidates)':<{width}}verified (accepted pairs)")
    rows = _ROWS + tuple(_coverage_row(c) for c in raw.coverage)
    for row, cells in zip(rows, zip(*columns, strict=True), strict=True):
        lines.append(f"{row:<17}: " + "".join(f"{cell:<{width}}" for cell in cells).rstrip())
    return "\n".join(lines)


def _percent(value: float) -> str:
    return f"{100 * value:.2f} %"
