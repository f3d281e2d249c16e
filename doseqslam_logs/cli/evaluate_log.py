"""`doseqslam-logs evaluate OUT.mcap`: score the run an annotated log records, draw it."""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import UsageError
from .progress import Progress

# The log's evaluation (ground truth: OpenCV, SciPy) is imported when it runs, not for --help.
if TYPE_CHECKING:
    from ..evaluation.log_run import LogEvaluationOptions

# Options of the annotated-log mode, by argparse destination, as the user spells them.
_LOG_OPTIONS = {
    "gt_topic": "--gt-topic",
    "radius": "--radius",
    "max_heading": "--max-heading",
    "min_travel": "--min-travel",
    "poses_topic": "--poses-topic",
    "source": "--source",
    "no_source_check": "--no-source-check",
    "plot": "--plot",
}
_PARAMETER_OPTIONS = {"config": "--config", "method": "--method", "overrides": "--set"}


def add_log_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group(
        "annotated log (OUT.mcap)",
        "The run's parameters come from the log; --config, --method and --set do not apply.",
    )
    add_pose_truth_options(group)
    group.add_argument(
        "--poses-topic",
        metavar="TOPIC",
        help="pose topic for the trajectory picture (default: --gt-topic)",
    )
    group.add_argument(
        "--source",
        type=Path,
        metavar="LOG",
        help="the log that was annotated, to read images and poses from when OUT.mcap is a "
        "sidecar (its sha256 must match the one recorded)",
    )
    add_source_check_option(group)
    group.add_argument(
        "--plot",
        type=Path,
        metavar="DIR",
        help="write pr_curve.png, difference_matrix.png and, with a pose topic, "
        "trajectory.png into DIR (needs matplotlib: pip install 'doseqslam-logs[plot]')",
    )


def add_source_check_option(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--no-source-check: take a given source log although it is not the annotated one."""
    parser.add_argument(
        "--no-source-check",
        action="store_true",
        help="use the given log even when its sha256 is not the one recorded at annotation "
        "(e.g. a log rewritten since; its times and topics must still be the annotated log's)",
    )


def add_truth_file_options(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--gt, --gt-variable, --tolerance: a ground-truth matrix and how a match is counted
    (evaluate's, for an image folder and a log; diff's)."""
    parser.add_argument(
        "--gt",
        type=Path,
        metavar="GTFILE",
        help="ground-truth matrix (.mat, .bmp/.png, .npy/.npz), one row per frame",
    )
    parser.add_argument(
        "--gt-variable", metavar="NAME", help="variable inside a .mat/.npz (default: the only one)"
    )
    parser.add_argument(
        "--tolerance",
        type=int,
        default=0,
        metavar="K",
        help="count a match within +-K frames of a ground-truth cell (default 0)",
    )


def add_pose_truth_options(group: argparse._ArgumentGroup) -> None:
    """--gt-topic and its revisit criteria (evaluate OUT.mcap's; diff's)."""
    group.add_argument(
        "--gt-topic",
        metavar="TOPIC",
        help="ground truth from this pose topic of the log (Odometry, PoseStamped, "
        "PoseWithCovarianceStamped, foxglove.PoseInFrame) instead of --gt",
    )
    group.add_argument(
        "--radius",
        type=float,
        metavar="R",
        help="with --gt-topic: frames within R metres of an earlier frame at least kappa_s "
        "seconds older revisit it",
    )
    group.add_argument(
        "--max-heading",
        type=float,
        metavar="DEG",
        help="with --gt-topic: and their yaws differ by at most DEG degrees",
    )
    group.add_argument(
        "--min-travel",
        type=float,
        metavar="M",
        help="with --gt-topic: and the camera moved at least M metres in between (a parked "
        "camera does not revisit itself)",
    )


def log_only_options(args: argparse.Namespace) -> list[str]:
    """The annotated-log options given on the command line."""
    return [flag for name, flag in _LOG_OPTIONS.items() if getattr(args, name) not in (None, False)]


def _check_log_args(args: argparse.Namespace) -> None:
    if args.fps is not None:
        raise UsageError("--fps: only with --images")
    parameters = [flag for name, flag in _PARAMETER_OPTIONS.items() if getattr(args, name)]
    if parameters:
        raise UsageError(
            f"{', '.join(parameters)}: the run's parameters come from {args.log}; "
            "detector options apply to --images only"
        )


def run_log(args: argparse.Namespace) -> int:
    from ..evaluation.log_run import evaluate_log

    _check_log_args(args)
    progress = Progress(None, "evaluate")  # a line per stage, off a terminal past QUIET_S
    try:
        report = evaluate_log(args.log, _options(args), stage=progress.started)
    finally:
        progress.close()
    if args.json:
        print(json.dumps(report.to_json_dict(), indent=2))
    else:
        print(report.format_report())
    return 0


def _options(args: argparse.Namespace) -> LogEvaluationOptions:
    from ..evaluation.log_run import LogEvaluationOptions

    names = [f.name for f in dataclasses.fields(LogEvaluationOptions) if f.name != "source_check"]
    return LogEvaluationOptions(
        **{name: getattr(args, name) for name in names}, source_check=not args.no_source_check
    )
