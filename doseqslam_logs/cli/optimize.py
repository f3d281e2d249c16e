"""`doseqslam-logs optimize OUT.mcap --odometry-topic T -o OPT.mcap`: the pose graph optimized
and written back into the log as /doseqslam/optimized_pose.

GTSAM is the optional extra `gtsam`; without it the command exits 2 naming it. docs/export.md
("Optimizing the pose graph") describes the graph, the robust kernel and the outlier check.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..export.base import (
    DEFAULT_KERNEL_WIDTH,
    DEFAULT_LOOP_KERNEL,
    DEFAULT_OUTLIER_BOUND,
    LOOP_KERNELS,
    OPTIMIZED_POSE_TOPIC,
    OptimizeOptions,
)
from .export import add_pose_graph_options, pose_graph_options, positive_float


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "optimize",
        help="optimize the pose graph (GTSAM) and write it back as a pose topic",
        description="Build the pose graph of `export --format g2o`, optimize it with "
        "Levenberg-Marquardt (robust loop edges, outlier check) and write the annotated log's "
        f"records plus {OPTIMIZED_POSE_TOPIC}. Needs the gtsam extra. docs/export.md.",
    )
    parser.add_argument("log", type=Path, metavar="OUT.mcap", help="an annotated MCAP (or sidecar)")
    parser.add_argument(
        "-o", "--output", type=Path, required=True, metavar="OPT.mcap", help="written atomically"
    )
    add_pose_graph_options(parser)
    parser.add_argument(
        "--loop-kernel",
        choices=LOOP_KERNELS,
        default=DEFAULT_LOOP_KERNEL,
        help=f"robust kernel on loop edges (default {DEFAULT_LOOP_KERNEL}; none: least squares)",
    )
    parser.add_argument(
        "--kernel-width",
        type=positive_float,
        default=DEFAULT_KERNEL_WIDTH,
        metavar="W",
        help=f"the kernel's width in sigmas of the loop edge (default {DEFAULT_KERNEL_WIDTH:g})",
    )
    parser.add_argument(
        "--outlier-bound",
        type=positive_float,
        default=DEFAULT_OUTLIER_BOUND,
        metavar="CHI2",
        help="drop loop edges whose squared Mahalanobis error after optimizing exceeds this, "
        f"and optimize again (default {DEFAULT_OUTLIER_BOUND:g}: chi-square, 6 dof, 99 %%)",
    )
    parser.add_argument(
        "--no-outlier-check", action="store_true", help="keep every loop edge (kernel only)"
    )
    parser.add_argument(
        "--no-odometry-calibration",
        action="store_true",
        help="take the odometry as stated (default: its heading drift and covariance factor "
        "calibrated from the metric loop edges; docs/export.md)",
    )
    parser.add_argument("--json", action="store_true", help="the summary as one JSON object")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ..export.optimize import optimize_log  # the pose graph: SciPy, not for --help

    options = pose_graph_options(args)
    optimize_options = OptimizeOptions(
        loop_kernel=args.loop_kernel,
        kernel_width=args.kernel_width,
        outlier_check=not args.no_outlier_check,
        outlier_bound=args.outlier_bound,
        calibrate_odometry=not args.no_odometry_calibration,
    )
    result = optimize_log(args.log, args.output, options, optimize_options)
    print(json.dumps(result.to_json()) if args.json else result.summary)
    return 0
