"""Each detector stage against small cases computed by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from doseqslam_logs.detector.association import greedy_matches, trajectory_matches
from doseqslam_logs.detector.difference import FrameStore, sad_rows
from doseqslam_logs.detector.doseqslam import weighted_decision
from doseqslam_logs.detector.enhance import enhance
from doseqslam_logs.detector.preprocess import frame_vector, patch_normalize
from doseqslam_logs.detector.trajectory import (
    distinct_velocities,
    next_best_starts,
    normalize,
    offsets,
    trajectory_scores,
)

VELOCITIES = (0.7, 0.8, 0.9, 1.0, 1.1, 1.2, 1.3)


def test_patch_normalization_by_hand() -> None:
    image = np.array([[1, 2, 5, 5], [3, 4, 5, 5]], np.float32)
    out = patch_normalize(image, 2)
    s = math.sqrt(1.25)  # population std of 1, 2, 3, 4
    expected = [[-1.5 / s, -0.5 / s, 0, 0], [0.5 / s, 1.5 / s, 0, 0]]
    np.testing.assert_allclose(out, expected, atol=1e-6)


def test_frame_vector_is_chi_long_and_patch_normalized() -> None:
    gray = np.random.default_rng(1).integers(0, 256, (192, 240), dtype=np.uint8)
    vec = frame_vector(gray, 64, 32, 8)
    assert vec.shape == (2048,) and vec.dtype == np.float32
    patches = vec.reshape(4, 8, 8, 8)
    np.testing.assert_allclose(patches.mean(axis=(1, 3)), 0, atol=1e-5)
    np.testing.assert_allclose(patches.std(axis=(1, 3)), 1, atol=1e-4)


def test_flat_frame_gives_zero_vector() -> None:
    assert not frame_vector(np.full((40, 80), 77, np.uint8), 64, 32, 8).any()


def test_sad_by_hand_and_across_blocks() -> None:
    store = FrameStore(4, block_frames=2)  # three blocks for five vectors
    for v in ([0, 0, 0, 0], [1, 2, 3, 4], [1, 1, 1, 1], [2, 2, 2, 2], [-1, 1, -1, 1]):
        store.append(np.array(v, np.float32))
    rows = sad_rows(np.array([[1, 1, 1, 1]], np.float32), store, 5)
    np.testing.assert_allclose(rows, [[1.0, 1.5, 0.0, 1.0, 1.0]])
    assert sad_rows(np.zeros((2, 4), np.float32), store, 3).shape == (2, 3)


def test_enhancement_by_hand() -> None:
    # epsilon = 2: window j-1 .. j+1, clipped; constant offset sqrt(2).
    out = enhance(np.array([[0, 0, 0, 10, 0, 0, 0]], np.float32), 2)
    r2 = math.sqrt(2)
    expected = [r2, r2, r2 - 1 / r2 * 1.0, r2 + r2, r2 - 1 / r2 * 1.0, r2, r2]
    np.testing.assert_allclose(out[0], expected, atol=1e-5)


@settings(max_examples=60, deadline=None)
@given(
    arrays(
        np.float32,
        st.tuples(st.integers(1, 4), st.integers(1, 40)),
        elements=st.floats(0, 4, width=32),
    ),
    st.sampled_from([2, 4, 10]),
)
def test_enhancement_is_non_negative_and_matches_a_naive_window(rows, epsilon) -> None:
    out = enhance(rows, epsilon)
    assert (out >= -1e-5).all()
    half = epsilon // 2
    for r in range(rows.shape[0]):
        for j in range(rows.shape[1]):
            window = rows[r, max(j - half, 0) : j + half + 1].astype(np.float64)
            std = window.std()
            z = 0.0 if std < 1e-9 else (rows[r, j] - window.mean()) / std
            assert out[r, j] == pytest.approx(z + math.sqrt(epsilon), abs=2e-3)


def test_offsets_round_halves_up() -> None:
    assert offsets(0.7, 6).tolist() == [0, 1, 1, 2, 3, 4]  # 0.7 * 5 = 3.5 -> 4
    assert offsets(1.3, 3).tolist() == [0, 1, 3]


def test_velocity_deduplication() -> None:
    assert [v for v, _ in distinct_velocities(VELOCITIES, 1)] == [1.0]
    assert [v for v, _ in distinct_velocities(VELOCITIES, 2)] == [1.0]
    groups = distinct_velocities(VELOCITIES, 3)
    assert [(v, o.tolist()) for v, o in groups] == [
        (1.0, [0, 1, 2]),
        (0.7, [0, 1, 1]),
        (1.3, [0, 1, 3]),
    ]


def test_trajectory_scores_by_hand() -> None:
    enhanced = np.array([[1, 5, 5, 5], [5, 2, 5, 5]], np.float32)
    scores = trajectory_scores(enhanced, (1.0,))
    np.testing.assert_allclose(scores.scores, [1.5, 5.0, 5.0, np.inf])


def test_trajectory_scores_pick_the_best_velocity_per_start() -> None:
    # The diagonal with slope 1.3 (offsets 0, 1, 3) is the only low path from j = 0.
    enhanced = np.full((3, 8), 9.0, np.float32)
    enhanced[0, 0] = enhanced[1, 1] = enhanced[2, 3] = 0.0
    scores = trajectory_scores(enhanced, VELOCITIES)
    assert scores.scores[0] == 0.0
    assert scores.best_velocity(0) == 1.3
    # From j = 6 only v = 0.7 (offsets 0, 1, 1) stays inside; from j = 7 nothing does.
    assert scores.scores[6] == 9.0 and scores.best_velocity(6) == 0.7
    assert np.isinf(scores.scores[7])


def test_normalization_and_exclusion_window() -> None:
    scores = np.array([4, 1, 1.5, 3, 2, np.inf], np.float32)
    norm = normalize(scores, before=1, after=1)  # excludes j = 0 .. 2
    assert norm is not None
    assert (norm.best_start, norm.best_score, norm.second_score) == (1, 1.0, 2.0)
    assert norm.gamma == pytest.approx(0.5)
    wide = normalize(scores, before=1, after=3)  # nothing finite outside
    assert wide is not None and wide.second_score is None and wide.gamma == 1.0
    assert normalize(np.full(3, np.inf, np.float32), 0, 0) is None


def test_weighted_decision_and_its_renormalized_ends() -> None:
    assert weighted_decision(0.5, 0.2, 0.8) == pytest.approx((0.5 + 0.8 + 0.8) / 6)
    assert weighted_decision(0.5, 0.2, None) == pytest.approx((0.5 + 0.8) / 5)
    assert weighted_decision(None, 0.2, 0.8) == pytest.approx((0.8 + 0.8) / 5)
    assert weighted_decision(None, 0.2, None) == pytest.approx(0.2)


def test_greedy_association_by_hand() -> None:
    enhanced = np.array([[9, 3, 1, 4, 5, 0], [9, 2, 8, 8, 0.5, 0]], np.float32)
    # length 2, v_max 1.3: columns j* = 1 .. 1 + round(2.6) = 4; column 5 is outside.
    assert greedy_matches(enhanced, 1, 1.3).tolist() == [2, 4]


def test_trajectory_association_follows_the_best_velocity() -> None:
    enhanced = np.full((3, 10), 9.0, np.float32)
    enhanced[0, 3] = enhanced[1, 4] = enhanced[2, 6] = 0.0
    scores = trajectory_scores(enhanced, VELOCITIES)
    assert trajectory_matches(scores, 3).tolist() == [3, 4, 6]


def test_next_best_starts_by_hand() -> None:
    scores = np.array([5, 1, 2, 9, 3, 0.5, 4, np.inf], np.float32)
    # Best 5 (0.5) rules out 4 and 6; then 1 (1.0) rules out 0 and 2; 3 (9.0) is all that is left.
    assert next_best_starts(scores, 5, 3, 1) == [1, 3]
    assert next_best_starts(scores, 5, 1, 1) == [1]
    assert next_best_starts(scores, 5, 9, 1) == [1, 3]  # 7 never fits (+inf)
    assert next_best_starts(scores, 1, 3, 3) == [5]  # 0..4 near 1, then 2..8 near 5
    assert next_best_starts(scores, 5, 0, 1) == []
    assert next_best_starts(scores, 5, 2, 10) == []  # everything lies within 10 of the best


@settings(max_examples=200, deadline=None)
@given(
    arrays(np.float32, st.integers(1, 60), elements=st.floats(0, 10, width=32)),
    st.integers(0, 6),
    st.integers(1, 8),
)
def test_next_best_starts_are_separated_and_each_the_lowest_left(scores, count, separation):
    best = int(np.argmin(scores))
    starts = next_best_starts(scores, best, count, separation)
    assert len(starts) <= count
    chosen = [best]
    for start in starts:
        allowed = [j for j in range(len(scores)) if all(abs(j - c) > separation for c in chosen)]
        assert start in allowed and scores[start] == min(scores[j] for j in allowed)
        chosen.append(start)
    if len(starts) < count:  # it stopped because every start lies near a chosen one
        assert all(any(abs(j - c) <= separation for c in chosen) for j in range(len(scores)))
