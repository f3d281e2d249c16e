"""Same place, same heading: the rotation limit and bracketing of the refined match (issue #5).

The samples' ground truth counts a pair when the cameras are within 2 m and 20 degrees. The
essential matrix has no scale, so the check alone accepts the same facades seen from several
metres further on, or across a turn. Bracketing keeps a match only where the query's position
lies between two verified frames of the match's trajectory, and the rotation limit drops pairs
that look too far apart in heading (docs/results.md, "Our sample logs: same place, same heading").
"""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.evaluation.groundtruth import load_ground_truth
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.pipeline.decode import FrameCounts, decoded_frames
from doseqslam_logs.sources import open_source, pick_image_topic
from doseqslam_logs.sources.camera_info import read_camera_info
from doseqslam_logs.verification import (
    DEFAULT_VERIFICATION,
    Intrinsics,
    extract_features,
    verified_detector_parameters,
    verify_pair,
)
from doseqslam_logs.verification.geometry import (
    NOT_BRACKETED,
    Verdict,
    bracketed_match,
    match_camera_direction,
)

pytestmark = pytest.mark.slow  # the pipeline runs in its fixtures (pyproject: markers)

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
# (log, stem, measured true pairs with the defaults): every committed sample log (sample_logs/
# README.md) at precision 100 %.
# Since the crossing is the run's best split (`geometry._crossing`) over the query's checked
# frames near the match, those turned too far included, and frames under the working size are
# enlarged to it: drive_loops 64 (49 before), varrate 34 (29), parked 28 (18); since pairs
# turned past max_rotation_deg are kept where the odometry places them (confirmed_rotation_deg):
# 77, 49, 40; since a pair not bracketed is placed by the odometry: 81, 49, 40; since the
# query is resected against the match's frames 1 m and 2 m away: 81, 53, 41; since a pair seen
# from nearly one spot is turned by its homography (geometry.HOMOGRAPHY_SHARE): 83, 58, 41.
SAMPLE_RUNS = [
    ("drive_loops.ros2.mcap", "drive_loops", 83),
    ("drive_loops.foxglove.mcap", "drive_loops", 83),  # intrinsics from CameraCalibration
    ("drive_loops.bag", "drive_loops", 83),
    ("drive_loops.rosbag2", "drive_loops", 83),
    ("drive_varrate.bag", "drive_varrate", 58),
    ("drive_parked.ros2.mcap", "drive_parked", 41),
]


def _verified(log: Path, out: Path, **changes: object) -> list[dict[str, object]]:
    options = AnnotateOptions(verification=DEFAULT_VERIFICATION.replace(**changes), sidecar=True)
    annotate_log(log, out, verified_detector_parameters(), options)
    return list(read_annotations(out).loop_closures)


def _reported_truth(loop_closures: list[dict[str, object]], stem: str) -> np.ndarray:
    gt = load_ground_truth(SAMPLES / f"{stem}.gt.npz")
    reported = [lc for lc in loop_closures if lc.verification == "accepted"]
    q = np.array([lc.query.index for lc in reported], dtype=np.int64)
    m = np.array([lc.matched.index for lc in reported], dtype=np.int64)
    return np.asarray(gt.are_true(q, m, 0))


@pytest.mark.parametrize(("name", "stem", "true_pairs"), SAMPLE_RUNS)
def test_every_sample_log_is_verified_at_full_precision(
    annotated_sample, name, stem, true_pairs
) -> None:
    """Issue #5: with the defaults, no reported pair is outside the samples' ground truth."""
    reported = list(read_annotations(annotated_sample(name)).loop_closures)
    true = _reported_truth(reported, stem)
    assert (~true).sum() == 0
    assert true.sum() >= true_pairs


def test_without_both_rules_the_check_accepts_other_places(tmp_path) -> None:
    """drive_varrate with bracketing off and no rotation limit: 27 of 112 reported pairs were
    outside the ground truth (same street 2-4 m on, or across a turn)."""
    closures = _verified(
        SAMPLES / "drive_varrate.bag", tmp_path / "out.mcap", bracket=False, max_rotation_deg=180.0
    )
    true = _reported_truth(closures, "drive_varrate")
    assert (~true).sum() >= 20
    rejected = {lc.rejection_reason for lc in closures if lc.verification == "rejected"}
    assert NOT_BRACKETED not in rejected and not any("rotation over" in r for r in rejected)


def test_rejections_name_the_rule_and_carry_no_pose(annotated_sample) -> None:
    # The command's defaults, which are the library's (test_annotate): the run's shared output.
    closures = list(read_annotations(annotated_sample("drive_varrate.bag")).loop_closures)
    reasons = [lc.rejection_reason for lc in closures if lc.verification == "rejected"]
    assert NOT_BRACKETED in reasons and "rotation over 10 deg" in reasons
    assert not any(lc.has_relative_pose for lc in closures if lc.verification != "accepted")


def test_the_match_camera_direction_agrees_with_the_true_poses() -> None:
    """Ahead or behind along the query's optical axis, from the essential matrix, against the
    poses the sample was rendered from: every 4th query of drive_loops with a ground-truth
    loop, against the frames +-8 of its nearest true match, pairs more than 1 m apart
    (measured: 99.8 % agree over all the pairs of the sample)."""
    log = SAMPLES / "drive_loops.ros2.mcap"
    with open_source(log) as source:
        topic = pick_image_topic(source, None)
        frames = list(decoded_frames(source.image_messages(topic), FrameCounts()))
    info = read_camera_info(log, topic)
    assert info is not None
    intrinsics = Intrinsics(info.fx, info.fy, info.cx, info.cy)
    params = DEFAULT_VERIFICATION.replace(max_rotation_deg=180.0)
    features = [extract_features(f.image, params) for f in frames]
    with (SAMPLES / "drive_loops.poses.csv").open() as stream:
        rows = list(csv.DictReader(stream))
    poses = [(float(r["x"]), float(r["y"]), float(r["yaw"])) for r in rows]
    gt = load_ground_truth(SAMPLES / "drive_loops.gt.npz")
    queries = [q for q in range(len(frames)) if any(gt.is_true(q, j) for j in range(q))]
    agree = []
    for q in queries[::4]:
        nearest = min(
            (j for j in range(q) if gt.is_true(q, j)),
            key=lambda j: math.dist(poses[q][:2], poses[j][:2]),
        )
        for m in range(max(0, nearest - 8), min(q, nearest + 9)):
            dx, dy = poses[m][0] - poses[q][0], poses[m][1] - poses[q][1]
            verdict = verify_pair(features[q], features[m], params, intrinsics)
            direction = match_camera_direction(verdict)
            if not verdict.accepted or direction is None or math.hypot(dx, dy) <= 1.0:
                continue
            ahead = dx * math.cos(poses[q][2]) + dy * math.sin(poses[q][2])
            agree.append(bool(direction[2] > 0) == (ahead > 0))
    assert len(agree) >= 100 and np.mean(agree) >= 0.97


unit = st.floats(-1.0, 1.0, allow_nan=False)


@given(st.tuples(unit, unit, unit, unit), st.tuples(unit, unit, unit))
def test_the_match_camera_direction_is_the_inverse_rotation_of_minus_t(
    quaternion: tuple[float, float, float, float], direction: tuple[float, float, float]
) -> None:
    """-R^T t in plain floats, as scipy's Rotation gives it to rounding (it replaced it: ten
    times the cost per call, and a bracketing reads it for every frame of a run)."""
    q, t = np.array(quaternion), np.array(direction)
    if np.linalg.norm(q) < 1e-3 or np.linalg.norm(t) < 1e-3:
        return
    q_unit, t_unit = q / np.linalg.norm(q), t / np.linalg.norm(t)
    verdict = _posed(tuple(q_unit.tolist()), tuple(t_unit.tolist()))
    found = match_camera_direction(verdict)
    assert found is not None
    expected = Rotation.from_quat(q_unit).inv().apply(-t_unit)
    assert np.allclose(found, expected, rtol=0.0, atol=1e-12)


def _posed(rotation_xyzw: object, direction: object, inliers: int = 50) -> Verdict:
    return Verdict(
        True,
        inliers,
        100,
        "E",
        "accepted",
        rotation_xyzw=tuple(rotation_xyzw),  # type: ignore[arg-type]
        rotation_deg=0.0,
        translation_direction=tuple(direction),  # type: ignore[arg-type]
    )


def _along(ahead: float, inliers: int = 50) -> Verdict:
    """A verdict whose match camera sits `ahead` (a direction cosine) along the optical axis."""
    side = math.sqrt(max(0.0, 1.0 - ahead * ahead))
    # No rotation: -t is the direction of the match camera.
    return _posed((0.0, 0.0, 0.0, 1.0), (-side, 0.0, -ahead), inliers)


def _failed(inliers: int = 5) -> Verdict:
    return Verdict(False, inliers, 100, "E", "too few inliers")


def test_the_nearer_frame_of_the_sign_change_is_kept() -> None:
    verdicts = [(10, _along(-0.9)), (11, _along(-0.4)), (12, _along(0.2)), (13, _along(0.8))]
    assert bracketed_match(verdicts, 13, verdicts[3][1]) == (12, verdicts[2][1])
    # Among two sign changes that split the run equally well, the pair with the most inliers.
    aheads = [(-0.5, 40), (-0.4, 90), (0.5, 90), (-0.6, 40), (0.3, 40), (0.9, 40)]
    twice = [(i, _along(a, inliers)) for i, (a, inliers) in enumerate(aheads, start=1)]
    assert bracketed_match(twice, 6, twice[5][1])[0] in (2, 3)
    # ... and a change that splits it better wins over one with more inliers.
    aheads = [(-0.5, 40), (-0.4, 90), (0.5, 90), (-0.6, 40), (-0.3, 40), (0.9, 40), (0.8, 40)]
    better = [(i, _along(a, inliers)) for i, (a, inliers) in enumerate(aheads, start=1)]
    assert bracketed_match(better, 7, better[6][1])[0] in (5, 6)


def test_a_crossing_at_a_frame_turned_too_far_rejects_the_pair() -> None:
    """A figure eight's false pair: the true crossing's frames fit but are over
    max_rotation_deg; a frame 3 m on, whose rotation passes, must not be kept instead."""
    turned = [
        dataclasses.replace(_along(a, 110), accepted=False, reason="rotation over 10 deg")
        for a in (-0.67, 0.13, -0.13, 0.93)
    ]
    run = [(i, _along(-0.9, 90)) for i in range(6)]
    run += [(6 + i, v) for i, v in enumerate(turned)]
    run += [(10, _along(-0.6, 48)), *((11 + i, _along(1.0, 60)) for i in range(5))]
    frame, verdict = bracketed_match(run, 11, run[11][1])
    assert frame in (6, 7, 8, 9) and verdict.reason == "rotation over 10 deg"


def test_a_crossing_beside_a_frame_turned_too_far_is_not_trusted() -> None:
    """128x64 drive_loops' false pair: the place lies between a frame estimated under the
    rotation limit and one over it, in a turn; the one estimate under it was 13 degrees off."""
    over = dataclasses.replace(_along(0.77, 48), accepted=False, reason="rotation over 10 deg")
    run = [(16, _along(-0.9)), (17, _along(-0.6)), (18, _along(-0.15, 42)), (19, over)]
    run += [(20 + i, _along(0.9)) for i in range(4)]
    frame, verdict = bracketed_match(run, 20, run[4][1])
    assert (frame, verdict.accepted, verdict.reason) == (18, False, "rotation over 10 deg")
    # The same crossing with both frames under the limit is kept, at the nearer.
    run[3] = (19, _along(0.77, 48))
    assert bracketed_match(run, 20, run[4][1]) == (18, run[2][1])


def test_a_run_ends_at_a_gap_of_unchecked_frames() -> None:
    behind = [(i, _along(-0.9)) for i in range(4)]
    ahead = [(40 + i, _along(0.9)) for i in range(4)]
    assert bracketed_match(behind + ahead, 41, ahead[1][1])[0] in (3, 40)
    frame, verdict = bracketed_match(behind + ahead, 41, ahead[1][1], max_gap=25)
    assert (frame, verdict.reason) == (41, NOT_BRACKETED)


def test_a_match_with_every_verified_frame_on_one_side_is_rejected() -> None:
    verdicts = [(5, _along(0.95, 60)), (6, _along(0.9, 80)), (7, _along(0.97, 40))]
    frame, verdict = bracketed_match(verdicts, 6, verdicts[1][1])
    assert frame == 6 and not verdict.accepted and verdict.reason == NOT_BRACKETED
    assert verdict.inliers == 80 and verdict.translation_direction is not None


def test_a_lone_sign_flip_is_noise_not_a_crossing() -> None:
    """The hour's two false pairs: one frame's sign flipped amid its neighbours' ("- + - -"
    at 2.2 m from the crossing, "+ + - +" at 2.5 m) and was taken as the crossing."""
    behind = [(i, _along(-0.9 + 0.05 * i)) for i in range(5)]
    behind[1] = (1, _along(0.3))  # a lone "+" among "-"
    frame, verdict = bracketed_match(behind, 1, behind[1][1])
    assert (frame, verdict.reason) == (1, NOT_BRACKETED)
    ahead = [(i, _along(0.9 - 0.05 * i)) for i in range(5)]
    ahead[3] = (3, _along(-0.2))  # a lone "-" among "+"
    assert bracketed_match(ahead, 3, ahead[3][1])[1].reason == NOT_BRACKETED
    # A flip beside a true crossing leaves the crossing: - + - - + +
    signs = [-0.8, 0.1, -0.5, -0.2, 0.3, 0.7]
    crossing = [(i, _along(a)) for i, a in enumerate(signs)]
    frame, verdict = bracketed_match(crossing, 0, crossing[0][1])
    assert verdict.accepted and frame in (3, 4)


def test_a_flip_beside_the_runs_end_is_not_a_crossing() -> None:
    """park180's pair 3.8 m off: "+ - + + + + +", frames 3-4 m past the place, the second
    one's sign flipped. One frame of seven is on the wrong side, but it is half the short
    side: the split there has no frame behind that another does not contradict."""
    aheads = [0.9, -0.95, 0.96, 0.97, 0.95, 0.98, 0.96]
    run = [(170 + i, _along(a, 40)) for i, a in enumerate(aheads)]
    frame, verdict = bracketed_match(run, 174, run[4][1])
    assert (frame, verdict.reason) == (174, NOT_BRACKETED)
    # Two frames behind before the flip make it a crossing again: - - + - + + + +
    aheads = [-0.9, -0.8, 0.3, -0.2, 0.5, 0.8, 0.9, 0.95]
    run = [(i, _along(a)) for i, a in enumerate(aheads)]
    assert bracketed_match(run, 7, run[7][1])[1].accepted


def test_a_sign_change_across_a_failed_frame_does_not_bracket() -> None:
    verdicts = [(5, _along(-0.8)), (6, _failed()), (7, _along(0.6)), (8, _along(0.9))]
    assert bracketed_match(verdicts, 8, verdicts[3][1])[1].reason == NOT_BRACKETED


def test_fundamental_and_rejected_verdicts_pass_through() -> None:
    plain = Verdict(True, 50, 100, "F", "accepted")
    assert bracketed_match([(3, plain)], 3, plain) == (3, plain)
    failed = _failed()
    assert bracketed_match([(3, failed)], 3, failed) == (3, failed)
    with pytest.raises(ValueError, match="not among the checked frames"):
        bracketed_match([(3, plain)], 4, plain)


@given(st.lists(st.floats(-1.0, 1.0), min_size=1, max_size=12), st.data())
def test_bracketing_keeps_a_neighbour_of_the_best_split_or_rejects(aheads, data) -> None:
    verdicts = [(i, _along(a, 30 + i)) for i, a in enumerate(aheads)]
    start = data.draw(st.integers(0, len(aheads) - 1))
    frame, verdict = bracketed_match(verdicts, start, verdicts[start][1])
    sides = [1 if a >= 0 else -1 for a in aheads]
    n = len(sides)

    def mostly(i: int) -> bool:  # more frames on their side than not, on each side
        return 2 * sides[: i + 1].count(-1) > i + 1 and 2 * sides[i + 1 :].count(1) > n - i - 1

    agree = {  # each sign change: the frames on their side of a split there
        i: sides[: i + 1].count(-1) + sides[i + 1 :].count(1)
        for i in range(n - 1)
        if sides[i] < 0 < sides[i + 1] and mostly(i)
    }
    best = max(agree.values(), default=None)
    if best is None or n - best > (n - 1) // 4:
        assert (frame, verdict.reason) == (start, NOT_BRACKETED)
    else:
        assert verdict.accepted
        i = next(i for i, a in agree.items() if a == best and frame in (i, i + 1))
        assert abs(aheads[frame]) <= abs(aheads[2 * i + 1 - frame])
