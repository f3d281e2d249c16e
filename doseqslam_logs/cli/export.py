"""`doseqslam-logs export OUT.mcap --format csv|jsonl|tum|g2o`: an annotated log for other tools.

The text goes to stdout, or with -o to a file that appears whole (atomic write); a line saying
what was written goes to stderr. docs/export.md describes every format and the g2o measurement
model.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path

from ..export import FORMATS, ExportOptions, export_log
from ..export.base import (
    DEFAULT_LOOP_ROTATION_SIGMA_DEG,
    DEFAULT_LOOP_TRANSLATION_SIGMA_M,
    LOOP_MODELS,
)
from .annotate import positive_int
from .evaluate_log import add_source_check_option


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    value = float(text)
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a number > 0, got {text}")
    return value


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    formats = "; ".join(f"{name}: {exporter.help}" for name, exporter in FORMATS.items())
    parser = subparsers.add_parser(
        "export",
        help="write the loop closures of an annotated log as csv, jsonl, tum or g2o",
        description=f"Export an annotated log for other tools. Formats: {formats}. "
        "Measurement model and columns: docs/export.md.",
    )
    parser.add_argument("log", type=Path, metavar="OUT.mcap", help="an annotated MCAP (or sidecar)")
    parser.add_argument("--format", required=True, choices=list(FORMATS), help="output format")
    parser.add_argument(
        "-o", "--output", type=Path, metavar="FILE", help="write here (atomically), not to stdout"
    )
    parser.add_argument(
        "--include-rejected",
        action="store_true",
        help="csv/jsonl: also the pairs verification rejected or skipped (column verification)",
    )
    parser.add_argument(
        "--calibrate-odometry",
        action="store_true",
        help="g2o: odometry edges calibrated from the metric loop edges (heading drift: a "
        "yaw-rate bias, and a yaw scale when the turns show one; a covariance factor), as "
        "optimize does by default; default: /odom as stated",
    )
    add_pose_graph_options(parser)
    parser.set_defaults(run=run)


def add_pose_graph_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--odometry-topic",
        metavar="TOPIC",
        help="tum/g2o: the pose topic (nav_msgs/Odometry, PoseStamped, "
        "PoseWithCovarianceStamped, foxglove.PoseInFrame) placed at the camera times "
        "(default: the one annotate picks: the first nav_msgs/Odometry topic, else the first "
        "of another pose type)",
    )
    parser.add_argument(
        "--poses-from",
        type=Path,
        metavar="LOG",
        help="tum/g2o: read the pose topic from this log (default: OUT.mcap itself; needed for "
        "a --sidecar output); it must be the log that was annotated (its sha256 is checked)",
    )
    add_source_check_option(parser)
    parser.add_argument(
        "--stride",
        type=positive_int,
        default=1,
        metavar="K",
        help="tum/g2o: keep every K-th frame, the first and last, and every loop-closure frame "
        "(default 1: all frames)",
    )
    parser.add_argument(
        "--loop-translation-sigma",
        type=positive_float,
        default=DEFAULT_LOOP_TRANSLATION_SIGMA_M,
        metavar="M",
        help="g2o: standard deviation of a loop edge's (zero) translation, metres "
        f"(default {DEFAULT_LOOP_TRANSLATION_SIGMA_M:g})",
    )
    parser.add_argument(
        "--loop-rotation-sigma",
        type=positive_float,
        default=DEFAULT_LOOP_ROTATION_SIGMA_DEG,
        metavar="DEG",
        help="g2o: standard deviation of a loop edge's rotation, degrees "
        f"(default {DEFAULT_LOOP_ROTATION_SIGMA_DEG:g})",
    )
    parser.add_argument(
        "--identity-loop-rotation",
        action="store_true",
        help="g2o: identity rotation on every loop edge, even when verification recorded one",
    )
    parser.add_argument(
        "--loop-model",
        choices=LOOP_MODELS,
        default="metric",
        help="loop edges: the metric pose recorded on the pair, the placeholder model where "
        "none was (metric, the default), or the placeholder model for every edge",
    )


def pose_graph_options(args: argparse.Namespace, include_rejected: bool = False) -> ExportOptions:
    """The ExportOptions of the arguments `add_pose_graph_options` added (export, optimize)."""
    return ExportOptions(
        include_rejected=include_rejected,
        odometry_topic=args.odometry_topic,
        poses_log=args.poses_from,
        poses_log_check=not args.no_source_check,
        stride=args.stride,
        loop_translation_sigma_m=args.loop_translation_sigma,
        loop_rotation_sigma_deg=args.loop_rotation_sigma,
        use_verified_rotation=not args.identity_loop_rotation,
        loop_model=args.loop_model,
    )


def run(args: argparse.Namespace) -> int:
    options = replace(
        pose_graph_options(args, args.include_rejected), calibrate_odometry=args.calibrate_odometry
    )
    result = export_log(args.log, args.format, options, args.output)
    if args.output is None:
        for chunk in result.chunks:
            sys.stdout.write(chunk)
        sys.stdout.flush()
    print(f"{args.output or args.format}: {result.summary}", file=sys.stderr)
    return 0
