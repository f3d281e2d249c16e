"""High frame rates: the query stride, coarse-to-fine windows, offset tracking, threads.

The committed samples run at 2 Hz, where every candidate is checked exhaustively; with
query_interval_s = 2 s the same real frames run the stride path (s = 4).
"""

from __future__ import annotations

from collections import Counter
from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from detector_helpers import sequence_decision
from hypothesis import given, settings
from hypothesis import strategies as st

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.annotations.records import FrameTimes
from doseqslam_logs.detector import make_detector
from doseqslam_logs.detector.events import Alternative
from doseqslam_logs.evaluation.groundtruth import load_ground_truth
from doseqslam_logs.export.loops import loops_summary
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.pipeline.decode import FrameCounts, decoded_frames
from doseqslam_logs.pipeline.replay import replay
from doseqslam_logs.pipeline.reread import FolderFrameReader, LogFrameReader
from doseqslam_logs.sources import open_source, pick_image_topic
from doseqslam_logs.sources.camera_info import read_camera_info
from doseqslam_logs.sources.image_folder import list_images
from doseqslam_logs.verification import (
    DEFAULT_VERIFICATION,
    FrameFeatures,
    stage,
    verified_detector_parameters,
)
from doseqslam_logs.verification.geometry import Intrinsics, _ratio_matches
from doseqslam_logs.verification.stage import (
    VerificationStats,
    VerifiedDecision,
    query_stride,
    verify_in_threads,
)

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
LOOPS = SAMPLES / "drive_loops.ros2.mcap"
TOPIC = "/camera/image/compressed"
STRIDED = DEFAULT_VERIFICATION.replace(query_interval_s=2.0)  # 2 Hz sample: s = 4


def test_query_stride_follows_the_frame_rate() -> None:
    assert query_stride(sequence_decision(30, 100_000_000), 0.5) == 5  # 10 Hz
    assert query_stride(sequence_decision(30, 500_000_000), 0.5) == 1  # 2 Hz: every candidate
    assert query_stride(sequence_decision(30, 1_000_000_000), 0.5) == 1  # 1 Hz
    assert query_stride(sequence_decision(30, 33_333_333), 0.5) == 15  # 30 Hz
    assert query_stride(sequence_decision(30, 100_000_000), 0.0) == 1  # 0: always every candidate
    assert query_stride(sequence_decision(1, 100_000_000), 0.5) == 1  # one frame: no rate


@pytest.fixture(scope="module")
def strided_log(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("strided") / "loops.mcap"
    params = verified_detector_parameters()
    annotate_log(LOOPS, out, params, AnnotateOptions(verification=STRIDED, workers=2))
    return out


def test_one_candidate_in_s_is_checked_and_the_others_are_not_reported(strided_log) -> None:
    log = read_annotations(strided_log)
    by_sequence: dict[int, list[dict]] = {}
    for lc in log.loop_closures:
        by_sequence.setdefault(lc.sequence_id, []).append(lc)
    skipped = 0
    for pairs in by_sequence.values():
        pairs.sort(key=lambda lc: lc.query.index)
        for z, lc in enumerate(pairs):
            if z % 4:
                assert lc.verification == "skipped" and lc.inliers == -1
                assert lc.rejection_reason == "not checked"
                skipped += 1
            elif lc.verification == "skipped":  # after two hopeless checks of the sequence
                assert lc.rejection_reason == "sequence given up" and lc.inliers == -1
                skipped += 1
            else:
                assert lc.verification in ("accepted", "rejected") and lc.inliers >= 0
    assert skipped > 50
    assert all(lc.verification == "accepted" for lc in log.reported_loop_closures)
    assert len(log.reported_loop_closures) >= 10
    summary = loops_summary(log, len(log.reported_loop_closures), include_rejected=False)
    assert f"{skipped} not checked (high frame rate)" in summary


def test_strided_acceptances_are_true_places(strided_log) -> None:
    gt = load_ground_truth(SAMPLES / "drive_loops.gt.npz")
    reported = read_annotations(strided_log).reported_loop_closures
    q = np.array([lc.query.index for lc in reported])
    m = np.array([lc.matched.index for lc in reported])
    # Measured: 12 of 12 GT cells (2 m, 20 deg); 18 of 21 before bracketing and the rotation
    # limit, which also apply to the coarse-to-fine search.
    assert len(q) >= 10 and gt.are_true(q, m, 0).all()


@pytest.mark.slow
def test_strided_search_checks_far_fewer_pairs_than_the_exhaustive_one(tmp_path) -> None:
    """Exhaustive: up to 2r + 1 = 51 frames per checked candidate; coarse to fine with s = 4:
    at most 13 grid frames and the match, then 6 fine, and 5 while an offset is tracked."""
    params = verified_detector_parameters()
    results = {}
    for name, vparams in (("strided", STRIDED), ("exhaustive", DEFAULT_VERIFICATION)):
        options = AnnotateOptions(verification=vparams, sidecar=True, workers=1)
        results[name] = annotate_log(LOOPS, tmp_path / f"{name}.mcap", params, options)
    strided = results["strided"].verification
    exhaustive = results["exhaustive"].verification
    assert strided is not None and exhaustive is not None
    checked = strided.stats.candidates - strided.stats.skipped
    assert strided.stats.skipped > 0 and exhaustive.stats.skipped == 0
    assert strided.stats.pairs <= 20 * checked
    assert exhaustive.stats.pairs > 40 * exhaustive.stats.candidates
    assert strided.stats.pairs < exhaustive.stats.pairs / 8


def test_two_hopeless_checks_give_the_sequence_up() -> None:
    """Blank frames have no features: every check is hopeless. At 10 Hz (s = 5) the first two
    of the six checked candidates are rejected, the other four skipped as given up, unread."""
    read: list[int] = []

    def blank(indices):
        read.extend(indices)
        return ((i, np.zeros((48, 64), np.uint8)) for i in indices)

    [verified], stats = verify_in_threads(
        [sequence_decision(30, 100_000_000, 30)], lambda: nullcontext(blank), DEFAULT_VERIFICATION
    )
    reasons = [check.verdict.reason for check in verified.checks]
    assert reasons[0] == reasons[5] == "too few features"
    assert [reasons[z] for z in (10, 15, 20, 25)] == ["sequence given up"] * 4
    assert all(reasons[z] == "not checked" for z in range(30) if z % 5)
    assert stats.given_up == 4 and stats.skipped == 28 and stats.accepted == 0
    # Candidate 0 (match 10, window 0..35): the 2s grid 0, 10, 20, 30, hopeless, so no finer
    # step; candidate 5 (match 15): the tracked frame 15 alone, hopeless again: rejected.
    assert stats.pairs == 5
    assert {100, 105}.issubset(read) and not {110, 115, 120, 125} & set(read)
    at_2_hz, _ = verify_in_threads(  # stride 1: exhaustive, nothing is given up
        [sequence_decision(6, 500_000_000, 6)], lambda: nullcontext(blank), DEFAULT_VERIFICATION
    )
    assert all(check.verdict.reason == "too few features" for check in at_2_hz[0].checks)


def test_a_tracked_check_near_enough_is_not_searched_again(monkeypatch) -> None:
    """Every pair has 20 inliers: rejected (under 30), but not hopeless (15 or more). At 10 Hz
    (s = 5) the first checked candidate searches its window coarse to fine; each later one
    checks only where the previous offset puts it (the frame and the grid beside it) and keeps
    that verdict: a search of its window would cost 15 frame pairs for the same near miss."""
    checked: list[tuple[int, int]] = []

    def features(gray, params):  # the frame index, as a keypoint
        return FrameFeatures(np.array([[gray[0, 0], 0]], np.float32), gray[:1, :32], "orb", 1.0)

    def near_miss(query, match, params, intrinsics=None):
        checked.append((int(query.keypoints[0, 0]), int(match.keypoints[0, 0])))
        return stage.Verdict(False, 20, 40, "F", "too few inliers")

    monkeypatch.setattr(stage, "extract_features", features)
    monkeypatch.setattr(stage, "verify_pair", near_miss)

    def numbered(indices):
        return ((i, np.full((48, 64), i % 256, np.uint8)) for i in indices)

    decision = sequence_decision(30, 100_000_000, 30, first=200, match=100)
    [verified], stats = verify_in_threads(
        [decision], lambda: nullcontext(numbered), DEFAULT_VERIFICATION
    )
    checked_queries = [c for c in verified.checks if c.verdict.reason == "too few inliers"]
    assert len(checked_queries) == 6 and stats.given_up == 0 and stats.accepted == 0
    per_query = Counter(q for q, _ in checked)
    first_search = per_query.pop(200)
    # The first: the 2s grid over its window 75..125, the match among them (5), the s grid
    # within 2s - 1 of the best (2: 95, 105), then the best's frames 2 either side (98, 102;
    # ties go to the match, 100), then 1 (99, 101): 11 (every frame within s - 1 took 8, 15 in
    # all). The others: the frame at the previous offset (0), itself on the s grid: one each.
    assert first_search == 11
    assert sorted(m for q, m in checked if q == 200) == [
        *(80, 90, 95, 98, 99, 100, 101, 102, 105, 110, 120)
    ]
    assert per_query == {205: 1, 210: 1, 215: 1, 220: 1, 225: 1}
    assert stats.pairs == first_search + 5


def test_alternatives_are_tried_in_order_and_given_up_after_two_hopeless_checks() -> None:
    """Blank frames: every check is hopeless. At 2 Hz (s = 1) each of the 4 candidates checks
    its own window; alternative 1 (matches 60, 61, ...) is checked for the first two only, then
    given up; alternative 2 (matches 0, 1, ...) likewise. Window frames seen once per query."""
    read: list[int] = []

    def blank(indices):
        read.extend(indices)
        return ((i, np.zeros((48, 64), np.uint8)) for i in indices)

    base = sequence_decision(4, 500_000_000, 4)  # matches 10..13, database 0..89
    alternatives = (
        Alternative(60, 1.0, 1.5, tuple(range(60, 64))),
        Alternative(0, 1.0, 1.6, tuple(range(0, 4))),
    )
    params = DEFAULT_VERIFICATION.replace(refine_radius=2)
    [verified], stats = verify_in_threads(
        [replace(base, alternatives=alternatives)], lambda: nullcontext(blank), params
    )
    assert [check.proposal for check in verified.checks] == [0, 0, 0, 0]
    assert not any(check.accepted for check in verified.checks)
    # Own windows: 5 frames each (8..12, 9..13, ...); alternative 1: 58..62 and 59..63 (q0, q1);
    # alternative 2: 0..2 and 0..3 (q0, q1, clipped at the database start); q2, q3: none.
    assert stats.pairs == 4 * 5 + 2 * 5 + (3 + 4)
    assert not {64, 65} & set(read)  # alternative 1's frames for q2, q3 were never read
    [plain], plain_stats = verify_in_threads([base], lambda: nullcontext(blank), params)
    assert plain_stats.pairs == 4 * 5 and plain.checks == verified.checks


def test_threads_give_the_same_checks(shared_data) -> None:
    """The decisions of RTAB-Map verified on 1 and 3 threads: the same checks, in order."""
    images = list_images(shared_data / "rtabmap_samples_loop" / "images")
    sequences = [
        sequence_decision(3, 1_000_000_000, 3, first=60 + 5 * k, sequence_id=k) for k in range(4)
    ]

    reader = FolderFrameReader(images)
    params = DEFAULT_VERIFICATION.replace(refine_radius=3)
    lone, lone_stats = verify_in_threads(sequences, lambda: nullcontext(reader), params)
    threaded, threaded_stats = verify_in_threads(
        sequences, lambda: nullcontext(reader), params, workers=3
    )
    assert [v.decision.sequence_id for v in threaded] == [0, 1, 2, 3]
    assert lone == threaded
    assert lone_stats.pairs == threaded_stats.pairs == 4 * 3 * 7


def test_a_failing_thread_stops_the_others() -> None:
    def broken(indices):
        raise LookupError("frames gone")
        yield  # pragma: no cover

    with pytest.raises(LookupError, match="frames gone"):
        verify_in_threads(
            [sequence_decision(3, 10**9, 3)] * 6,
            lambda: nullcontext(broken),
            DEFAULT_VERIFICATION,
            workers=2,
        )


def knn_reference(query: FrameFeatures, match: FrameFeatures, ratio: float):
    """The BFMatcher.knnMatch formulation the vectorized ratio test replaced."""
    best: dict[int, tuple[float, int]] = {}
    for pair in cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(query.descriptors, match.descriptors, 2):
        if len(pair) == 2 and pair[0].distance < ratio * pair[1].distance:
            kept = best.get(pair[0].trainIdx)
            if kept is None or pair[0].distance < kept[0]:
                best[pair[0].trainIdx] = (pair[0].distance, pair[0].queryIdx)
    m_index = np.array(sorted(best), dtype=np.int64)
    return np.array([best[int(m)][1] for m in m_index], dtype=np.int64), m_index


def orb_features(descriptors: np.ndarray) -> FrameFeatures:
    points = np.zeros((len(descriptors), 2), np.float32)
    return FrameFeatures(points, descriptors, "orb", 1.0)


@settings(max_examples=200, deadline=None)
@given(
    st.integers(0, 40),
    st.integers(0, 40),
    st.integers(1, 6),  # palette size: few distinct descriptors make many distance ties
    st.floats(0.3, 1.0),
    st.integers(0, 2**32 - 1),
)
def test_ratio_matches_equal_knn_match(n_query, n_match, palette, ratio, seed) -> None:
    rng = np.random.default_rng(seed)
    colours = rng.integers(0, 256, (palette, 32), dtype=np.uint8)
    query = colours[rng.integers(0, palette, n_query)] ^ rng.integers(0, 2, (n_query, 32)).astype(
        np.uint8
    )
    match = colours[rng.integers(0, palette, n_match)]
    a, b = orb_features(query), orb_features(match)
    expected = knn_reference(a, b, ratio)
    got = _ratio_matches(a, b, ratio)
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])


def sample_frames() -> tuple[FrameTimes, list[np.ndarray]]:
    """Every frame of the sample, decoded on one pass, with its times (as annotate records)."""
    with open_source(LOOPS) as source:
        topic = pick_image_topic(source, None)
        frames = list(decoded_frames(source.image_messages(topic), FrameCounts()))
    times = FrameTimes.from_pairs([(f.log_time_ns, f.header_stamp_ns) for f in frames])
    return times, [f.image for f in frames]


def test_the_frame_reader_reads_around_and_gives_the_same_frames() -> None:
    times, images = sample_frames()
    wanted = [200, 5, 6, 120, 7, 201, 30, 199, 8, 121]
    with LogFrameReader(LOOPS, TOPIC, times) as reader:
        for index in wanted:  # one frame at a time, as the stage asks at high frame rates
            [(got, gray)] = list(reader([index]))
            assert got == index and np.array_equal(gray, images[index])
        assert reader.reads == 3  # around 200, 5 and 120 (+-32 frames): the others were kept
    with LogFrameReader(LOOPS, TOPIC, times, cache_bytes=1) as tiny:  # keeps one message
        assert [i for i, _ in tiny([5, 6, 7])] == [5, 6, 7]
        list(tiny([6]))
        assert tiny.reads == 2


def test_ranged_reads_do_not_parse_the_summary_again(monkeypatch) -> None:
    import mcap.reader

    parsed = []
    original = mcap.reader._read_summary_from_stream_reader
    monkeypatch.setattr(
        mcap.reader,
        "_read_summary_from_stream_reader",
        lambda stream: parsed.append(1) or original(stream),
    )
    with open_source(LOOPS) as source:
        opened = len(parsed)  # the source reads it once, on opening
        for start in range(0, 100, 10):
            t0 = 1_700_000_000_000_000_000 + start * 500_000_000
            assert len(list(source.image_messages(TOPIC, t0, t0 + 10**9))) == 2
    assert opened == 1 and len(parsed) == 1


def test_pictures_draw_skipped_pairs_apart_from_rejected_ones(strided_log) -> None:
    plots = pytest.importorskip("doseqslam_logs.evaluation.plots")
    from doseqslam_logs.evaluation.log_run import detections

    log = read_annotations(strided_log)
    gt = load_ground_truth(SAMPLES / "drive_loops.gt.npz")
    statuses = Counter(d.status for d in detections(plots, log, gt, 0))
    verdicts = Counter(lc.verification for lc in log.loop_closures)
    assert statuses["skipped"] == verdicts["skipped"] > 0
    assert statuses["rejected"] == verdicts["rejected"]
    assert statuses["tp"] + statuses["fp"] == verdicts["accepted"]
    assert list(plots._by_status(detections(plots, log, gt, 0)))[:2] == ["skipped", "rejected"]
    assert plots.LABELS["skipped"] == "not checked (high frame rate)"


def test_a_sequence_looks_first_where_the_one_before_was_verified(monkeypatch) -> None:
    """At a high frame rate each sequence first checks where the previous one's last accepted
    pair puts it (proposal -1, `Hint`): the same true places for fewer frame pairs than with
    every sequence on its own (chains of one decision), and the same checks on 1 and 2
    threads (the chains are fixed)."""
    params = verified_detector_parameters()
    with open_source(LOOPS) as source:
        frames = list(decoded_frames(source.image_messages(TOPIC), FrameCounts()))
    decisions = replay(frames, make_detector(params)).decisions
    times = FrameTimes.from_pairs((f.log_time_ns, f.header_stamp_ns) for f in frames)
    info = read_camera_info(LOOPS, TOPIC)
    assert info is not None
    k = Intrinsics(info.fx, info.fy, info.cx, info.cy)

    def run(workers: int) -> tuple[list[VerifiedDecision], VerificationStats]:
        return verify_in_threads(
            decisions, lambda: LogFrameReader(LOOPS, TOPIC, times), STRIDED, k, workers
        )

    chained, chained_stats = run(1)
    assert run(2)[0] == chained
    monkeypatch.setattr(stage, "CHAIN_DECISIONS", 1)
    alone, alone_stats = run(1)
    continued = [c for v in chained for c in v.checks if c.accepted and c.proposal == -1]
    assert continued and chained_stats.continued == len(continued)
    assert all(c.continued_match >= 0 for c in continued)
    gt = load_ground_truth(SAMPLES / "drive_loops.gt.npz")
    for verified in (chained, alone):
        accepted = [c for v in verified for c in v.checks if c.accepted]
        q = np.array([c.candidate.query_index for c in accepted])
        m = np.array([c.refined_match_index for c in accepted])
        assert gt.are_true(q, m, 0).all()
    assert chained_stats.accepted >= alone_stats.accepted
    assert chained_stats.pairs < alone_stats.pairs
