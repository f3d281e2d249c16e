"""`evaluate OUT.mcap`: the figures of an annotated log equal those of the in-memory run; ground
truth from the log's poses agrees with the sample's committed matrix; errors and exit codes."""

from __future__ import annotations

import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from golden import DRIVE_LOOPS_GT_LOOP_EVENTS as LOOP_EVENTS
from golden import DRIVE_LOOPS_PAPER_PAIRS as PAIRS
from hypothesis import given, settings
from hypothesis import strategies as st

from doseqslam_logs.annotations.reader import AnnotatedLog, read_annotations
from doseqslam_logs.annotations.records import FrameRef, FrameTimes
from doseqslam_logs.cli.main import main
from doseqslam_logs.detector import Parameters
from doseqslam_logs.errors import ExitCode, GroundTruthError
from doseqslam_logs.evaluation import log_run
from doseqslam_logs.evaluation.groundtruth import GroundTruth, load_ground_truth
from doseqslam_logs.evaluation.metrics import evaluate
from doseqslam_logs.evaluation.pose_ground_truth import (
    FramePoses,
    LoopCriteria,
    PoseGroundTruth,
    frame_poses,
    loop_cells,
    pose_ground_truth,
    yaw_from_quaternions,
)
from doseqslam_logs.evaluation.recorded_run import (
    evaluate_annotated_log,
    format_log_report,
    raw_decisions,
)
from doseqslam_logs.pipeline.annotate import AnnotateOptions, AnnotateResult, annotate_log
from doseqslam_logs.sources import open_source
from doseqslam_logs.sources.poses import read_poses

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
LOG = SAMPLES / "drive_loops.ros2.mcap"
GT = SAMPLES / "drive_loops.gt.npz"
POSES = "/ground_truth/pose"
# How tools/loggen/make_sample_logs.py made the committed ground truth (sample_logs/README.md).
SAMPLE_GT = ["--radius", "2", "--max-heading", "20", "--min-travel", "20"]


@pytest.fixture(scope="module")
def annotated(tmp_path_factory) -> tuple[Path, AnnotateResult]:
    out = tmp_path_factory.mktemp("evaluate_log") / "drive_loops.annotated.mcap"
    return out, annotate_log(LOG, out, Parameters(), AnnotateOptions(verification=None))


@pytest.fixture(scope="module")
def sidecar(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("evaluate_log_sidecar") / "drive_loops.sidecar.mcap"
    annotate_log(LOG, out, Parameters(), AnnotateOptions(sidecar=True, verification=None))
    return out


def run_cli(capsys, *argv: object) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


# -- the figures --------------------------------------------------------------------------


@pytest.mark.parametrize("json_output", [False, True])
def test_evaluate_log_gives_the_commands_report(annotated, capsys, json_output) -> None:
    out, _ = annotated
    options = log_run.LogEvaluationOptions(gt_topic=POSES, radius=2.0, max_heading=20.0)
    report = log_run.evaluate_log(out, options)
    argv = ["evaluate", out, "--gt-topic", POSES, "--radius", "2", "--max-heading", "20"]
    code, stdout, _ = run_cli(capsys, *argv, *["--json"] * json_output)
    expected = (
        json.dumps(report.to_json_dict(), indent=2) if json_output else report.format_report()
    )
    assert code == 0 and stdout == expected + "\n" and report.result.raw.tp > 0


def test_rebuilt_decisions_are_the_runs(annotated) -> None:
    out, result = annotated
    assert raw_decisions(read_annotations(out)) == result.replay.decisions


@pytest.mark.parametrize("tolerance", [0, 3])
def test_figures_equal_those_of_the_in_memory_run(annotated, tolerance) -> None:
    out, result = annotated
    gt = load_ground_truth(GT)
    log = read_annotations(out)
    times = log.detector_times_ns()  # for the revisit coverage
    expected = evaluate(result.replay.decisions, gt, Parameters().threshold, tolerance, times)
    got = evaluate_annotated_log(log, gt, tolerance)
    assert got.raw == expected and len(got.raw.coverage) == 2
    assert got.verified is None  # the run recorded no verification
    assert expected.tp + expected.fp == PAIRS and expected.gt_loop_events == LOOP_EVENTS


def test_json_holds_the_in_memory_figures(annotated, capsys) -> None:
    out, result = annotated
    code, stdout, _ = run_cli(capsys, "evaluate", out, "--gt", GT, "--json")
    assert code == 0
    doc = json.loads(stdout)
    times = read_annotations(out).detector_times_ns()
    expected = evaluate(result.replay.decisions, load_ground_truth(GT), 0.75, 0, times)
    expected_json = expected.to_json_dict()
    assert {key: doc[key] for key in expected_json} == expected_json
    assert doc["ground_truth"] == {"kind": "file", "file": str(GT), "variable": "gt"}
    assert doc["verified"] is None and doc["plots"] == []
    assert doc["parameters_hash"] == read_annotations(out).metadata.parameters_hash
    assert doc["parameters"]["kappa_s"] == 40.0 and doc["image_topic"] == "/camera/image/compressed"
    assert doc["source_file"] == LOG.name
    assert len(doc["curve"]) > 1 and doc["threshold_at_r_p100"] is not None


def test_text_report_names_the_run_and_the_figures(annotated, capsys) -> None:
    out, _ = annotated
    code, stdout, _ = run_cli(capsys, "evaluate", out, "--gt", GT)
    assert code == 0
    lines = stdout.splitlines()
    assert lines[0].startswith("doseqslam run recorded in")
    assert read_annotations(out).metadata.parameters_hash in lines[0]
    assert f"reported pairs   : {PAIRS} (TP {PAIRS}, FP 0)" in lines
    assert (
        f"recall           : {100 * PAIRS / LOOP_EVENTS:.2f} % ({PAIRS} of {LOOP_EVENTS})" in lines
    )
    assert any(line.startswith("R@P100           : 38.21 % at th = ") for line in lines)


def test_ground_truth_of_another_size_is_refused(annotated, capsys) -> None:
    out, _ = annotated
    code, _, err = run_cli(capsys, "evaluate", out, "--gt", SAMPLES / "drive_parked.gt.npz")
    assert code == ExitCode.USAGE
    assert "ground truth has 300 frames but" in err and "over 240 frames" in err
    assert err.count("\n") == 1


def test_size_check_without_frame_times_uses_the_sequences(annotated) -> None:
    out, _ = annotated
    log = replace(read_annotations(out), frame_times=None)  # annotated before frame times
    assert evaluate_annotated_log(log, load_ground_truth(GT)).raw.tp == PAIRS
    with pytest.raises(GroundTruthError, match=r"has 241 frames but .* over 240 frames"):
        evaluate_annotated_log(log, GroundTruth(241, [], []))


# -- verified figures ---------------------------------------------------------------------


def with_verification(log: AnnotatedLog) -> AnnotatedLog:
    """The log as a verified run would record it: odd query frames rejected; the first
    accepted pair refined onto frame 0 (so it turns false)."""
    assert log.frame_times is not None
    first_accepted = min(lc.query.index for lc in log.loop_closures if lc.query.index % 2 == 0)
    closures = []
    for lc in log.loop_closures:
        verdict = "rejected" if lc.query.index % 2 else "accepted"
        refined = 0 if lc.query.index == first_accepted else lc.match.index
        closures.append(
            replace(lc, verification=verdict, refined_match=FrameRef.of(refined, log.frame_times))
        )
    sequences = tuple(replace(s, verification="on") for s in log.sequences)
    return replace(log, loop_closures=tuple(closures), sequences=sequences)


def test_verified_figures_count_accepted_pairs_at_their_refined_match(annotated) -> None:
    out, _ = annotated
    log = with_verification(read_annotations(out))
    gt = load_ground_truth(GT)
    result = evaluate_annotated_log(log, gt)
    accepted = [lc for lc in log.loop_closures if lc.verification == "accepted"]
    truth = [gt.is_true(lc.query.index, lc.matched.index) for lc in accepted]
    assert result.verified is not None
    assert (result.verified.tp, result.verified.fp) == (sum(truth), len(truth) - sum(truth))
    assert result.verified.fp == 1 and result.verified.tp == len(accepted) - 1
    # Only pairs below th were verified: the verified sweep ends at the recorded threshold.
    assert max(p.threshold for p in result.verified.curve) <= 0.75 + 1e-6
    assert result.raw == evaluate_annotated_log(read_annotations(out), gt).raw
    report = format_log_report(result)
    assert "verified (accepted pairs)" in report
    assert f"{len(accepted)} (TP {len(accepted) - 1}, FP 1)" in report


@pytest.fixture(scope="module")
def verified_run(tmp_path_factory) -> tuple[Path, AnnotateResult, float]:
    """drive_loops annotated as the annotate command does: verified, at the verified th."""
    from doseqslam_logs.verification import (
        VERIFIED_THRESHOLD,
        VerificationParameters,
        verified_detector_parameters,
    )

    out = tmp_path_factory.mktemp("evaluate_log_verified") / "drive_loops.verified.mcap"
    params = verified_detector_parameters()
    options = AnnotateOptions(verification=VerificationParameters())
    return out, annotate_log(LOG, out, params, options), VERIFIED_THRESHOLD


def test_verified_figures_of_a_verified_run_equal_the_in_memory_ones(verified_run) -> None:
    from doseqslam_logs.evaluation.verified import verified_decisions

    out, result, threshold = verified_run
    assert result.verification is not None
    gt = load_ground_truth(GT)
    in_memory = verified_decisions(result.verification.decisions.values())
    log = read_annotations(out)
    times = log.detector_times_ns()
    expected_verified = evaluate(in_memory, gt, threshold, 0, times)
    got = evaluate_annotated_log(log, gt)
    assert got.raw == evaluate(result.replay.decisions, gt, threshold, 0, times)
    assert got.verified == expected_verified
    assert got.verified.tp + got.verified.fp == result.loop_closures > 0
    assert got.raw.tp + got.raw.fp > got.verified.tp + got.verified.fp


def test_cli_reports_verified_figures_side_by_side(annotated, capsys, monkeypatch) -> None:
    out, _ = annotated
    log = with_verification(read_annotations(out))
    monkeypatch.setattr(log_run, "read_annotations", lambda path: log)
    code, stdout, _ = run_cli(capsys, "evaluate", out, "--gt", GT, "--json")
    doc = json.loads(stdout)
    assert code == 0 and doc["verified"]["fp"] == 1 and doc["tp"] == PAIRS
    assert doc["verified"]["tp"] + doc["verified"]["fp"] < doc["tp"] + doc["fp"]


# -- ground truth from poses --------------------------------------------------------------


def test_pose_ground_truth_of_the_log_is_the_committed_one(annotated, capsys) -> None:
    out, _ = annotated
    log = read_annotations(out)
    assert log.frame_times is not None
    times = log.frame_times.detector_times_ns(log.metadata.time_source)
    poses = frame_poses(read_poses(out, POSES), times)
    committed = load_ground_truth(GT)
    for travel in (20.0, None):  # the travel condition never binds on drive_loops
        gt = pose_ground_truth(poses, LoopCriteria(2.0, 40.0, 20.0, travel))
        assert gt.nnz == committed.nnz == 810
        assert gt.n_loop_events == committed.n_loop_events
        assert np.array_equal(gt.query_rows(), committed.query_rows())
        assert (gt.materialized().matrix != committed.matrix).nnz == 0
    code, stdout, _ = run_cli(capsys, "evaluate", out, "--gt-topic", POSES, *SAMPLE_GT, "--json")
    doc = json.loads(stdout)
    _, file_out, _ = run_cli(capsys, "evaluate", out, "--gt", GT, "--json")
    from_file = json.loads(file_out)
    assert code == 0 and doc["gt_file"].startswith(POSES)
    for key in ("gt_loop_events", "tp", "fp", "recall", "r_p100", "recall_at_p90", "curve"):
        assert doc[key] == from_file[key]
    assert doc["ground_truth"]["min_age_s"] == 40.0
    assert doc["ground_truth"]["frames_without_pose"] == 0


def test_min_travel_keeps_a_parked_camera_from_revisiting_itself() -> None:
    """drive_parked stands still for 60 s: without --min-travel its parked frames revisit each
    other; with the sample's 20 m the ground truth is the committed one."""
    log = SAMPLES / "drive_parked.ros2.mcap"
    with open_source(log) as source:
        pairs = [
            (m.log_time_ns, m.header_stamp_ns)
            for m in source.image_messages("/camera/image/compressed")
        ]
    poses = frame_poses(
        read_poses(log, POSES), FrameTimes.from_pairs(pairs).detector_times_ns("header")
    )
    committed = load_ground_truth(SAMPLES / "drive_parked.gt.npz")
    strict = pose_ground_truth(poses, LoopCriteria(2.0, 40.0, 20.0, 20.0)).materialized()
    loose = pose_ground_truth(poses, LoopCriteria(2.0, 40.0, 20.0, None)).materialized()
    assert (strict.matrix != committed.matrix).nnz == 0
    assert loose.nnz > committed.nnz and (committed.matrix > loose.matrix).nnz == 0


def test_sidecar_reads_poses_from_the_source_log(annotated, sidecar, capsys) -> None:
    code, _, err = run_cli(capsys, "evaluate", sidecar, "--gt-topic", POSES, "--radius", "2")
    assert code == ExitCode.USAGE and "--source" in err
    code, stdout, _ = run_cli(
        capsys, "evaluate", sidecar, "--gt-topic", POSES, *SAMPLE_GT, "--source", LOG, "--json"
    )
    assert code == 0 and json.loads(stdout)["tp"] == PAIRS
    wrong = SAMPLES / "drive_parked.ros2.mcap"
    code, _, err = run_cli(
        capsys, "evaluate", sidecar, "--gt-topic", POSES, "--radius", "2", "--source", wrong
    )
    assert code == ExitCode.USAGE and "not the log" in err and "--no-source-check" in err
    code, stdout, _ = run_cli(
        capsys, "evaluate", sidecar, "--gt-topic", POSES, *SAMPLE_GT, "--json",
        "--source", LOG.with_name("drive_loops.rosbag2"), "--no-source-check",
    )  # fmt: skip
    assert code == 0 and json.loads(stdout)["tp"] == PAIRS  # the same drive in another file


def test_diff_of_sidecars_checks_their_source_as_evaluate_does(sidecar, capsys) -> None:
    truth = ["--gt-topic", POSES, *SAMPLE_GT]
    code, out, _ = run_cli(capsys, "diff", sidecar, sidecar, *truth, "--source", LOG)
    assert code == 0 and "common" in out
    wrong = SAMPLES / "drive_parked.ros2.mcap"
    code, _, err = run_cli(capsys, "diff", sidecar, sidecar, *truth, "--source", wrong)
    assert code == ExitCode.USAGE and "--source" in err and "not the log" in err


# -- usage errors and exit codes ----------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "code", "message"),
    [
        (["evaluate", "--gt", "{gt}"], ExitCode.USAGE, "exactly one of"),
        (["evaluate", "{out}", "--images", "/x", "--gt", "{gt}"], ExitCode.USAGE, "exactly one"),
        (["evaluate", "{out}"], ExitCode.USAGE, "--gt GTFILE or --gt-topic"),
        (
            ["evaluate", "{out}", "--gt", "{gt}", "--gt-topic", POSES, "--radius", "2"],
            ExitCode.USAGE,
            "exactly one of --gt",
        ),
        (["evaluate", "{out}", "--gt-topic", POSES], ExitCode.USAGE, "needs --radius"),
        (["evaluate", "{out}", "--gt", "{gt}", "--radius", "2"], ExitCode.USAGE, "--radius"),
        (["evaluate", "{out}", "--gt", "{gt}", "--set", "kappa_s=1"], ExitCode.USAGE, "--set"),
        (["evaluate", "{out}", "--gt", "{gt}", "--fps", "2"], ExitCode.USAGE, "--fps"),
        (["evaluate", "{out}", "--gt", "{gt}", "--tolerance", "-1"], ExitCode.USAGE, "tolerance"),
        (
            ["evaluate", "{out}", "--gt", "{gt}", "--poses-topic", "/odom"],
            ExitCode.USAGE,
            "--plot",
        ),
        (
            ["evaluate", "--images", "/x", "--fps", "1", "--gt", "{gt}", "--plot", "/tmp/p"],
            ExitCode.USAGE,
            "only with an annotated log",
        ),
        (["evaluate", "--images", "/x", "--gt", "{gt}"], ExitCode.USAGE, "--fps"),
        (
            ["evaluate", "{out}", "--gt-topic", POSES, "--radius", "-1"],
            ExitCode.USAGE,
            "--radius must be",
        ),
        (
            ["evaluate", "{out}", "--gt-topic", "/nothing", "--radius", "2"],
            ExitCode.UNREADABLE_INPUT,
            "'/nothing' is not in the log",
        ),
        (
            ["evaluate", "{out}", "--gt-topic", "/camera/camera_info", "--radius", "2"],
            ExitCode.UNREADABLE_INPUT,
            "not a supported pose type",
        ),
        (["evaluate", "/no/such.mcap", "--gt", "{gt}"], ExitCode.UNREADABLE_INPUT, "such.mcap"),
        (["evaluate", "{log}", "--gt", "{gt}"], ExitCode.UNREADABLE_INPUT, "not annotated"),
    ],
)
def test_errors_are_one_line_with_their_exit_code(annotated, capsys, argv, code, message) -> None:
    out, _ = annotated
    argv = [a.format(out=out, gt=GT, log=LOG) for a in argv]
    got, _, err = run_cli(capsys, *argv)
    assert got == code, err
    assert err.count("\n") == 1 and err.startswith("doseqslam-logs: error: ") and message in err


def test_plot_without_matplotlib_is_a_usage_error(annotated, capsys, monkeypatch, tmp_path) -> None:
    out, _ = annotated
    monkeypatch.delitem(sys.modules, "doseqslam_logs.evaluation.plots", raising=False)
    # Every matplotlib module: cached submodules (an earlier test drew pictures) would
    # otherwise still import.
    hidden = [name for name in sys.modules if name.split(".")[0] == "matplotlib"]
    for name in {"matplotlib", *hidden}:
        monkeypatch.setitem(sys.modules, name, None)  # importing it raises ImportError
    code, stdout, err = run_cli(capsys, "evaluate", out, "--gt", GT, "--plot", tmp_path / "p")
    assert code == ExitCode.USAGE and "doseqslam-logs[plot]" in err and stdout == "", err
    assert not (tmp_path / "p").exists()


# -- the pose ground-truth math -----------------------------------------------------------


def brute_force_cells(times, xyz, criteria, yaw) -> set[tuple[int, int]]:
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xyz, axis=0), axis=1))])
    cells = set()
    for i in range(len(times)):
        for j in range(i):
            if np.linalg.norm(xyz[i] - xyz[j]) > criteria.radius_m:
                continue
            if times[i] - times[j] < round(criteria.min_age_s * 1e9):
                continue
            turn = abs((yaw[i] - yaw[j] + math.pi) % (2 * math.pi) - math.pi)
            if criteria.max_heading_deg is not None and turn > math.radians(
                criteria.max_heading_deg
            ):
                continue
            if criteria.min_travel_m is not None and travelled[i] - travelled[j] < (
                criteria.min_travel_m
            ):
                continue
            cells.add((i, j))
    return cells


@settings(max_examples=150, deadline=None)
@given(
    data=st.data(),
    n=st.integers(0, 40),
    radius=st.floats(0.1, 3.0),
    age=st.floats(0.0, 5.0),
    heading=st.one_of(st.none(), st.floats(0.0, 180.0)),
    travel=st.one_of(st.none(), st.floats(0.0, 10.0)),
    batch=st.integers(1, 50),
)
def test_loop_cells_match_brute_force(data, n, radius, age, heading, travel, batch) -> None:
    coordinate = st.floats(-3.0, 3.0, allow_nan=False)
    xyz = np.array(
        data.draw(st.lists(st.tuples(coordinate, coordinate, coordinate), min_size=n, max_size=n)),
        dtype=np.float64,
    ).reshape(n, 3)
    steps = data.draw(st.lists(st.integers(0, 2_000_000_000), min_size=n, max_size=n))
    times = np.cumsum(np.array(steps, dtype=np.int64))
    yaw = np.array(data.draw(st.lists(st.floats(-4.0, 4.0), min_size=n, max_size=n)))
    criteria = LoopCriteria(radius, age, heading, travel)
    rows, cols = loop_cells(times, xyz, criteria, yaw, batch_neighbours=batch)
    got = list(zip(rows.tolist(), cols.tolist(), strict=True))
    assert got == sorted(got)  # row-major order, no duplicates
    assert set(got) == brute_force_cells(times, xyz, criteria, yaw) and len(got) == len(set(got))


@settings(max_examples=100, deadline=None)
@given(
    data=st.data(),
    n=st.integers(0, 30),
    heading=st.one_of(st.none(), st.floats(0.0, 180.0)),
    travel=st.one_of(st.none(), st.floats(0.0, 6.0)),
    batch=st.integers(1, 40),
    tolerance=st.integers(0, 3),
)
def test_pose_ground_truth_answers_as_its_cells(data, n, heading, travel, batch, tolerance) -> None:
    """Answered from the poses, it says what the matrix of every cell says, pair by pair."""
    coordinate = st.floats(-2.0, 2.0, allow_nan=False)
    xyz = np.array(
        data.draw(st.lists(st.tuples(coordinate, coordinate, coordinate), min_size=n, max_size=n)),
        dtype=np.float64,
    ).reshape(n, 3)
    if n:
        xyz[data.draw(st.lists(st.integers(0, n - 1), max_size=3))] = np.nan  # no pose
    times = np.cumsum(np.array(data.draw(st.lists(st.integers(0, 10**9), min_size=n, max_size=n))))
    yaw = np.array(data.draw(st.lists(st.floats(-4.0, 4.0), min_size=n, max_size=n)))
    poses = FramePoses(times.astype(np.int64), xyz, yaw, np.isfinite(xyz).all(axis=1))
    criteria = LoopCriteria(1.5, 1.0, heading, travel)
    truth = PoseGroundTruth(poses, criteria, batch_neighbours=batch)
    rows, cols = loop_cells(times, xyz, criteria, yaw)
    cells = GroundTruth(n, rows, cols)
    assert truth.nnz == cells.nnz and truth.n_loop_events == cells.n_loop_events
    assert np.array_equal(truth.query_rows(), cells.query_rows())
    if n:
        q = np.array(data.draw(st.lists(st.integers(0, n - 1), max_size=20)), dtype=np.int64)
        m = np.array(data.draw(st.lists(st.integers(0, n - 1), min_size=q.size, max_size=q.size)))
        assert np.array_equal(truth.are_true(q, m, tolerance), cells.are_true(q, m, tolerance))
    with pytest.raises(GroundTruthError, match="outside"):
        truth.is_true(n, 0)


def test_pose_ground_truth_holds_no_loop_cells() -> None:
    """A camera parked for 2,000 frames revisits itself in 2 million cells (the 8-hour
    generated log: 240 million): the ground truth's memory follows the frames, not them."""
    import tracemalloc

    n = 2_000
    poses = FramePoses(
        np.arange(n, dtype=np.int64) * 10**8, np.zeros((n, 3)), np.zeros(n), np.ones(n, bool)
    )
    tracemalloc.start()
    try:
        truth = PoseGroundTruth(poses, LoopCriteria(2.0, 0.0), batch_neighbours=1 << 15)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert truth.nnz == n * (n - 1) // 2 and truth.n_loop_events == n - 1
    assert truth.is_true(n - 1, 0) and not truth.is_true(0, 1)
    assert peak < 8 << 20  # every cell held (loop_cells into a GroundTruth): 76 MB


def test_frames_without_a_pose_have_no_loop() -> None:
    times = np.arange(6, dtype=np.int64) * 10**9
    xyz = np.zeros((6, 3))
    xyz[2] = np.nan
    rows, cols = loop_cells(times, xyz, LoopCriteria(1.0, 2.0))
    assert 2 not in rows and 2 not in cols
    assert set(zip(rows.tolist(), cols.tolist(), strict=True)) == {
        (i, j) for i in range(6) for j in range(i - 1) if 2 not in (i, j)
    }


@given(yaw=st.floats(-math.pi + 1e-9, math.pi), scale=st.floats(0.1, 10.0))
def test_yaw_from_quaternions_inverts_a_rotation_about_z(yaw, scale) -> None:
    quaternion = scale * np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])
    assert yaw_from_quaternions(quaternion)[0] == pytest.approx(yaw, abs=1e-9)


def test_frame_times_follow_the_runs_clock() -> None:
    frame_times = FrameTimes([100, 200, 300, 400], [150, -1, 0, 450])
    assert frame_times.detector_times_ns("header").tolist() == [150, 200, 300, 450]
    assert frame_times.detector_times_ns("log").tolist() == [100, 200, 300, 400]


def test_criteria_are_checked() -> None:
    from doseqslam_logs.errors import UsageError

    for bad in ({"radius_m": 0.0}, {"max_heading_deg": 200.0}, {"min_travel_m": -1.0}):
        with pytest.raises(UsageError):
            LoopCriteria(**{"radius_m": 1.0, "min_age_s": 1.0, **bad})
