"""Issue #19: every output profile opens in a real viewer, the Foxglove Studio 1.48 web app
(npm @foxglove/studio-base's prebuilt bundle) in headless Chromium, with our topics listed
and no problem reported for them; and docs/foxglove_layout.json over an optimized log draws
the optimized and the odometry path, each in its colour.

Needs node, Chromium and the npm packages of tests/viewer/foxglove_check.cjs in
$DOSEQSLAM_VIEWER_MODULES (default ~/.cache/doseqslam-viewer); .ci/run installs them, and the
test is skipped with the reason when one is missing. Screenshots of every log (its Topics and
Problems tabs, and a loop closure in the Raw Messages panel) go to $DOSEQSLAM_VIEWER_SHOTS
when it is set (else into tmp_path).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from doseqslam_logs.cli.main import main

REPO = Path(__file__).resolve().parents[1]
DRIVER = REPO / "tests" / "viewer" / "foxglove_check.cjs"
MODULES = Path(
    os.environ.get("DOSEQSLAM_VIEWER_MODULES", Path.home() / ".cache" / "doseqslam-viewer")
)
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
NEEDED = ("playwright-core", "react", "react-dom", "@foxglove/studio-base")
# One input per output profile: ROS 2, ROS 1 (a .bag becomes a ros1-profile MCAP) and JSON
# (our channels of a foxglove-profile input with protobuf images).
PROFILES = {
    "ros2": "drive_loops.ros2.mcap",
    "ros1": "drive_loops.bag",
    "json": "drive_loops.foxglove.mcap",
}
OUR_TOPICS = (
    "/doseqslam/loop_closures",
    "/doseqslam/sequences",
    # The visualization channels (sinks.visualization): decoded by the viewer, no problem.
    "/doseqslam/match/image/compressed",
    "/doseqslam/match/annotations",
    "/doseqslam/markers",
    "/doseqslam/match/marker",
    "/doseqslam/loop_lines",
    "/doseqslam/current_pose",
)
LAYOUT = REPO / "docs" / "foxglove_layout.json"
# Where the layout screenshot is taken: 108 s of the 119.5 s drive, query frame 216 of a run
# of loop closures (its match, frame 88, is the one shown).
LOOP_CLOSURE_AT = 0.9
# 72 s: between the loop closures of 68 s and 75 s, where the match panel once went on
# showing the 68 s match.
BETWEEN_LOOPS_AT = 0.6025


def _missing() -> str:
    """Why the viewer cannot run here ("" when it can)."""
    if shutil.which("node") is None:
        return "node is not installed"
    if not Path(CHROMIUM).is_file():
        return f"no Chromium at {CHROMIUM} (apt-get install chromium)"
    absent = [name for name in NEEDED if not (MODULES / "node_modules" / name).is_dir()]
    if absent:
        return f"npm packages {absent} are not in {MODULES} (see .ci/run)"
    return ""


@pytest.mark.slow
@pytest.mark.skipif(bool(_missing()), reason=_missing() or "ready")
def test_every_output_profile_opens_in_foxglove_with_no_problem(
    tmp_path: Path, annotated_sample
) -> None:
    outputs = []
    for profile, name in PROFILES.items():
        output = tmp_path / f"{profile}.annotated.mcap"
        # --no-verify: the same schemas and channels, in a second instead of ten; the run's
        # shared output, under the name the driver reports.
        shutil.copyfile(annotated_sample(name, "--no-verify"), output)
        outputs.append(output)
    shots = Path(os.environ.get("DOSEQSLAM_VIEWER_SHOTS", tmp_path))
    shots.mkdir(parents=True, exist_ok=True)
    run = subprocess.run(
        ["node", str(DRIVER), str(MODULES), CHROMIUM, str(shots), *map(str, outputs)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    seen = [json.loads(line) for line in run.stdout.splitlines()]
    assert [Path(s["log"]).name for s in seen] == [o.name for o in outputs]
    for result in seen:
        assert set(OUR_TOPICS) <= set(result["topics"]), result
        ours = [line for line in result["problems"] if "/doseqslam/" in line]
        assert ours == [], result  # a problem names its topic: "Error in topic /doseqslam/..."
        assert "No problems found" in result["problems"], result
        assert result["errors"] == [], result
        # The Raw Messages panel decoded a loop closure, its times as {sec, nsec}.
        assert any(line.startswith("query_log_time") for line in result["message"]), result
        for tab in ("topics", "problems", "message"):
            assert (shots / f"{Path(result['log']).name}.{tab}.png").stat().st_size > 0


# The layout's colours of the optimized and the odometry path (docs/foxglove_layout.json), as
# the screenshot holds them (BGR): nothing else in the picture has either hue.
OPTIMIZED_BGR = (255, 0, 255)
ODOMETRY_BGR = (0, 176, 255)
# The inlier keypoints' colour (sinks.visualization.INLIER_COLOR, yellow), which the sample's
# camera images never have (their colours are far from saturated).
INLIERS_BGR = (0, 255, 255)
MATCH_ANNOTATIONS = "/doseqslam/match/image_annotations"
PATHS = ("/doseqslam/optimized_path", "/doseqslam/odometry_path")
# The current pose's arrow (#8000ff in the layout).
CURRENT_POSE_BGR = (255, 0, 128)


def pixels_of(
    screenshot: str | Path | np.ndarray[Any, Any], bgr: tuple[int, int, int], tolerance: int = 40
) -> int:
    """How many pixels of the screenshot (a file, or pixels of one) have the colour `bgr`,
    give or take `tolerance` per channel (antialiased edges blend with the background)."""
    image = screenshot
    if not isinstance(image, np.ndarray):
        image = cv2.imread(str(screenshot), cv2.IMREAD_COLOR)
        assert image is not None, screenshot
    near = np.abs(image.astype(np.int16) - np.array(bgr, np.int16)) <= tolerance
    return int(np.count_nonzero(near.all(axis=2)))


def centre_of(pixels: np.ndarray[Any, Any], bgr: tuple[int, int, int], tolerance: int = 40) -> Any:
    """The mean (x, y) of the pixels of the colour `bgr` (as `pixels_of`)."""
    near = np.abs(pixels.astype(np.int16) - np.array(bgr, np.int16)) <= tolerance
    ys, xs = np.nonzero(near.all(axis=2))
    return np.array([xs.mean(), ys.mean()])


def image_panel_pixels(seek: dict[str, Any], side: str = "match") -> np.ndarray[Any, Any]:
    """The screenshot's pixels of an Image panel: the top row's right canvas for the match,
    its left one for the query."""
    top = min(canvas["y"] for canvas in seek["canvases"])
    row = [c for c in seek["canvases"] if c["y"] == top]
    panel = max(row, key=lambda c: c["x"]) if side == "match" else min(row, key=lambda c: c["x"])
    x, y, width, height = (round(panel[k]) for k in ("x", "y", "width", "height"))
    screenshot = cv2.imread(seek["screenshot"])
    assert screenshot is not None, seek
    return np.asarray(screenshot[y : y + height, x : x + width])


def match_panel_pixels(seek: dict[str, Any]) -> np.ndarray[Any, Any]:
    return image_panel_pixels(seek, "match")


def below_image_panels(seek: dict[str, Any]) -> np.ndarray[Any, Any]:
    """The screenshot's pixels below the Image panels: the 3-D and Raw Messages panels (the
    images' keypoints, antialiased, blend into a few pixels of the paths' colours)."""
    top = min(canvas["y"] for canvas in seek["canvases"])
    bottom = max(round(c["y"] + c["height"]) for c in seek["canvases"] if c["y"] == top)
    screenshot = cv2.imread(seek["screenshot"])
    assert screenshot is not None, seek
    return np.asarray(screenshot[bottom:])


def shows_no_loop(panel: np.ndarray[Any, Any]) -> bool:
    """The grey "no loop" frame: its upper part one grey, its middle the white label."""
    height, width = panel.shape[:2]
    upper = panel[height // 10 : height * 3 // 10, width // 10 : width * 9 // 10]
    middle = panel[height * 4 // 10 : height * 6 // 10, width // 4 : width * 3 // 4]
    grey = abs(float(upper.mean()) - 128) < 4 and float(upper.std()) < 3
    return grey and bool((middle > 200).all(axis=2).any())


def open_in_layout(log: Path, shots: Path, seeks: str) -> dict[str, Any]:
    """The log in docs/foxglove_layout.json, seeked to each fraction of `seeks` in turn."""
    run = subprocess.run(
        ["node", str(DRIVER), str(MODULES), CHROMIUM, str(shots), "--layout", str(LAYOUT),
         seeks, str(log)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    [result] = [json.loads(line) for line in run.stdout.splitlines()]
    return dict(result)


@pytest.mark.slow
@pytest.mark.skipif(bool(_missing()), reason=_missing() or "ready")
def test_the_layout_shows_query_match_loop_lines_and_both_paths_with_no_problem(
    tmp_path: Path, annotated_sample
) -> None:
    """docs/foxglove_layout.json over `optimize` of the ROS 2 output of the `annotate`
    defaults, seeked to a loop closure and then between two: the run drives the viewer; the
    screenshot at the loop closure (docs/images/foxglove_loop_closure.png) is looked at. The
    current pose's arrow is where the robot is at each seek. The annotated log alone, without
    the paths, has neither path colour."""
    pytest.importorskip("gtsam")
    annotated, output = tmp_path / "ros2.annotated.mcap", tmp_path / "ros2.layout.mcap"
    shutil.copyfile(annotated_sample(PROFILES["ros2"]), annotated)  # the run's shared output
    assert main(["optimize", str(annotated), "-o", str(output)]) == 0
    shots = Path(os.environ.get("DOSEQSLAM_VIEWER_SHOTS", tmp_path))
    shots.mkdir(parents=True, exist_ok=True)
    result = open_in_layout(output, shots, f"{LOOP_CLOSURE_AT},{BETWEEN_LOOPS_AT}")
    # With verification the pairs it did not accept are on a topic of their own, and the match
    # image has annotations of its own.
    ours = {*OUR_TOPICS, *PATHS, "/doseqslam/candidates", MATCH_ANNOTATIONS}
    assert ours <= set(result["topics"]), result
    assert "No problems found" in result["problems"], result
    assert result["errors"] == [], result
    # The layout's panels are known (an unknown type says "Unknown panel type") and have data.
    assert not [line for line in result["problems"] if "Unknown panel" in line], result
    # After the seek to a loop closure both Image panels have an image, and the loop closure
    # of query frame 216 is in the Raw Messages panel.
    assert not [line for line in result["message"] if line.startswith("Waiting for")], result
    assert "216" in result["message"], result
    at_loop, between = result["seeks"]
    # What a user sees in the match panel: the match at the loop closure, and between loop
    # closures the grey "no loop" frame, not the last match.
    assert not shows_no_loop(match_panel_pixels(at_loop)), at_loop
    assert shows_no_loop(match_panel_pixels(between)), between
    # The inlier keypoints, in their colour, on both images at the loop closure (a point is a
    # dot of a dozen pixels or more at this zoom, and the pair has dozens), none between.
    for side in ("query", "match"):
        assert pixels_of(image_panel_pixels(at_loop, side), INLIERS_BGR) > 300, (side, at_loop)
        assert pixels_of(image_panel_pixels(between, side), INLIERS_BGR) < 20, (side, between)
    # The 3-D panel draws both paths, each in its colour: a line of the trajectory's length
    # (the drive spans about 20 m: each line covers thousands of pixels, the odometry, wider,
    # shows on both sides of the optimized one).
    assert pixels_of(below_image_panels(at_loop), OPTIMIZED_BGR) > 1000
    assert pixels_of(below_image_panels(at_loop), ODOMETRY_BGR) > 1000
    # The current pose's arrow, where the robot is at each seek: it moves between them (the
    # 108 s and the 72 s frames are on opposite sides of the drive).
    here, there = below_image_panels(at_loop), below_image_panels(between)
    assert pixels_of(here, CURRENT_POSE_BGR) > 60 and pixels_of(there, CURRENT_POSE_BGR) > 60
    moved = centre_of(here, CURRENT_POSE_BGR) - centre_of(there, CURRENT_POSE_BGR)
    assert np.hypot(*moved) > 50, moved
    # The same layout over the annotated log, which has no paths: neither colour.
    without = open_in_layout(annotated, shots, str(LOOP_CLOSURE_AT))
    assert "No problems found" in without["problems"], without
    [plain] = without["seeks"]
    assert pixels_of(below_image_panels(plain), OPTIMIZED_BGR) < 50
    assert pixels_of(below_image_panels(plain), ODOMETRY_BGR) < 50
