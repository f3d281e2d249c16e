"""Evaluation against ground truth: hand-computed cases and the sweep checked by brute force."""

from __future__ import annotations

import itertools
import json
from collections.abc import Sequence
from dataclasses import astuple
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from doseqslam_logs.detector.events import Candidate, SequenceDecision
from doseqslam_logs.errors import GroundTruthError, UsageError
from doseqslam_logs.evaluation.groundtruth import GroundTruth, load_ground_truth
from doseqslam_logs.evaluation.metrics import CurvePoint, evaluate, format_report

Pair = tuple[int, int]


def decision(
    f: float,
    pairs: Sequence[Pair] = (),
    *,
    frames: tuple[int, int] | None = None,
    sequence_id: int = 0,
    threshold: float = 0.75,
) -> SequenceDecision:
    """A SequenceDecision with the given f and (query, match) pairs; frames default to the
    span of the query indices."""
    if frames is None:
        queries = [q for q, _ in pairs] or [0]
        frames = (min(queries), max(queries))
    candidates = tuple(Candidate(q, m, q * 1_000_000_000, m * 1_000_000_000, 0.5) for q, m in pairs)
    return SequenceDecision(
        sequence_id=sequence_id,
        first_index=frames[0],
        last_index=frames[1],
        first_timestamp_ns=frames[0] * 1_000_000_000,
        last_timestamp_ns=frames[1] * 1_000_000_000,
        database_size=max(0, frames[0] - 2),
        best_start=pairs[0][1] if pairs else None,
        best_velocity=1.0 if pairs else None,
        best_score=f if pairs else None,
        second_score=1.0 if pairs else None,
        gamma=f,
        gamma_previous=None,
        gamma_next=None,
        f=f,
        threshold=threshold,
        accepted=bool(pairs) and f < threshold,
        candidates=candidates,
        method="doseqslam",
    )


# GT: five query frames (5..9) with one earlier match each.
GT_PAIRS = [(5, 1), (6, 2), (7, 3), (8, 0), (9, 4)]


@pytest.fixture
def gt() -> GroundTruth:
    return GroundTruth.from_pairs(10, GT_PAIRS, source="/somewhere/hand.npy")


@pytest.fixture
def run() -> list[SequenceDecision]:
    return [
        decision(0.9, frames=(0, 2), sequence_id=0),  # empty database: no candidate
        decision(0.8, [(3, 0), (4, 1)], sequence_id=1),  # FP, FP
        decision(0.2, [(5, 1), (6, 2)], sequence_id=2),  # TP, TP
        decision(0.4, [(7, 3), (8, 1)], sequence_id=3),  # TP, FP (GT is (8, 0))
        decision(0.6, [(9, 4)], sequence_id=4),  # TP
    ]


# -- hand-computed --------------------------------------------------------------------------


def test_counts_at_a_threshold(run: list[SequenceDecision], gt: GroundTruth) -> None:
    e = evaluate(run, gt, threshold=0.5)
    assert (e.tp, e.fp, e.accepted_sequences) == (3, 1, 2)
    assert e.precision == pytest.approx(0.75)
    assert e.recall == pytest.approx(0.6)
    assert (e.frames, e.sequences, e.gt_loop_events, e.gt_frames) == (10, 5, 5, 10)
    assert e.gt_file == "hand.npy"


def test_full_curve(run: list[SequenceDecision], gt: GroundTruth) -> None:
    e = evaluate(run, gt, threshold=0.75)
    expected = [
        CurvePoint(0.3, 2, 0, 1.0, 0.4),
        CurvePoint(0.5, 3, 1, 0.75, 0.6),
        CurvePoint(0.7, 4, 1, 0.8, 0.8),
        CurvePoint(0.8 + 1e-6, 4, 3, 4 / 7, 0.8),
    ]
    assert [astuple(p) for p in e.curve] == [pytest.approx(astuple(p)) for p in expected]


def test_r_p100_and_its_threshold(run: list[SequenceDecision], gt: GroundTruth) -> None:
    e = evaluate(run, gt, threshold=0.75)
    assert e.r_p100 == pytest.approx(0.4)
    assert e.threshold_at_r_p100 is not None
    assert e.threshold_at_r_p100 == pytest.approx(0.3)
    again = evaluate(run, gt, threshold=e.threshold_at_r_p100)
    assert (again.tp, again.fp, again.recall) == (2, 0, e.r_p100)
    assert e.recall_at_p90 == pytest.approx(0.4)
    assert e.recall_at_precision(0.75) == pytest.approx(0.8)
    assert e.recall_at_precision(0.0) == pytest.approx(0.8)


def test_every_curve_point_is_reproduced_by_its_threshold(
    run: list[SequenceDecision], gt: GroundTruth
) -> None:
    for point in evaluate(run, gt, threshold=0.75).curve:
        e = evaluate(run, gt, threshold=point.threshold)
        assert (e.tp, e.fp, e.precision, e.recall) == (
            point.tp,
            point.fp,
            point.precision,
            point.recall,
        )


def test_tolerance_turns_a_false_positive_into_a_true_one(
    run: list[SequenceDecision], gt: GroundTruth
) -> None:
    e = evaluate(run, gt, threshold=0.5, tolerance=1)
    assert (e.tp, e.fp, e.precision, e.recall) == (4, 0, 1.0, 0.8)
    assert e.r_p100 == pytest.approx(1.0)
    assert e.threshold_at_r_p100 == pytest.approx(0.7)
    assert e.tolerance == 1


def test_threshold_is_strict(run: list[SequenceDecision], gt: GroundTruth) -> None:
    e = evaluate(run, gt, threshold=0.2)  # f < th: the f = 0.2 decision is not in
    assert (e.tp, e.fp, e.precision, e.recall) == (0, 0, 1.0, 0.0)


def test_equal_f_values_enter_together(gt: GroundTruth) -> None:
    run = [
        decision(0.4, [(5, 1)], sequence_id=0),  # TP
        decision(0.4, [(6, 0)], sequence_id=1),  # FP
        decision(0.7, [(7, 3)], sequence_id=2),  # TP
    ]
    e = evaluate(run, gt, threshold=0.75)
    assert [(p.tp, p.fp) for p in e.curve] == [(1, 1), (2, 1)]
    assert e.r_p100 == 0.0 and e.threshold_at_r_p100 is None  # no clean point exists


def test_a_query_frame_counts_once_for_its_most_confident_decision(gt: GroundTruth) -> None:
    run = [
        decision(0.5, [(5, 0)], sequence_id=0),  # FP, less confident
        decision(0.3, [(5, 1)], sequence_id=1),  # TP for the same query frame
    ]
    e = evaluate(run, gt, threshold=0.75)
    assert (e.tp, e.fp) == (1, 0)
    assert [(p.tp, p.fp) for p in e.curve] == [(1, 0), (1, 0)]


def test_out_of_range_index_is_an_error(gt: GroundTruth) -> None:
    with pytest.raises(GroundTruthError, match="ground truth has 10 frames but the run has 12"):
        evaluate([decision(0.1, [(11, 2)])], gt, threshold=0.5)
    with pytest.raises(GroundTruthError, match="ground truth has 10 frames but the run has 11"):
        evaluate([decision(0.9, [(5, 10)])], gt, threshold=0.5)  # even when not reported
    with pytest.raises(GroundTruthError, match="ground truth has 10 frames but the run has 15"):
        evaluate([decision(0.9, frames=(10, 14))], gt, threshold=0.5)  # no candidates at all


def test_bad_arguments(run: list[SequenceDecision], gt: GroundTruth) -> None:
    with pytest.raises(UsageError, match="tolerance"):
        evaluate(run, gt, threshold=0.5, tolerance=-1)
    with pytest.raises(UsageError, match="NaN"):
        evaluate(run, gt, threshold=float("nan"))


def test_non_finite_f_is_never_reported(gt: GroundTruth) -> None:
    run = [decision(float("nan"), [(5, 1)]), decision(float("-inf"), [(6, 2)], sequence_id=1)]
    e = evaluate(run, gt, threshold=1.0)
    assert (e.tp, e.fp, e.curve) == (0, 0, ())


def test_empty_run(gt: GroundTruth) -> None:
    e = evaluate([], gt, threshold=0.75)
    assert (e.tp, e.fp, e.precision, e.recall, e.r_p100, e.frames) == (0, 0, 1.0, 0.0, 0.0, 0)
    assert e.curve == () and e.threshold_at_r_p100 is None
    assert "R@P100" in format_report(e)


def test_length_distribution_and_frames() -> None:
    gt = GroundTruth.from_pairs(100, [(50, 1)])
    run = [
        decision(0.9, frames=(0, 9)),
        decision(0.9, frames=(10, 10)),
        decision(0.9, frames=(11, 40)),
        decision(0.9, frames=(45, 49)),  # frames 41..44 are not decided
    ]
    e = evaluate(run, gt, threshold=0.75)
    assert e.frames == 46
    s = e.lengths
    assert (s.min, s.median, s.max) == (1, 7.5, 30)
    assert s.mean == pytest.approx(11.5)
    assert s.p10 <= s.p25 <= s.median <= s.p75 <= s.p90


def test_json_dict_is_plain_json(run: list[SequenceDecision], gt: GroundTruth) -> None:
    data = evaluate(run, gt, threshold=0.5).to_json_dict()
    assert json.loads(json.dumps(data, allow_nan=False)) == data
    assert data["tp"] == 3 and data["gt_file"] == "hand.npy"
    assert data["lengths"]["max"] == 3
    assert data["curve"][0] == {
        "threshold": pytest.approx(0.3),
        "tp": 2,
        "fp": 0,
        "precision": 1.0,
        "recall": 0.4,
    }


def test_report_names_the_figures(run: list[SequenceDecision], gt: GroundTruth) -> None:
    report = format_report(evaluate(run, gt, threshold=0.5))
    for text in (
        "hand.npy (10 frames, 5 loop events",
        "frames decided   : 10",
        "sequences        : 5 (length min 1",
        "TP 3, FP 1",
        "precision        : 75.00 %",
        "recall           : 60.00 % (3 of 5 loop events)",
        "R@P100           : 40.00 % at th = 0.3",
        "recall at P>=0.9 : 40.00 %",
    ):
        assert text in report


def test_report_warns_when_the_run_is_shorter_than_the_ground_truth(gt: GroundTruth) -> None:
    report = format_report(evaluate([decision(0.3, [(5, 1)])], gt, threshold=0.5))
    assert "the run decided 1 frames, the ground truth has 10" in report


def test_real_ground_truth_perfect_and_shifted_runs(shared_data: Path) -> None:
    gt = load_ground_truth(shared_data / "lip6_outdoor/ground_truth/Lip6OutdoorGroundTruth.mat")
    rows = gt.query_rows()
    first_match = gt.matrix.indices[gt.matrix.indptr[rows]]
    pairs = list(zip(rows.tolist(), first_match.tolist(), strict=True))
    # One decision per 10 query frames; from the 31st on (higher f) each frame is matched with
    # itself, which a strictly lower triangular GT never marks.
    run = [
        decision(0.01 * k, [(q, m if k < 30 else q) for q, m in pairs[i : i + 10]])
        for k, i in enumerate(range(0, len(pairs), 10))
    ]
    e = evaluate(run, gt, threshold=10.0)
    assert e.r_p100 == pytest.approx(300 / 603)
    assert e.tp == 300 and e.fp == len(pairs) - 300
    assert e.gt_file == "Lip6OutdoorGroundTruth.mat"


# -- properties -----------------------------------------------------------------------------

F_VALUES = st.sampled_from([0.1, 0.2, 0.3, 0.35, 0.5, 0.7, 0.9])


@st.composite
def scenarios(draw: st.DrawFn) -> tuple[GroundTruth, list[SequenceDecision], int]:
    n = draw(st.integers(2, 20))
    index = st.integers(0, n - 1)
    cells = draw(st.lists(st.tuples(index, index), max_size=30))
    # Query frames may repeat across decisions, to exercise the count-once rule.
    runs = draw(st.lists(st.tuples(F_VALUES, st.lists(st.tuples(index, index), max_size=4))))
    decisions = [decision(f, pairs, sequence_id=k) for k, (f, pairs) in enumerate(runs)]
    return GroundTruth.from_pairs(n, cells), decisions, draw(st.integers(0, 3))


def naive_counts(
    decisions: Sequence[SequenceDecision], gt: GroundTruth, threshold: float, tolerance: int
) -> tuple[int, int]:
    """Recount from scratch: decisions with f < th in (f, run order); first claim on a query."""
    dense = gt.matrix.toarray()
    entered = sorted(
        (d for d in decisions if d.f < threshold and d.candidates), key=lambda d: d.f
    )  # sorted() is stable: equal f keep run order
    seen: set[int] = set()
    tp = fp = 0
    for d in entered:
        for c in d.candidates:
            if c.query_index in seen:
                continue
            seen.add(c.query_index)
            low = max(0, c.match_index - tolerance)
            if dense[c.query_index, low : c.match_index + tolerance + 1].any():
                tp += 1
            else:
                fp += 1
    return tp, fp


@settings(max_examples=150, deadline=None)
@given(scenarios(), st.floats(0.0, 1.0))
def test_sweep_equals_a_naive_recount(
    scenario: tuple[GroundTruth, list[SequenceDecision], int], threshold: float
) -> None:
    gt, decisions, tolerance = scenario
    e = evaluate(decisions, gt, threshold, tolerance)
    assert (e.tp, e.fp) == naive_counts(decisions, gt, threshold, tolerance)
    distinct = sorted({d.f for d in decisions if d.candidates})
    assert len(e.curve) == len(distinct)
    for f, point in zip(distinct, e.curve, strict=True):
        assert f < point.threshold
        assert (point.tp, point.fp) == naive_counts(decisions, gt, f + 1e-9, tolerance)


@settings(max_examples=150, deadline=None)
@given(scenarios(), st.floats(0.0, 1.0))
def test_ratios_stay_in_range_and_recall_never_decreases(
    scenario: tuple[GroundTruth, list[SequenceDecision], int], threshold: float
) -> None:
    gt, decisions, tolerance = scenario
    e = evaluate(decisions, gt, threshold, tolerance)
    assert 0.0 <= e.precision <= 1.0 and 0.0 <= e.recall <= 1.0
    assert 0.0 <= e.r_p100 <= 1.0 and 0.0 <= e.recall_at_p90 <= 1.0
    recalls = [p.recall for p in e.curve]
    assert all(0.0 <= p.precision <= 1.0 and 0.0 <= p.recall <= 1.0 for p in e.curve)
    assert recalls == sorted(recalls)
    assert [p.threshold for p in e.curve] == sorted(p.threshold for p in e.curve)
    clean = [p.recall for p in e.curve if p.fp == 0 and p.tp > 0]
    assert e.r_p100 == max(clean, default=0.0)
    if e.threshold_at_r_p100 is not None:
        again = evaluate(decisions, gt, e.threshold_at_r_p100, tolerance)
        assert (again.fp, again.recall) == (0, e.r_p100)


# -- revisit coverage ---------------------------------------------------------------------


def test_revisit_coverage_counts_windows_with_a_revisit_and_a_true_pair() -> None:
    """Frames at 10 Hz: revisits at frames 20-39 (0.2 s apart from 2.0 s to 3.9 s) and 60-61;
    true pairs reported at frames 20 and 35, a false one at frame 61, one above th at 60."""
    gt = GroundTruth.from_pairs(70, [(q, q - 20) for q in [*range(20, 40), 60, 61]])
    times = [i * 100_000_000 for i in range(70)]
    decisions = [
        decision(0.3, [(20, 0), (35, 15)], sequence_id=0),
        decision(0.4, [(61, 0)], sequence_id=1),  # a false pair: no coverage
        decision(0.9, [(60, 40)], sequence_id=2),  # true, but above th
    ]
    result = evaluate(decisions, gt, 0.75, frame_times_ns=times)
    one, five = result.coverage
    # 1-s windows with a revisit: [2, 3) [3, 4) [6, 7); covered: [2, 3) and [3, 4).
    assert (one.window_s, one.windows, one.covered) == (1.0, 3, 2)
    # 5-s windows: [0, 5) and [5, 10) hold revisits; only the first has a true pair.
    assert (five.windows, five.covered) == (2, 1) and five.share == 0.5
    assert "coverage 1 s     : 66.67 % (2 of 3) windows with a revisit" in format_report(result)
    assert result.to_json_dict()["coverage"][0] == {
        "window_s": 1.0,
        "windows": 3,
        "covered": 2,
        "share": 2 / 3,
    }
    assert evaluate(decisions, gt, 0.95, frame_times_ns=times).coverage[0].covered == 3
    assert evaluate(decisions, gt, 0.75).coverage == ()  # no times, no coverage


@settings(max_examples=40, deadline=None)
@given(
    revisits=st.sets(st.integers(0, 59), min_size=1),
    found=st.sets(st.integers(0, 59)),
    gaps=st.lists(st.integers(1, 700_000_000), min_size=60, max_size=60),
)
def test_coverage_is_never_above_one_and_is_one_when_every_revisit_is_found(
    revisits: set[int], found: set[int], gaps: list[int]
) -> None:
    gt = GroundTruth.from_pairs(61, [(q + 1, 0) for q in revisits])
    times = [0, *itertools.accumulate(gaps)]
    pairs = [(q + 1, 0) for q in sorted(found)]
    for coverage in evaluate([decision(0.1, pairs)], gt, 0.75, frame_times_ns=times).coverage:
        assert 0 <= coverage.covered <= coverage.windows <= len(revisits)
    every = [(q + 1, 0) for q in sorted(revisits)]
    for coverage in evaluate([decision(0.1, every)], gt, 0.75, frame_times_ns=times).coverage:
        assert coverage.covered == coverage.windows
