"""Scoring the run an annotated log records against ground truth, and drawing it
(`evaluate OUT.mcap`): no detector run, the decisions come from /doseqslam/sequences.

Ground truth is a matrix file (`gt`) or comes from a pose topic of the log (`gt_topic` with
`radius`, optional `max_heading` and `min_travel`); a sidecar reads its images and poses from
`source`, the log it was annotated from.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from .. import __version__
from ..annotations.reader import AnnotatedLog, read_annotations
from ..annotations.source_check import check_source_log
from ..errors import UsageError
from ..sinks.atomic import check_output_path
from ..sources import open_source
from ..sources.poses import PoseTrack, read_poses
from .groundtruth import LoopTruth, load_ground_truth
from .metrics import Evaluation
from .pose_ground_truth import (
    FramePoses,
    LoopCriteria,
    frame_poses,
    pose_ground_truth,
)
from .recorded_run import LogEvaluation, evaluate_annotated_log, format_log_report


@dataclass(frozen=True)
class LogEvaluationOptions:
    """What `evaluate OUT.mcap` takes besides the log (the command's options, same names)."""

    gt: Path | None = None  # a ground-truth matrix file, or:
    gt_variable: str | None = None
    gt_topic: str | None = None  # a pose topic, with the revisit criteria below
    radius: float | None = None
    max_heading: float | None = None
    min_travel: float | None = None
    tolerance: int = 0
    source: Path | None = None  # the annotated log's source (for a sidecar)
    source_check: bool = True  # refuse a `source` that is not the annotated log's
    plot: Path | None = None  # folder for the pictures (needs matplotlib)
    poses_topic: str | None = None  # the trajectory picture's topic (default gt_topic)


@dataclass(frozen=True)
class LogReport:
    """The figures of one annotated log, and the pictures written."""

    log: AnnotatedLog
    ground_truth: dict[str, Any]  # what the ground truth was (kind, file or topic, criteria)
    result: LogEvaluation
    plots: list[Path]
    truth: LoopTruth  # what `result` was scored against (diff labels pairs with it)

    @property
    def reported(self) -> Evaluation:
        """The figures of the loop closures the run reports: the verified ones when it
        verified its pairs, else every accepted candidate."""
        return self.result.verified or self.result.raw

    def format_report(self) -> str:
        """The `evaluate OUT.mcap` report: headline, figures, pictures written."""
        lines = [_headline(self.log), *_feature_warnings(self.log), format_log_report(self.result)]
        return "\n".join(lines + [f"wrote {path}" for path in self.plots])

    def to_json_dict(self) -> dict[str, Any]:
        """The `evaluate OUT.mcap --json` document."""
        return _json_document(
            self.log, self.ground_truth, self.result, [str(p) for p in self.plots]
        )


def evaluate_log(
    log: AnnotatedLog | str | Path,
    options: LogEvaluationOptions | None = None,
    stage: Callable[[str], None] | None = None,
) -> LogReport:
    """Score the run recorded in an annotated log (or sidecar; a path, or already read)
    against ground truth, and draw it when `options.plot` names a folder, as `evaluate
    OUT.mcap` does. `stage(name)` as each part begins: "read" (the annotations), "truth"
    (the ground truth: its file, or the pose topic read and its loops found), "score", "draw".

    Raises UsageError (no ground truth, a sidecar without source, matplotlib missing for
    plots, ...), SourceError (not an annotated log), GroundTruthError.
    """
    began = stage or (lambda name: None)
    options = options or LogEvaluationOptions()
    check_options(options)
    plots = _plots_module() if options.plot is not None else None  # fail before the work
    began("read")
    annotated = log if isinstance(log, AnnotatedLog) else read_annotations(log)
    inputs = _Inputs(options, annotated)
    began("truth")
    gt, gt_info = _ground_truth(inputs)
    began("score")
    result = evaluate_annotated_log(annotated, gt, options.tolerance)
    if gt_info["kind"] == "poses":
        result = _renamed(result, gt.source)
    written: list[Path] = []
    if plots is not None:
        began("draw")
        written = _draw(plots, inputs, gt, result)
    return LogReport(annotated, gt_info, result, written, gt)


# The pose ground truth's criteria, by option name, as the command spells them.
_POSE_CRITERIA = {
    "radius": "--radius",
    "max_heading": "--max-heading",
    "min_travel": "--min-travel",
}


def check_options(options: LogEvaluationOptions) -> None:
    """Raises UsageError for options that do not go together (named as the command spells
    them: the library's names are the same, with underscores)."""
    if (options.gt is None) == (options.gt_topic is None):
        raise UsageError("give exactly one of --gt GTFILE or --gt-topic TOPIC")
    if options.gt_topic is not None and options.radius is None:
        raise UsageError("--gt-topic needs --radius R (metres)")
    criteria = [flag for name, flag in _POSE_CRITERIA.items() if getattr(options, name) is not None]
    if options.gt_topic is None and criteria:
        raise UsageError(f"{', '.join(criteria)}: only with --gt-topic")
    if options.gt_topic is not None and options.gt_variable is not None:
        raise UsageError("--gt-variable: only with --gt")
    if options.poses_topic is not None and options.plot is None:
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


def _content_log(options: LogEvaluationOptions, log: AnnotatedLog) -> Path:
    """The log that holds the images and poses: --source, else OUT.mcap when it is a full copy."""
    if options.source is not None:
        if options.source_check:
            check_source_log(log, Path(options.source), "--source")
        return Path(options.source)
    topic = log.metadata.image_topic
    with open_source(log.path) as source:
        topics = {channel.topic for channel in source.channels()}
    if topic not in topics:
        raise UsageError(
            f"{log.path}: holds only the annotations (a sidecar?): give the annotated log "
            "with --source LOG"
        )
    return Path(log.path)


class _Inputs:
    """What the ground truth and the pictures need, each read once and only when needed."""

    def __init__(self, options: LogEvaluationOptions, log: AnnotatedLog) -> None:
        self.options, self.log = options, log
        self._content: Path | None = None
        self._tracks: dict[str, PoseTrack] = {}
        self.frame_poses: FramePoses | None = None

    @property
    def content(self) -> Path:
        if self._content is None:
            self._content = _content_log(self.options, self.log)
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
        times = self.log.frame_times.detector_times_ns(self.log.metadata.time_source)
        return frame_poses(self.track(topic), times)


def _ground_truth(inputs: _Inputs) -> tuple[LoopTruth, dict[str, Any]]:
    options, log = inputs.options, inputs.log
    if options.gt is not None:
        gt = load_ground_truth(options.gt, options.gt_variable)
        return gt, {"kind": "file", "file": str(options.gt), "variable": gt.variable}
    topic, radius = options.gt_topic, options.radius
    assert topic is not None and radius is not None  # evaluate_log checked them
    kappa = float(log.parameters.get("kappa_s", 0.0))
    criteria = LoopCriteria(radius, kappa, options.max_heading, options.min_travel)
    poses = inputs.poses_at_frames(topic)
    inputs.frame_poses = poses
    name = f"{options.gt_topic} ({criteria.describe()})"
    truth = pose_ground_truth(poses, criteria, source=name)
    info = {
        "kind": "poses",
        "topic": options.gt_topic,
        "radius_m": options.radius,
        "max_heading_deg": options.max_heading,
        "min_age_s": kappa,
        "min_travel_m": options.min_travel,
        "frames_without_pose": int(np.count_nonzero(~poses.has_pose)),
    }
    return truth, info


def _renamed(result: LogEvaluation, name: str) -> LogEvaluation:
    """Name the pose ground truth by its topic and criteria (not a file name)."""
    raw = dataclasses.replace(result.raw, gt_file=name)
    verified = result.verified and dataclasses.replace(result.verified, gt_file=name)
    return LogEvaluation(raw, verified)


def _headline(log: AnnotatedLog) -> str:
    meta = log.metadata
    return (
        f"{meta.method} run recorded in {log.path} (source {meta.source_file}, "
        f"{meta.image_topic}, parameters {meta.parameters_hash}, annotated by "
        f"doseqslam-logs {meta.tool_version})"
    )


def _feature_warnings(log: AnnotatedLog) -> list[str]:
    """The run's feature-poor warnings, as annotate recorded them (none for a healthy run)."""
    poor = log.metadata.feature_poor
    return [f"WARNING: {text}" for text in poor.get("warnings", [])] + (
        [f"         {poor['advice']}"] if poor.get("advice") else []
    )


def _json_document(
    log: AnnotatedLog, gt_info: dict[str, Any], result: LogEvaluation, plots: list[str]
) -> dict[str, Any]:
    meta = log.metadata
    return {
        "tool_version": __version__,
        "log": str(log.path),
        "annotated_by": meta.tool_version,
        "source_file": meta.source_file,
        "image_topic": meta.image_topic,
        "time_source": meta.time_source,
        "method": meta.method,
        "parameters_hash": meta.parameters_hash,
        "parameters": log.parameters,
        "verification": meta.verification,
        "feature_poor": meta.feature_poor or None,
        "ground_truth": gt_info,
        **result.raw.to_json_dict(),
        "verified": None if result.verified is None else result.verified.to_json_dict(),
        "plots": plots,
    }


# -- pictures -----------------------------------------------------------------------------


def detections(plots: ModuleType, log: AnnotatedLog, gt: LoopTruth, tolerance: int) -> list[Any]:
    """Every pair decided on, true or false (rejected and skipped ones, on
    /doseqslam/candidates, marked so)."""
    pairs = [(lc.query.index, lc.matched.index) for lc in log.loop_closures]
    truth = gt.are_true([q for q, _ in pairs], [m for _, m in pairs], tolerance)
    found = []
    for lc, (query, match), true in zip(log.loop_closures, pairs, truth, strict=True):
        status = lc.verification if not lc.reported else ("tp" if true else "fp")
        found.append(plots.Detection(query, match, status))
    return found


PICTURES = ("pr_curve.png", "difference_matrix.png", "trajectory.png")


def _draw(plots: ModuleType, inputs: _Inputs, gt: LoopTruth, result: LogEvaluation) -> list[Path]:
    from .difference_matrix import difference_matrix

    options, log = inputs.options, inputs.log
    folder = options.plot
    assert folder is not None
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"{folder}: cannot create the picture folder ({exc.strerror})") from exc
    for name in PICTURES:  # before drawing any: none is written if one cannot be
        check_output_path(folder / name)
    meta = log.metadata
    title = f"{log.path.name} | {meta.image_topic} | parameters {meta.parameters_hash}"
    marked = detections(plots, log, gt, options.tolerance)
    written = [plots.plot_pr_curve(folder / "pr_curve.png", result.raw, result.verified, title)]
    matrix = difference_matrix(inputs.content, log)
    written.append(
        plots.plot_difference_matrix(folder / "difference_matrix.png", matrix, marked, gt, title)
    )
    topic = options.poses_topic or options.gt_topic
    if topic is not None:
        poses = inputs.frame_poses if topic == options.gt_topic else None
        poses = poses or inputs.poses_at_frames(topic)
        track = inputs.track(topic)
        written.append(
            plots.plot_trajectory(
                folder / "trajectory.png",
                track.positions,
                poses.positions,
                marked,
                title,
                topic,
            )
        )
    return written
