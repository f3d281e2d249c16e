"""`doseqslam-logs evaluate OUT.mcap`: score the run an annotated log records, draw it."""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from .. import __version__
from ..annotations.reader import NOT_REPORTED, AnnotatedLog, read_annotations
from ..errors import UsageError
from ..evaluation.groundtruth import GroundTruth, load_ground_truth
from ..evaluation.pose_ground_truth import (
    FramePoses,
    LoopCriteria,
    frame_pose_times,
    frame_poses,
    pose_ground_truth,
)
from ..evaluation.recorded_run import (
    LogEvaluation,
    evaluate_annotated_log,
    format_log_report,
    matched_index,
)
from ..pipeline.annotate import source_sha256
from ..sources import open_source
from ..sources.poses import PoseTrack, read_poses

# Options of the annotated-log mode, by argparse destination, as the user spells them.
_LOG_OPTIONS = {
    "gt_topic": "--gt-topic",
    "radius": "--radius",
    "max_heading": "--max-heading",
    "min_travel": "--min-travel",
    "poses_topic": "--poses-topic",
    "source": "--source",
    "plot": "--plot",
}
_PARAMETER_OPTIONS = {"config": "--config", "method": "--method", "overrides": "--set"}


def add_log_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group(
        "annotated log (OUT.mcap)",
        "The run's parameters come from the log; --config, --method and --set do not apply.",
    )
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
    group.add_argument(
        "--plot",
        type=Path,
        metavar="DIR",
        help="write pr_curve.png, difference_matrix.png and, with a pose topic, "
        "trajectory.png into DIR (needs matplotlib: pip install 'doseqslam-logs[plot]')",
    )


def log_only_options(args: argparse.Namespace) -> list[str]:
    """The annotated-log options given on the command line."""
    return [flag for name, flag in _LOG_OPTIONS.items() if getattr(args, name) is not None]


def _check_log_args(args: argparse.Namespace) -> None:
    if args.fps is not None:
        raise UsageError("--fps: only with --images")
    parameters = [flag for name, flag in _PARAMETER_OPTIONS.items() if getattr(args, name)]
    if parameters:
        raise UsageError(
            f"{', '.join(parameters)}: the run's parameters come from {args.log}; "
            "detector options apply to --images only"
        )
    if (args.gt is None) == (args.gt_topic is None):
        raise UsageError("evaluate OUT.mcap needs exactly one of --gt GTFILE or --gt-topic TOPIC")
    if args.gt_topic is not None and args.radius is None:
        raise UsageError("--gt-topic needs --radius R (metres)")
    pose_only = [
        flag
        for name, flag in _LOG_OPTIONS.items()
        if name in ("radius", "max_heading", "min_travel") and getattr(args, name) is not None
    ]
    if args.gt_topic is None and pose_only:
        raise UsageError(f"{', '.join(pose_only)}: only with --gt-topic")
    if args.gt_topic is not None and args.gt_variable is not None:
        raise UsageError("--gt-variable: only with --gt")
    if args.poses_topic is not None and args.plot is None:
        raise UsageError("--poses-topic only draws the trajectory: use it with --plot DIR")


def _plots_module() -> ModuleType:
    """doseqslam_logs.evaluation.plots, or a usage error when matplotlib is not installed."""
    try:
        # Through sys.modules, not the package attribute `from .. import plots` would return
        # once the module was imported (a test that removes matplotlib relies on that).
        return importlib.import_module("doseqslam_logs.evaluation.plots")
    except ImportError as exc:
        raise UsageError(
            f"--plot needs matplotlib ({exc}): pip install 'doseqslam-logs[plot]'"
        ) from exc


def _content_log(args: argparse.Namespace, log: AnnotatedLog) -> Path:
    """The log that holds the images and poses: --source, else OUT.mcap when it is a full copy."""
    if args.source is not None:
        recorded = log.metadata.get("source_sha256", "")
        if recorded and source_sha256(args.source) != recorded:
            raise UsageError(
                f"{args.source}: not the log {args.log} was annotated from "
                f"({log.metadata.get('source_file', '?')}, sha256 differs)"
            )
        return Path(args.source)
    topic = log.metadata.get("image_topic", "")
    with open_source(args.log) as source:
        topics = {channel.topic for channel in source.channels()}
    if topic not in topics:
        raise UsageError(
            f"{args.log}: holds only the annotations (a sidecar?): give the annotated log "
            "with --source LOG"
        )
    return Path(args.log)


class _Inputs:
    """What the ground truth and the pictures need, each read once and only when needed."""

    def __init__(self, args: argparse.Namespace, log: AnnotatedLog) -> None:
        self.args, self.log = args, log
        self._content: Path | None = None
        self._tracks: dict[str, PoseTrack] = {}
        self.frame_poses: FramePoses | None = None

    @property
    def content(self) -> Path:
        if self._content is None:
            self._content = _content_log(self.args, self.log)
        return self._content

    def track(self, topic: str) -> PoseTrack:
        if topic not in self._tracks:
            self._tracks[topic] = read_poses(self.content, topic)
        return self._tracks[topic]

    def poses_at_frames(self, topic: str) -> FramePoses:
        if self.log.frame_times is None:
            raise UsageError(
                f"{self.log.path}: annotated by an older version without frame times; "
                "annotate the log again to use its poses"
            )
        times = frame_pose_times(self.log.frame_times, self.log.metadata.get("time_source", ""))
        return frame_poses(self.track(topic), times)


def _ground_truth(inputs: _Inputs) -> tuple[GroundTruth, dict[str, Any]]:
    args, log = inputs.args, inputs.log
    if args.gt is not None:
        gt = load_ground_truth(args.gt, args.gt_variable)
        return gt, {"kind": "file", "file": str(args.gt), "variable": gt.variable}
    kappa = float(log.parameters.get("kappa_s", 0.0))
    criteria = LoopCriteria(args.radius, kappa, args.max_heading, args.min_travel)
    poses = inputs.poses_at_frames(args.gt_topic)
    inputs.frame_poses = poses
    name = f"{args.gt_topic} ({criteria.describe()})"
    gt = pose_ground_truth(poses, criteria, source=name)
    info = {
        "kind": "poses",
        "topic": args.gt_topic,
        "radius_m": args.radius,
        "max_heading_deg": args.max_heading,
        "min_age_s": kappa,
        "min_travel_m": args.min_travel,
        "frames_without_pose": int(np.count_nonzero(~poses.has_pose)),
    }
    return gt, info


def _renamed(result: LogEvaluation, name: str) -> LogEvaluation:
    """Name the pose ground truth by its topic and criteria (not a file name)."""
    raw = dataclasses.replace(result.raw, gt_file=name)
    verified = result.verified and dataclasses.replace(result.verified, gt_file=name)
    return LogEvaluation(raw, verified)


def run_log(args: argparse.Namespace) -> int:
    _check_log_args(args)
    plots = _plots_module() if args.plot is not None else None  # fail before the work
    log = read_annotations(args.log)
    inputs = _Inputs(args, log)
    gt, gt_info = _ground_truth(inputs)
    result = evaluate_annotated_log(log, gt, args.tolerance)
    if gt_info["kind"] == "poses":
        result = _renamed(result, gt.source)
    written: list[str] = []
    if plots is not None:
        written = [str(p) for p in _draw(plots, inputs, gt, result)]
    if args.json:
        print(json.dumps(_json_document(log, gt_info, result, written), indent=2))
    else:
        print(_headline(log))
        print(format_log_report(result))
        for path in written:
            print(f"wrote {path}")
    return 0


def _headline(log: AnnotatedLog) -> str:
    meta = log.metadata
    return (
        f"{meta.get('method', '?')} run recorded in {log.path} (source {meta.get('source_file')}, "
        f"{meta.get('image_topic')}, parameters {meta.get('parameters_hash')}, annotated by "
        f"doseqslam-logs {meta.get('tool_version')})"
    )


def _json_document(
    log: AnnotatedLog, gt_info: dict[str, Any], result: LogEvaluation, plots: list[str]
) -> dict[str, Any]:
    meta = log.metadata
    return {
        "tool_version": __version__,
        "log": str(log.path),
        "annotated_by": meta.get("tool_version"),
        "source_file": meta.get("source_file"),
        "image_topic": meta.get("image_topic"),
        "time_source": meta.get("time_source"),
        "method": meta.get("method"),
        "parameters_hash": meta.get("parameters_hash"),
        "parameters": log.parameters,
        "verification": meta.get("verification", "off"),
        "ground_truth": gt_info,
        **result.raw.to_json_dict(),
        "verified": None if result.verified is None else result.verified.to_json_dict(),
        "plots": plots,
    }


# -- pictures -----------------------------------------------------------------------------


def _detections(plots: ModuleType, log: AnnotatedLog, gt: GroundTruth, tolerance: int) -> list[Any]:
    """Every pair on /doseqslam/loop_closures, true or false (rejected ones marked so)."""
    pairs = [(int(lc["query_index"]), matched_index(lc)) for lc in log.loop_closures]
    truth = gt.are_true([q for q, _ in pairs], [m for _, m in pairs], tolerance)
    detections = []
    for lc, (query, match), true in zip(log.loop_closures, pairs, truth, strict=True):
        verdict = lc.get("verification")
        status = verdict if verdict in NOT_REPORTED else ("tp" if true else "fp")
        detections.append(plots.Detection(query, match, status))
    return detections


def _draw(plots: ModuleType, inputs: _Inputs, gt: GroundTruth, result: LogEvaluation) -> list[Path]:
    from ..evaluation.difference_matrix import difference_matrix

    args, log = inputs.args, inputs.log
    folder: Path = args.plot
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"{folder}: cannot create the picture folder ({exc.strerror})") from exc
    meta = log.metadata
    title = (
        f"{log.path.name} | {meta.get('image_topic')} | parameters {meta.get('parameters_hash')}"
    )
    detections = _detections(plots, log, gt, args.tolerance)
    written = [plots.plot_pr_curve(folder / "pr_curve.png", result.raw, result.verified, title)]
    matrix = difference_matrix(inputs.content, log)
    written.append(
        plots.plot_difference_matrix(
            folder / "difference_matrix.png", matrix, detections, gt, title
        )
    )
    topic = args.poses_topic or args.gt_topic
    if topic is not None:
        poses = inputs.frame_poses if topic == args.gt_topic else None
        poses = poses or inputs.poses_at_frames(topic)
        track = inputs.track(topic)
        written.append(
            plots.plot_trajectory(
                folder / "trajectory.png",
                track.positions,
                poses.positions,
                detections,
                title,
                topic,
            )
        )
    return written
