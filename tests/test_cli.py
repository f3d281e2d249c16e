"""The command line: real output, exit codes, one-line errors without tracebacks."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from golden import RTABMAP_FRAMES, RTABMAP_LOOP_EVENTS

from doseqslam_logs.cli.main import main
from doseqslam_logs.errors import ExitCode


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def rtabmap_args(shared_data) -> list[str]:
    folder = shared_data / "rtabmap_samples_loop"
    return ["--images", folder / "images", "--fps", "1", "--gt", folder / "samples_GT.bmp"]


def test_evaluate_json_reports_the_rtabmap_figures(shared_data, capsys) -> None:
    # The detector's own figures (--no-verify); the verified ones: test_evaluate_images_verified.
    code, out, _ = run_cli(
        capsys,
        "evaluate",
        *rtabmap_args(shared_data),
        "--set",
        "kappa_s=10",
        "--json",
        "--no-verify",
    )
    assert code == 0
    doc = json.loads(out)
    assert doc["gt_loop_events"] == RTABMAP_LOOP_EVENTS and doc["frames"] == RTABMAP_FRAMES
    assert doc["parameters"]["kappa_s"] == 10.0
    assert doc["tp"] + doc["fp"] >= 0 and 0 <= doc["precision"] <= 1
    assert doc["r_p100"] > 0 and doc["threshold_at_r_p100"] is not None
    # The threshold it names reproduces the figure.
    th = doc["threshold_at_r_p100"]
    code, out, _ = run_cli(
        capsys,
        "evaluate",
        *rtabmap_args(shared_data),
        "--set",
        "kappa_s=10",
        "--set",
        f"threshold={th}",
        "--json",
        "--no-verify",
    )
    again = json.loads(out)
    assert again["fp"] == 0 and again["recall"] == pytest.approx(doc["r_p100"])


def test_evaluate_text_report_names_method_and_gt(shared_data, capsys) -> None:
    code, out, _ = run_cli(
        capsys,
        "evaluate",
        *rtabmap_args(shared_data),
        "--method",
        "seqslam",
        "--set",
        "kappa_s=10",
        "--no-verify",
    )
    assert code == 0
    assert out.startswith("seqslam on ") and "samples_GT.bmp" in out and "R@P100" in out


@pytest.mark.parametrize(
    ("argv", "code", "message"),
    [
        (
            ["evaluate", "--images", "/nonexistent", "--fps", "1", "--gt", "x.npy"],
            ExitCode.USAGE,
            "x.npy",
        ),
        (
            ["evaluate", "--images", "/nonexistent", "--fps", "1", "--gt", "{gt}"],
            ExitCode.UNREADABLE_INPUT,
            "not a folder of images",
        ),
        (
            ["evaluate", "--images", "{img}", "--fps", "1", "--gt", "{gt}", "--set", "kapa=1"],
            ExitCode.USAGE,
            "unknown parameter",
        ),
        (
            ["evaluate", "--images", "{img}", "--fps", "1", "--gt", "{gt}", "--config", "/no.toml"],
            ExitCode.USAGE,
            "cannot read parameters",
        ),
        (["info", "/nonexistent.mcap"], ExitCode.UNREADABLE_INPUT, "nonexistent.mcap"),
        (["info", "{img}/1.jpg"], ExitCode.UNREADABLE_INPUT, "not a log"),
    ],
)
def test_errors_are_one_line_with_their_exit_code(shared_data, capsys, argv, code, message):
    folder = shared_data / "rtabmap_samples_loop"
    argv = [a.format(gt=folder / "samples_GT.bmp", img=folder / "images") for a in argv]
    got, _out, err = run_cli(capsys, *argv)
    assert got == code
    assert err.count("\n") == 1 and err.startswith("doseqslam-logs: error: ") and message in err
    assert "Traceback" not in err


def test_evaluate_refuses_ground_truth_of_another_size(shared_data, capsys) -> None:
    lip6_gt = shared_data / "lip6_outdoor" / "ground_truth" / "groundTruthLip6O.mat"
    folder = shared_data / "rtabmap_samples_loop"
    code, _, err = run_cli(
        capsys, "evaluate", "--images", folder / "images", "--fps", "1", "--gt", lip6_gt
    )
    assert code == ExitCode.USAGE
    assert "ground truth has 1063 frames but" in err and "has 84 images" in err


def test_info_lists_the_camera_channels_of_a_real_ros2_mcap(shared_data, capsys) -> None:
    log = shared_data / "rosbag2_mcap_rerun_sensor_msgs" / "rosbag2_2025_09_10-13_03_56_0.mcap"
    _code, out, _ = run_cli(capsys, "info", log, "--json")
    doc = json.loads(out)
    cams = {c["topic"]: c for c in doc["cameras"]}
    assert set(cams) == {"/image", "/compressed_image"}
    assert cams["/image"]["encoding"] == "rgb8" and cams["/image"]["resolution"] == "640x480"
    assert cams["/compressed_image"]["resolution"] == "640x480"
    assert len(doc["other_channels"]) == 30


def test_info_says_when_there_is_no_camera(shared_data, capsys) -> None:
    code, out, _ = run_cli(
        capsys, "info", shared_data / "ros1_bags_rosbagjs_turtlesim" / "example-lz4.bag"
    )
    assert code == 0 and "no camera channel" in out and "/turtle1/pose" in out


def test_console_script_runs(shared_data) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "doseqslam_logs.cli.main", "info", "/nonexistent.bag"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == ExitCode.UNREADABLE_INPUT and "Traceback" not in proc.stderr


def test_info_on_an_annotated_log_summarises_the_run_and_counts_one_camera(
    annotated_sample, capsys
) -> None:
    out_log = annotated_sample("drive_loops.ros2.mcap")
    code, out, _ = run_cli(capsys, "info", out_log, "--json")
    doc = json.loads(out)
    assert code == 0 and [c["topic"] for c in doc["cameras"]] == ["/camera/image/compressed"]
    assert "/doseqslam/match/image/compressed" in {c["topic"] for c in doc["other_channels"]}
    run = doc["doseqslam_run"]
    assert run["loop_closures"] == 83 and run["verification"] == "on"
    assert run["source_file"] == "drive_loops.ros2.mcap" and run["candidate_pairs"] >= 83
    assert run["odometry_topic"] == "/odom"
    code, text, _ = run_cli(capsys, "info", out_log)
    assert "1 camera channel(s)" in text and "annotated by doseqslam-logs" in text
    assert "from drive_loops.ros2.mcap, odometry /odom" in text
    assert "83 loop closures of" in text
    sample = Path(__file__).resolve().parents[1] / "sample_logs" / "drive_loops.ros2.mcap"
    _code, plain, _ = run_cli(capsys, "info", sample)
    assert "annotated by" not in plain
