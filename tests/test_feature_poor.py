"""Issue #22: a run on frames too small or too poor in features never looks like a run that
found nothing. The feature-poor logs are built here from a committed sample log, shrunk to
the 64x32 and 128x64 grey frames of thumbnail cameras (tools/shrink_log.py)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import pytest

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.cli.main import main
from doseqslam_logs.pipeline.feature_health import (
    CheckFeasibility,
    SegmentationFeatures,
    feature_health,
)

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "sample_logs"
sys.path.insert(0, str(REPO / "tools"))

import shrink_log  # noqa: E402

SEGMENTATION_WARNING = "WARNING: feature-poor frames: 240 of 240 frames (100 %)"
CHECKS_WARNING = "verification could not check"
ADVICE = "try --method seqslam --no-verify"


def cli(capsys: pytest.CaptureFixture[str], *args: str | Path) -> tuple[int, str]:
    code = main([str(arg) for arg in args])
    return code, capsys.readouterr().out


def cli_stderr(capsys: pytest.CaptureFixture[str], *args: str | Path) -> tuple[int, str]:
    code = main([str(arg) for arg in args])
    return code, capsys.readouterr().err


def small_log(tmp_path: Path, width: int, height: int) -> Path:
    """drive_loops (240 frames, 256x192 JPEG) as width x height mono8 frames."""
    out = tmp_path / f"drive_loops_{width}x{height}.mcap"
    frames = shrink_log.log_frames(SAMPLES / "drive_loops.ros2.mcap")
    assert shrink_log.write_small_log(frames, out, (width, height)) == 240
    return out


def test_64x32_frames_say_so_in_summary_json_and_metadata(tmp_path, capsys) -> None:
    log = small_log(tmp_path, 64, 32)
    out = tmp_path / "out.mcap"
    code, line = cli(capsys, "annotate", log, "-o", out)
    assert code == 0
    assert "0 loop closures" in line  # the silent zero of the issue ...
    assert SEGMENTATION_WARNING in line  # ... is no longer silent
    assert "median 0 a frame at 64x32" in line and ADVICE in line

    code, err = cli_stderr(capsys, "annotate", log, "-o", out, "--json")
    assert f"doseqslam-logs: warning: {log}: feature-poor frames: 240 of 240" in err
    code, text = cli(capsys, "annotate", log, "-o", out, "--json")
    features = json.loads(text)["features"]
    assert features["feature_poor"] is True
    assert (features["frames_below_need"], features["frames_measured"]) == (240, 240)
    assert features["advice"].startswith(ADVICE)

    recorded = read_annotations(out).metadata.feature_poor
    assert recorded["feature_poor"] is True
    assert recorded["warnings"] == features["warnings"]


def test_impossible_checks_are_named_not_counted_as_rejections(tmp_path, capsys) -> None:
    # A 20-frame cap makes sequences, hence candidates: every one has too few features.
    log = small_log(tmp_path, 128, 64)
    out = tmp_path / "out.mcap"
    code, line = cli(capsys, "annotate", log, "-o", out, "--set", "max_sequence_length=20")
    assert code == 0
    assert f"{CHECKS_WARNING} 60 of the 60 candidate pairs it tried (100 %" in line
    assert "12 of the 12 sequences end only at the 20-frame cap" in line
    code, report = cli(capsys, "evaluate", out, "--gt", SAMPLES / "drive_loops.gt.npz")
    assert code == 0
    assert SEGMENTATION_WARNING in report and CHECKS_WARNING in report and ADVICE in report
    code, text = cli(capsys, "evaluate", out, "--gt", SAMPLES / "drive_loops.gt.npz", "--json")
    assert json.loads(text)["feature_poor"]["checks_too_few_features"] == 60


@pytest.mark.parametrize(
    "log", ["drive_loops.ros2.mcap", "drive_parked.ros2.mcap", "drive_varrate.bag"]
)
def test_committed_sample_logs_are_not_feature_poor(log, tmp_path, capsys) -> None:
    out = tmp_path / "out.mcap"
    code, text = cli(capsys, "annotate", SAMPLES / log, "-o", out, "--json")
    assert code == 0
    assert json.loads(text)["features"]["feature_poor"] is False
    metadata = read_annotations(out).metadata
    assert "feature_poor" not in metadata.recorded  # a healthy run's record keeps its bytes
    code, report = cli(capsys, "evaluate", out, "--gt", SAMPLES / f"{log.split('.')[0]}.gt.npz")
    assert "WARNING" not in report


def test_batch_names_the_feature_poor_log(tmp_path, capsys) -> None:
    inputs = tmp_path / "logs"
    inputs.mkdir()
    small_log(inputs, 64, 32)
    code, text = cli(capsys, "batch", inputs, "-o", tmp_path / "annotated", "-j", "1")
    assert code == 0
    assert SEGMENTATION_WARNING.removeprefix("WARNING: ") in text
    assert "drive_loops_64x32.mcap  (feature-poor" in text  # the summary table's row
    assert "1 too poor in features to trust a count of 0" in text
    manifest = (tmp_path / "annotated" / "manifest.jsonl").read_text().splitlines()
    assert ADVICE in json.loads(manifest[-1])["warning"]


def test_too_few_matches_alone_is_not_feature_poor() -> None:
    # A wrong candidate on healthy frames gives "too few matches": a check that worked.
    checks = CheckFeasibility.of(["too few matches"] * 9 + ["accepted"])
    assert (checks.checked, checks.too_few_matches, checks.poor) == (10, 9, False)
    reasons = ["too few features"] * 5 + ["not checked"] * 7 + ["too few inliers"] * 5
    impossible = CheckFeasibility.of(reasons, skipped=["not checked"])
    assert (impossible.checked, impossible.share, impossible.poor) == (10, 0.5, True)


def test_a_method_without_feature_segmentation_is_not_measured() -> None:
    unmeasured = SegmentationFeatures.of("none", 10, [-1, -1, -1], "64x32")
    health = feature_health(unmeasured, None, [3], 300, 0)
    assert (unmeasured.frames, health.poor, health.note()) == (0, False, "")


def test_evaluate_images_on_64x32_rtabmap_frames_says_so(shared_data, tmp_path, capsys) -> None:
    rtabmap = shared_data / "rtabmap_samples_loop"
    folder = tmp_path / "rtabmap_64x32"
    folder.mkdir()
    for _, gray in shrink_log.folder_frames(rtabmap / "images", 1.0):
        name = folder / f"{len(list(folder.iterdir())) + 1}.png"
        cv2.imwrite(str(name), shrink_log.shrink_gray(gray, 64, 32))
    args = ["evaluate", "--images", folder, "--fps", "1", "--gt", rtabmap / "samples_GT.bmp"]
    code, report = cli(capsys, *args)
    assert code == 0
    assert "WARNING: feature-poor frames: 84 of 84 frames (100 %)" in report and ADVICE in report
    code, text = cli(capsys, *args, "--json")
    assert json.loads(text)["features"]["feature_poor"] is True
