#!/usr/bin/env python3
"""The pose-graph table of docs/export.md: annotate, export g2o, optimize with GTSAM, ATE.

For the three generated drifting drives (seeds 29, 2, 20, made like the test's) and the three
committed sample drives: annotate with the command's defaults, export `--format g2o
--odometry-topic /odom`, then the round trip tests/test_pose_graph.py asserts on
(tools/pose_graph_check.py: readG2o, a tight prior on the first pose, Levenberg-Marquardt, ATE
after rigid alignment against /ground_truth/pose: plain least squares), and the `optimize`
command's optimization of the same graph (robust loop edges, outlier check; ATE and loop
edges rejected). A second table injects `--wrong N` wrong loop edges (random vertex pairs more
than 15 m apart) into each graph and compares plain least squares, each kernel alone, and each
kernel with the outlier check. Needs the `gtsam` extra. A few minutes.

    python tools/pose_graph_table.py [--wrong 5]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import pose_graph_check as check

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.export.gtsam_graph import OptimizeOptions

ROOT = Path(__file__).resolve().parent.parent

SAMPLES = ROOT / "sample_logs"
COMMITTED = [
    ("drive_loops (committed)", SAMPLES / "drive_loops.ros2.mcap"),
    ("drive_parked (committed)", SAMPLES / "drive_parked.ros2.mcap"),
    ("drive_varrate (committed)", SAMPLES / "drive_varrate.bag"),
]


# The second table's optimizations: least squares, each kernel alone, each with the check.
INJECTED = {
    "least squares": OptimizeOptions(loop_kernel="none", outlier_check=False),
    "check only": OptimizeOptions(loop_kernel="none"),
    "Huber": OptimizeOptions(loop_kernel="huber", outlier_check=False),
    "Cauchy": OptimizeOptions(loop_kernel="cauchy", outlier_check=False),
    "Huber + check": OptimizeOptions(loop_kernel="huber"),
    "Cauchy + check (default)": OptimizeOptions(),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--wrong", type=int, default=5, help="wrong loop edges to inject")
    args = parser.parse_args()
    graphs = []
    with tempfile.TemporaryDirectory() as scratch:
        root = Path(scratch)
        drifting = [(f"seed {s}", check.generate_drifting_drive(root, s)) for s in (29, 2, 20)]
        logs = drifting + COMMITTED
        print(
            "| drive | loop edges | ATE before | ATE after | factor "
            "| `optimize` ATE | factor | rejected |"
        )
        print("|---|---:|---:|---:|---:|---:|---:|---:|")
        for name, log in logs:
            folder = root / f"out{len(list(root.iterdir()))}"
            folder.mkdir()
            paths = check.annotate_and_export(log, folder)
            before, after, _ = check.trajectory_errors(paths)
            edges = len(read_annotations(paths["annotated"]).reported_loop_closures)
            graph, truth = check.pose_graph_and_truth(paths["annotated"])
            robust, rejected = check.robust_errors(graph, truth)
            graphs.append((name, graph, truth))
            row = (
                f"| {name} | {edges} | {before:.3f} m | {after:.3f} m | {before / after:.2f} "
                f"| {robust:.3f} m | {before / robust:.2f} | {rejected} |"
            )
            print(row, flush=True)
    print(f"\nWith {args.wrong} wrong loop edges injected: ATE (m), wrong edges rejected\n")
    print("| drive | " + " | ".join(INJECTED) + " |")
    print("|---|" + "---:|" * len(INJECTED))
    for name, graph, truth in graphs:
        wrong = check.with_wrong_loops(graph, truth, args.wrong)
        cells = []
        for options in INJECTED.values():
            ate, rejected = check.robust_errors(wrong, truth, options)
            cells.append(f"{ate:.3f}" + (f" ({rejected})" if options.outlier_check else ""))
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
