#!/usr/bin/env python3
"""The pose-graph table of docs/export.md: annotate, export g2o, optimize with GTSAM, ATE.

For the three generated drifting drives (seeds 29, 2, 20, made like the test's) and the three
committed sample drives: annotate with the command's defaults, export `--format g2o
--odometry-topic /odom`, then the round trip tests/test_pose_graph.py asserts on
(tools/pose_graph_check.py: readG2o, a tight prior on the first pose, Levenberg-Marquardt, ATE
after rigid alignment against /ground_truth/pose). Needs the `gtsam` extra. About two minutes.

    python tools/pose_graph_table.py
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import pose_graph_check as check

from doseqslam_logs.annotations.reader import read_annotations

ROOT = Path(__file__).resolve().parent.parent

SAMPLES = ROOT / "sample_logs"
COMMITTED = [
    ("drive_loops (committed)", SAMPLES / "drive_loops.ros2.mcap"),
    ("drive_parked (committed)", SAMPLES / "drive_parked.ros2.mcap"),
    ("drive_varrate (committed)", SAMPLES / "drive_varrate.bag"),
]


def main() -> None:
    with tempfile.TemporaryDirectory() as scratch:
        root = Path(scratch)
        drifting = [(f"seed {s}", check.generate_drifting_drive(root, s)) for s in (29, 2, 20)]
        logs = drifting + COMMITTED
        print("| drive | loop edges | ATE before | ATE after | factor |")
        print("|---|---:|---:|---:|---:|")
        for name, log in logs:
            folder = root / f"out{len(list(root.iterdir()))}"
            folder.mkdir()
            paths = check.annotate_and_export(log, folder)
            before, after, _ = check.trajectory_errors(paths)
            edges = len(read_annotations(paths["annotated"]).reported_loop_closures)
            row = f"| {name} | {edges} | {before:.3f} m | {after:.3f} m | {before / after:.2f} |"
            print(row, flush=True)


if __name__ == "__main__":
    main()
