"""The walk of a check that passed but was not bracketed (issue #17): every verified frame of the
window sees the match camera on one side of the query, so the query's place lies beyond the
window; the check steps that way while frames pass, and brackets the match where the side
changes. The geometry here is synthetic (verify_pair replaced by a rule of the frame index), so
each case states exactly where the place is and which frames pass.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
import pytest
from detector_helpers import sequence_decision
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from doseqslam_logs.verification import (
    DEFAULT_VERIFICATION,
    NOT_BRACKETED,
    FrameFeatures,
    Verdict,
    stage,
)
from doseqslam_logs.verification.geometry import (
    Intrinsics,
    bracketed_match,
    crossing,
    side_of_query,
)
from doseqslam_logs.verification.metric_pose import OPTICAL_TO_BODY
from doseqslam_logs.verification.motion import CameraPath
from doseqslam_logs.verification.stage import WALK_RADII, Verifier, lone_side_holds

R = DEFAULT_VERIFICATION.refine_radius
# The stand-in geometry passes every frame of `passing`, those between match and query too, as a
# still camera's would: the motion rule (tests/test_motion_rule.py) is left out here.
PARAMS = DEFAULT_VERIFICATION.replace(motion_rule=False)
QUERY, MATCH, DATABASE = 400, 100, 380


def frames(indices: Sequence[int]) -> Iterator[tuple[int, np.ndarray]]:
    """A loader whose "image" of frame i holds i, for the stand-in feature extractor."""
    for index in indices:
        yield index, np.frombuffer(index.to_bytes(4, "little"), np.uint8).reshape(1, 4).copy()


def features_of_frame(gray: np.ndarray, params: object) -> FrameFeatures:
    """The frame's index as its features' `scale`: all the stand-in geometry needs."""
    index = int.from_bytes(gray.tobytes(), "little")
    return FrameFeatures(np.empty((0, 2), np.float32), np.empty((0, 32), np.uint8), "orb", index)


def geometry(place: int, passing: range):
    """verify_pair's stand-in: frames in `passing` pass with a pose, the match camera behind
    the query before `place` (translation +z) and ahead of it from `place` on."""

    def verify_pair(query, match, params, intrinsics):
        m = int(match.scale)
        if m not in passing:
            return Verdict(False, 0, 40, "E", "too few matches")
        t = (0.0, 0.0, 1.0) if m < place else (0.0, 0.0, -1.0)
        return Verdict(True, 200 - abs(m - place), 300, "E", "accepted", (0, 0, 0, 1), 0.0, t)

    return verify_pair


@pytest.fixture(autouse=True)
def indexed_features(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(stage, "extract_features", features_of_frame)


def check(monkeypatch: pytest.MonkeyPatch, place: int, passing: range) -> stage.PairCheck:
    monkeypatch.setattr(stage, "verify_pair", geometry(place, passing))
    verifier = Verifier(PARAMS, frames)
    decision = sequence_decision(1, 10**9, 1, QUERY, match=MATCH, database_size=DATABASE)
    (result,) = verifier.verify(decision).checks
    return result


@pytest.mark.parametrize("place", [MATCH + R + 10, MATCH - R - 10, MATCH + (1 + WALK_RADII) * R])
def test_a_place_beyond_the_window_is_walked_to_and_bracketed(monkeypatch, place) -> None:
    result = check(monkeypatch, place, range(0, DATABASE))
    assert result.accepted, result.verdict.reason
    assert result.refined_match_index in (place - 1, place)


def test_the_walk_stops_at_a_frame_that_fails(monkeypatch) -> None:
    place = MATCH + R + 10
    result = check(monkeypatch, place, range(0, place - 3))  # the view is lost before the place
    assert not result.accepted and result.verdict.reason == NOT_BRACKETED
    assert abs(result.refined_match_index - MATCH) <= R  # the window's best, not a walked frame


def test_the_walk_stops_at_its_reach(monkeypatch) -> None:
    place = MATCH + (1 + WALK_RADII) * R + 2  # just past what a candidate may move
    result = check(monkeypatch, place, range(0, DATABASE))
    assert not result.accepted and result.verdict.reason == NOT_BRACKETED


def test_a_bracketed_window_does_not_walk(monkeypatch) -> None:
    result = check(monkeypatch, MATCH + 3, range(0, DATABASE))
    assert result.accepted and result.refined_match_index in (MATCH + 2, MATCH + 3)


def test_side_of_query_follows_the_bracketing_sign() -> None:
    behind = Verdict(True, 50, 60, "E", "accepted", (0, 0, 0, 1), 0.0, (0.0, 0.0, 1.0))
    ahead = Verdict(True, 50, 60, "E", "accepted", (0, 0, 0, 1), 0.0, (0.0, 0.0, -1.0))
    assert side_of_query(behind) == 1  # the place is at later frames of the match
    assert side_of_query(ahead) == -1
    assert side_of_query(Verdict(False, 0, 0, "E", "too few matches")) == 0
    assert side_of_query(Verdict(True, 50, 60, "F", "accepted")) == 0  # no pose


def moving_geometry(first_place: int, passing: range, flipped=(), turned=()):
    """`geometry`'s stand-in for a revisit: query QUERY + k is at frame first_place + k of the
    match's pass. Frames of `flipped` give the wrong sign (a direction estimate gone astray),
    (query, frame) pairs of `turned` fit with a rotation past the limit."""

    def verify_pair(query, match, params, intrinsics):
        q, m = int(query.scale), int(match.scale)
        if m not in passing:
            return Verdict(False, 0, 40, "E", "too few matches")
        behind = (m < first_place + q - QUERY) != (m in flipped)
        t = (0.0, 0.0, 1.0) if behind else (0.0, 0.0, -1.0)
        inliers = 200 - abs(m - (first_place + q - QUERY))
        if (q, m) in turned:
            return Verdict(False, inliers, 300, "E", "rotation over 10 deg", (0, 0, 0, 1), 12.0, t)
        return Verdict(True, inliers, 300, "E", "accepted", (0, 0, 0, 1), 0.0, t)

    return verify_pair


def test_a_lone_flipped_frame_on_the_walk_is_walked_past(monkeypatch) -> None:
    """A walk that meets one frame whose direction estimate flipped looks one step further:
    that frame is still on the side it left, so the flip is not the place, and the walk goes
    on to the true one (4-hour log, query 128062: one flipped frame 3 m past the place was
    bracketed, 4 m off)."""
    place = MATCH + R + 10
    flip = MATCH + R + 4
    monkeypatch.setattr(stage, "verify_pair", moving_geometry(place, range(DATABASE), [flip]))
    verifier = Verifier(PARAMS, frames)
    decision = sequence_decision(1, 10**9, 1, QUERY, match=MATCH, database_size=DATABASE)
    (result,) = verifier.verify(decision).checks
    assert result.accepted, result.verdict.reason
    assert result.refined_match_index in (place - 1, place)


def test_a_crossing_between_frames_a_stride_apart_is_looked_at_frame_by_frame(
    monkeypatch,
) -> None:
    """At 10 Hz a tracked check looks at the frames a stride apart: the frame between its
    crossing's two that is turned past the limit is checked, and the pair is rejected for
    its rotation (4-hour log, query 133418: 7.5 degrees at a frame between two turned ones,
    20.3 true)."""
    first_place = MATCH + 3  # query QUERY + 5 is at frame MATCH + 8, tracked there
    tracked_query = QUERY + 5
    turned = {(tracked_query, MATCH + 7)}
    passing = range(DATABASE)
    decision = sequence_decision(10, 10**8, 10, QUERY, match=MATCH, database_size=DATABASE)
    assert stage.query_stride(decision, PARAMS.query_interval_s) == 5
    monkeypatch.setattr(stage, "verify_pair", moving_geometry(first_place, passing, (), turned))
    checks = Verifier(PARAMS, frames).verify(decision).checks
    assert checks[0].accepted and checks[0].refined_match_index == first_place
    tracked = checks[5]
    assert not tracked.accepted and tracked.verdict.reason == "rotation over 10 deg"
    # The same check without the turned frame passes at the place.
    monkeypatch.setattr(stage, "verify_pair", moving_geometry(first_place, passing))
    checks = Verifier(PARAMS, frames).verify(decision).checks
    assert checks[5].accepted and checks[5].refined_match_index == first_place + 5


def test_a_crossing_with_one_frame_on_a_side_needs_the_frame_beyond_it(monkeypatch) -> None:
    """At 10 Hz the window's first frame is the only one behind the query, and its sign is a
    flipped estimate: the place lies 40 frames before the window. A side of one frame is
    confirmed a stride beyond it; there the match camera is ahead again, so the window is not
    bracketed at the flip, and the walk finds the place (generated drives with more corners:
    a lone flip at a run's end bracketed 2-2.5 m past the place)."""
    place = MATCH - R - 40
    flip = MATCH - R
    monkeypatch.setattr(stage, "verify_pair", moving_geometry(place, range(DATABASE), [flip]))
    decision = sequence_decision(10, 10**8, 10, QUERY, match=MATCH, database_size=DATABASE)
    assert stage.query_stride(decision, PARAMS.query_interval_s) > 1
    result = Verifier(PARAMS, frames).verify(decision).checks[0]
    assert result.accepted, result.verdict.reason
    assert result.refined_match_index in (place - 1, place)


def test_a_crossing_that_the_odometry_places_metres_off_is_not_the_place(monkeypatch) -> None:
    """Thirty frames past the place (3 m at 0.1 m a frame) the signs still say "behind", but
    one: far points and a sideways offset flip the direction over a stretch, and the run's
    best split lies 3 m past the place with a frame on its wrong side. With a pose topic the
    query is then placed from the crossing's frames (PnP with the odometry's baseline, here
    exact): 3 m from them, so that crossing is not the place, and the pair is accepted where
    it is placed (generated grey drive with more corners: 2.64 m off)."""
    step_m, place = 0.1, MATCH - 20
    positions = np.zeros((DATABASE, 3))
    positions[:, 0] = step_m * np.arange(DATABASE)
    optical = Rotation.from_matrix(OPTICAL_TO_BODY).as_quat()
    path = CameraPath("/odom", positions, np.ones(DATABASE, bool), np.tile(optical, (DATABASE, 1)))

    def placed(self, query, frame, around, fitted):
        return np.array([0.0, 0.0, step_m * (place + int(query.scale) - QUERY - frame)])

    monkeypatch.setattr(Verifier, "_position", placed)
    flipped = [m for m in range(place, place + 30) if m != place + 20]
    monkeypatch.setattr(stage, "verify_pair", moving_geometry(place, range(DATABASE), flipped))
    decision = sequence_decision(1, 10**9, 1, QUERY, match=MATCH, database_size=DATABASE)
    camera = Intrinsics(100.0, 100.0, 50.0, 50.0)
    verifier = Verifier(PARAMS, frames, camera, camera_path=path)
    (result,) = verifier.verify(decision).checks
    assert result.accepted, result.verdict.reason
    assert result.refined_match_index == place


@given(
    st.lists(st.floats(-1.0, 1.0), min_size=1, max_size=30),
    st.lists(st.integers(30, 300), min_size=30, max_size=30),
    st.data(),
)
def test_the_crossing_is_the_one_the_bracketing_picks_from(zs, inliers, data) -> None:
    """`crossing` names the two frames `bracketed_match` chooses between, and the frames of
    the run on either side that agree with it: a run of random directions (z of the match
    camera), each frame passing with a pose."""
    verdicts = [
        (m, Verdict(True, inliers[m], 300, "E", "accepted", (0, 0, 0, 1), 0.0, (0.0, 0.0, -z)))
        for m, z in enumerate(zs)
    ]
    refined = data.draw(st.integers(0, len(zs) - 1))
    found = crossing(verdicts, refined)
    frame, verdict = bracketed_match(verdicts, refined, verdicts[refined][1])
    assert (found is None) == (verdict.reason == NOT_BRACKETED)
    if found is not None:
        assert found.after == found.before + 1 and frame in (found.before, found.after)
        assert all(zs[m] < 0 for m in found.behind) and all(zs[m] >= 0 for m in found.ahead)
        assert max(found.behind) == found.before and min(found.ahead) == found.after
        wrong = sum(zs[m] >= 0 for m in range(found.after)) + sum(
            zs[m] < 0 for m in range(found.after, len(zs))
        )
        assert found.wrong == wrong


def test_at_a_low_rate_a_side_of_one_frame_contradicted_beyond_it_is_no_crossing(
    monkeypatch,
) -> None:
    """At 1 frame a second every frame of the window is checked, and a side of one frame is
    common (its neighbour metres away fails), so it is kept where the frame beyond it is
    silent; where that frame fits and lies on the other side, the lone frame is a flipped
    estimate and not the place (drive_parked with FAST 10: a flip among parked frames 5 m
    from the query was bracketed)."""
    place = MATCH - R - 40
    flip = MATCH - R
    decision = sequence_decision(1, 10**9, 1, QUERY, match=MATCH, database_size=DATABASE)
    assert stage.query_stride(decision, PARAMS.query_interval_s) == 1
    monkeypatch.setattr(stage, "verify_pair", moving_geometry(place, range(DATABASE), [flip]))
    result = Verifier(PARAMS, frames).verify(decision).checks[0]
    assert result.refined_match_index not in (flip, flip + 1)
    # The frame beyond the flip silent (it fails): the lone frame is kept as a side.
    silent = range(flip, DATABASE)
    monkeypatch.setattr(stage, "verify_pair", moving_geometry(place, silent, [flip]))
    result = Verifier(PARAMS, frames).verify(decision).checks[0]
    assert result.accepted, result.verdict.reason
    assert result.refined_match_index in (flip, flip + 1)


@pytest.mark.parametrize(
    ("beyond", "confirmed", "holds"),
    [
        ("same", True, True),
        ("other", True, False),
        ("silent", True, False),
        ("past the ends", True, False),
        ("same", False, True),
        ("other", False, False),
        ("silent", False, True),
        ("past the ends", False, True),
    ],
)
def test_a_side_of_one_frame_against_the_frame_beyond_it(beyond, confirmed, holds) -> None:
    """Above 2 Hz the frame beyond must confirm the side; at low rates it must not deny it."""
    side = -1  # before the crossing: the match camera behind the query (translation +z)
    verdicts = {
        "same": Verdict(True, 50, 60, "E", "accepted", (0, 0, 0, 1), 0.0, (0.0, 0.0, 1.0)),
        "other": Verdict(True, 50, 60, "E", "accepted", (0, 0, 0, 1), 0.0, (0.0, 0.0, -1.0)),
        "silent": Verdict(False, 3, 40, "E", "too few matches"),
        "past the ends": None,
    }
    assert lone_side_holds(side, verdicts[beyond], confirmed) is holds
