"""The verification stage in the pipeline: annotate records it, --no-verify is the paper's."""

from __future__ import annotations

import csv
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from golden import DRIVE_LOOPS_PAPER_PAIRS, RTABMAP_VERIFIED_MIN_TP

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.cli.main import main
from doseqslam_logs.detector import Parameters, make_detector
from doseqslam_logs.evaluation.groundtruth import load_ground_truth
from doseqslam_logs.evaluation.metrics import evaluate
from doseqslam_logs.evaluation.verified import verified_decisions
from doseqslam_logs.pipeline.decode import FrameCounts, decoded_frames
from doseqslam_logs.pipeline.replay import replay
from doseqslam_logs.pipeline.reread import FolderFrameReader, runs
from doseqslam_logs.sources import open_source, pick_image_topic
from doseqslam_logs.sources.camera_info import read_camera_info
from doseqslam_logs.sources.image_folder import folder_frames, list_images
from doseqslam_logs.verification import (
    DEFAULT_VERIFICATION,
    VERIFIED_THRESHOLD,
    Intrinsics,
    Verifier,
    verified_detector_parameters,
)
from doseqslam_logs.verification.stage import WALK_RADII, FeatureCache

pytestmark = pytest.mark.slow  # the pipeline runs in its fixtures (pyproject: markers)

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
LOOPS = SAMPLES / "drive_loops.ros2.mcap"
VERIFIED = verified_detector_parameters()


@pytest.fixture(scope="module")
def verified_log(annotated_sample) -> Path:
    # = annotate_log(LOOPS, out, VERIFIED, AnnotateOptions(verification=DEFAULT_VERIFICATION))
    return annotated_sample(LOOPS.name)


def yaw_by_frame() -> dict[int, float]:
    with (SAMPLES / "drive_loops.poses.csv").open() as stream:
        return {int(row["frame"]): float(row["yaw"]) for row in csv.DictReader(stream)}


def test_each_candidate_is_recorded_with_its_verdict(verified_log) -> None:
    log = read_annotations(verified_log)
    verdicts = {lc.verification for lc in log.loop_closures}
    assert verdicts == {"accepted", "rejected"}  # rejected pairs stay visible
    accepted = [lc for lc in log.loop_closures if lc.verification == "accepted"]
    assert log.reported_loop_closures == accepted
    assert all(lc.inliers >= DEFAULT_VERIFICATION.min_inliers for lc in accepted)
    assert all(lc.rejection_reason for lc in log.loop_closures if lc not in accepted)
    # The refined match is near the match of its proposal: within its window, or as far as a
    # walk past it may go (Verifier._reach).
    reach = (1 + WALK_RADII) * DEFAULT_VERIFICATION.refine_radius
    for lc in log.loop_closures:
        assert abs(lc.matched.index - lc.proposal_match_index) <= reach
        assert (lc.proposal == 0) == (lc.proposal_match_index == lc.match.index)
        assert lc.proposal == 0 or lc.verification == "accepted"
    # Some pairs were found on a next-best trajectory of their sequence, far from the match.
    alternative = [lc for lc in accepted if lc.proposal > 0]
    assert alternative
    r = DEFAULT_VERIFICATION.refine_radius
    assert all(abs(lc.matched.index - lc.match.index) > r for lc in alternative)
    assert log.metadata.verification == "on"
    assert log.metadata.intrinsics_source == "/camera/camera_info"
    assert log.metadata.loop_closures == len(accepted)
    sequences = [s for s in log.sequences if s.verified_pairs]
    assert sum(s.accepted_pairs for s in sequences) == len(accepted)
    assert all(s.verification == "on" for s in log.sequences)


def test_relative_rotation_matches_the_ground_truth_poses(verified_log) -> None:
    """The sample camera looks along the heading, so |R| is the yaw difference."""
    yaw = yaw_by_frame()
    errors = []
    for lc in read_annotations(verified_log).reported_loop_closures:
        assert lc.has_relative_pose and lc.verification_model == "essential"
        q, m = lc.query.index, lc.matched.index
        turned = abs(math.remainder(yaw[q] - yaw[m], math.tau))
        errors.append(abs(lc.rotation_deg - math.degrees(turned)))
    assert len(errors) >= 30
    assert np.median(errors) < 2.0 and np.percentile(errors, 90) < 5.0


def test_verified_pairs_are_true_places_on_the_sample(verified_log) -> None:
    """Measured: all 50 verified pairs are GT loop events (2 m, 20 deg); before bracketing and
    the rotation limit, 3 of 97 were the same place one frame past the GT boundary
    (docs/results.md)."""
    gt = load_ground_truth(SAMPLES / "drive_loops.gt.npz")
    reported = read_annotations(verified_log).reported_loop_closures
    q = np.array([lc.query.index for lc in reported])
    m = np.array([lc.matched.index for lc in reported])
    true = gt.are_true(q, m, 0)
    assert true.sum() >= 45 and (~true).sum() == 0


def test_no_verify_is_the_papers_decision(tmp_path) -> None:
    out = tmp_path / "raw.mcap"
    assert main(["annotate", str(LOOPS), "-o", str(out), "--no-verify"]) == 0
    log = read_annotations(out)
    assert log.parameters["threshold"] == 0.75  # Table II, not VERIFIED_THRESHOLD
    assert {lc.verification for lc in log.loop_closures} == {"off"}
    assert all(lc.inliers == -1 for lc in log.loop_closures)
    assert all(lc.matched.index == lc.match.index for lc in log.loop_closures)
    assert log.metadata.verification == "off" and len(log.loop_closures) == DRIVE_LOOPS_PAPER_PAIRS


def test_cli_verifies_by_default_with_the_verified_threshold(tmp_path, capsys) -> None:
    out = tmp_path / "v.mcap"
    args = ["annotate", str(LOOPS), "-o", str(out), "-E", "1700000060000000000"]
    assert main(args) == 0
    assert "verified" in capsys.readouterr().out
    log = read_annotations(out)
    assert log.parameters["threshold"] == VERIFIED_THRESHOLD
    assert main([*args, "--set", "threshold=0.8"]) == 0
    assert read_annotations(out).parameters["threshold"] == 0.8


def test_intrinsics_option_is_checked(tmp_path, capsys) -> None:
    out = tmp_path / "v.mcap"
    assert main(["annotate", str(LOOPS), "-o", str(out), "--intrinsics", "1,2,3"]) == 2
    assert "--intrinsics" in capsys.readouterr().err and not out.exists()


def test_camera_info_is_found_in_every_container() -> None:
    """sensor_msgs/CameraInfo in the ROS containers, foxglove.CameraCalibration (protobuf) in
    the Foxglove MCAP: the same intrinsics."""
    for name in (
        "drive_loops.ros2.mcap",
        "drive_loops.bag",
        "drive_loops.rosbag2",
        "drive_loops.foxglove.mcap",
    ):
        info = read_camera_info(SAMPLES / name, "/camera/image/compressed")
        assert info is not None and (info.width, info.height) == (256, 192)
        assert info.cx == 128.0 and info.fx == pytest.approx(182.80294486299067)


def test_verified_figures_on_rtabmap_reach_the_target(shared_data) -> None:
    """Issue #5: R@P100 >= 60 % with defaults (kappa 10 s); measured 79.5 %, 35 TP / 0 FP
    (the same with the SIFT segmentation, one of them on a next-best trajectory there)."""
    folder = shared_data / "rtabmap_samples_loop" / "images"
    params = verified_detector_parameters(kappa_s=10.0)
    decisions = replay(folder_frames(folder, 1.0), make_detector(params)).decisions
    verifier = Verifier(DEFAULT_VERIFICATION, FolderFrameReader(list_images(folder)))
    verified = verified_decisions(verifier.verify_all(decisions))
    gt = load_ground_truth(shared_data / "rtabmap_samples_loop" / "samples_GT.bmp")
    raw, checked = evaluate(decisions, gt, params.threshold), evaluate(verified, gt, 0.99)
    assert raw.r_p100 < 0.25 and checked.r_p100 >= 0.6
    assert checked.fp == 0 and checked.tp >= RTABMAP_VERIFIED_MIN_TP


def test_next_best_trajectories_add_true_pairs_and_no_false_one() -> None:
    """drive_loops: the same decisions with and without alternatives (they only add
    information); verified, the alternatives find 2 more true pairs (50 against 48; 50 against
    44 before a check walks past its window to bracket the match, which finds most of what
    they found) and no false one (94 against 80, both with 3 false ones, before bracketing and
    the rotation limit)."""
    stamped, intrinsics = _sample_frames(LOOPS)
    gt = load_ground_truth(SAMPLES / "drive_loops.gt.npz")
    figures = {}
    for count in (0, 3):
        detector = make_detector(verified_detector_parameters(alternatives=count))
        decisions = [d for t, gray in stamped for d in detector.push(t, gray)]
        decisions += detector.finish()
        grays = [gray for _, gray in stamped]
        verifier = Verifier(DEFAULT_VERIFICATION, _list_loader(grays), intrinsics)
        checks = verifier.verify_all(decisions)
        figures[count] = (decisions, evaluate(verified_decisions(checks), gt, 0.99), checks)
    plain, with_alternatives = figures[0], figures[3]
    assert [replace(d, alternatives=()) for d in with_alternatives[0]] == plain[0]
    assert all(not d.alternatives for d in plain[0])
    assert any(d.alternatives for d in with_alternatives[0])
    assert with_alternatives[1].tp >= plain[1].tp + 2
    assert with_alternatives[1].fp == plain[1].fp == 0
    for item in with_alternatives[2]:  # each accepted pair lies on the trajectory it names
        for z, check in enumerate(item.checks):
            if check.proposal:
                match = item.decision.alternatives[check.proposal - 1].match_indices[z]
                assert abs(check.refined_match_index - match) <= DEFAULT_VERIFICATION.refine_radius


def _sample_frames(log: Path) -> tuple[list[tuple[int, np.ndarray]], Intrinsics | None]:
    with open_source(log) as source:
        topic = pick_image_topic(source, None)
        messages = source.image_messages(topic, None, None)
        frames = list(decoded_frames(messages, FrameCounts(), "header", "skip"))
    info = read_camera_info(log, topic)
    intrinsics = None if info is None else Intrinsics(info.fx, info.fy, info.cx, info.cy)
    return [(f.timestamp_ns, f.image) for f in frames], intrinsics


def _list_loader(grays: list[np.ndarray]):
    def load(indices):
        return ((i, grays[i]) for i in indices)

    return load


def test_feature_cache_stays_within_its_budget(shared_data) -> None:
    folder = shared_data / "rtabmap_samples_loop" / "images"
    reader = FolderFrameReader(list_images(folder))
    from doseqslam_logs.verification import extract_features

    features = [extract_features(gray, DEFAULT_VERIFICATION) for _, gray in reader(range(6))]
    cache = FeatureCache(max_bytes=2 * max(f.nbytes for f in features))
    for index, item in enumerate(features):
        cache.put(index, item)
        assert cache.bytes <= cache.max_bytes
    assert cache.get(5) is features[5] and cache.get(0) is None
    kept = [i for i in range(6) if cache.get(i) is not None]
    assert sum(features[i].nbytes for i in kept) == cache.bytes <= cache.max_bytes


def test_runs_group_neighbouring_frames() -> None:
    assert runs([5, 1, 2, 40, 3, 200], max_gap=32) == [[1, 2, 3, 5], [40], [200]]
    assert runs([]) == []


def test_intrinsics_reject_nonsense() -> None:
    with pytest.raises(ValueError):
        Intrinsics(0, 1, 0, 0)


def test_alternatives_default_on_with_verification_and_stay_as_given(tmp_path) -> None:
    from doseqslam_logs.cli.main import build_parser
    from doseqslam_logs.cli.params_args import run_parameters
    from doseqslam_logs.verification import VERIFIED_ALTERNATIVES

    def params(*argv: str) -> Parameters:
        args = build_parser().parse_args(["annotate", "log.mcap", "-o", "out.mcap", *argv])
        return run_parameters(args)

    config = tmp_path / "p.toml"
    config.write_text("alternatives = 1\n")
    assert params().alternatives == VERIFIED_ALTERNATIVES == 3
    assert params("--no-verify").alternatives == 0  # the paper: the detector's match only
    assert params("--set", "alternatives=0").alternatives == 0
    assert params("--config", str(config)).alternatives == 1
    assert params("--set", "alternatives=5", "--no-verify").alternatives == 5


def test_segmentation_is_orb_at_320_with_verification_unless_either_is_given(tmp_path) -> None:
    from doseqslam_logs.cli.main import build_parser
    from doseqslam_logs.cli.params_args import run_parameters

    def segmentation(*argv: str) -> tuple[str, int]:
        args = build_parser().parse_args(["annotate", "log.mcap", "-o", "out.mcap", *argv])
        params = run_parameters(args)
        return params.feature_detector, params.feature_image_max_side

    config = tmp_path / "p.toml"
    config.write_text('feature_detector = "sift"\n')
    assert segmentation() == ("orb", 320)
    assert segmentation("--no-verify") == ("auto", 240)  # paper-like: SURF, else SIFT
    assert segmentation("--set", "feature_detector=sift") == ("sift", 240)
    assert segmentation("--set", "feature_image_max_side=200") == ("auto", 200)
    assert segmentation("--config", str(config)) == ("sift", 240)
    assert verified_detector_parameters().feature_detector == "orb"
    assert verified_detector_parameters(feature_detector="klt").feature_image_max_side == 240
