"""`doseqslam-logs annotate LOG -o OUT.mcap`: replay the detector and write the annotated log."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..sinks.output_format import CHUNK_SIZE, COMPRESSIONS, OutputFormat
from ..sources.image_header import DEFAULT_MAX_PIXELS
from ..verification.summary import verification_summary
from .params_args import (
    add_parameter_options,
    add_verification_options,
    intrinsics_from_args,
    run_parameters,
    verification_from_args,
)
from .progress import Progress
from .times import time_argument

# The pipeline (OpenCV, SciPy, faiss) is imported when a run starts: parsing the arguments,
# --help and a usage error do not pay for it.
if TYPE_CHECKING:
    from ..pipeline.annotate import AnnotateOptions, AnnotateResult


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "annotate",
        help="replay the detector over a log and write it back with loop closures",
        description="Replay the detector over the camera channel of LOG and write OUT.mcap: "
        "every record of the input unchanged, plus /doseqslam/loop_closures (the reported loop "
        "closures), /doseqslam/candidates (the pairs verification rejected or skipped), "
        "/doseqslam/sequences and a 'doseqslam' metadata record.",
    )
    parser.add_argument("log", type=Path, help="MCAP file, ROS 1 .bag, rosbag2 folder or .db3")
    parser.add_argument("-o", "--output", type=Path, required=True, metavar="OUT.mcap")
    add_run_options(parser)
    parser.add_argument(
        "--json",
        action="store_true",
        help="print the run's counts as one JSON object instead of the summary line",
    )
    parser.add_argument(
        "--workers",
        type=positive_int,
        default=2,
        metavar="N",
        help="threads that prepare frames (features) ahead of the detector (default 2); the "
        "output is the same for any N",
    )
    parser.set_defaults(run=run)


def add_run_options(parser: argparse.ArgumentParser) -> None:
    """Every option of a run but the input, the output and --workers (annotate and batch)."""
    parser.add_argument("--topic", help="camera topic (needed when the log has several)")
    parser.add_argument(
        "--time-source",
        choices=["header", "log"],
        default="header",
        help="time the detector uses: the image header stamp (default; a zero stamp falls "
        "back to the log time) or the log time",
    )
    parser.add_argument(
        "-S",
        "--start",
        type=time_argument,
        metavar="TIME",
        help="first log time to use (ns since the epoch, or RFC 3339)",
    )
    parser.add_argument(
        "-E",
        "--end",
        type=time_argument,
        metavar="TIME",
        help="log time to stop before (ns since the epoch, or RFC 3339)",
    )
    parser.add_argument(
        "--on-error",
        choices=["skip", "fail"],
        default="skip",
        help="an undecodable image or a frame stamped before the previous one: skip and count "
        "it (default) or stop with an error (exit code 5)",
    )
    parser.add_argument(
        "--recover",
        action="store_true",
        help="MCAP input cut short or with corrupt chunks: use every complete message it still "
        "holds (copied first into a temporary file beside the output) instead of failing",
    )
    add_max_pixels_option(parser)
    parser.add_argument(
        "--sidecar",
        action="store_true",
        help="write only our channels and metadata, not the input's records",
    )
    parser.add_argument(
        "--compression",
        choices=sorted(COMPRESSIONS),
        default="zstd",
        help="the output's chunk compression (default zstd)",
    )
    parser.add_argument(
        "--chunk-size",
        type=positive_int,
        default=CHUNK_SIZE,
        metavar="BYTES",
        help=f"the output's chunk size, before compression (default {CHUNK_SIZE})",
    )
    parser.add_argument(
        "--no-visualization",
        dest="visualization",
        action="store_false",
        help="leave out the channels Foxglove draws (match images, image texts, 3-D lines)",
    )
    parser.add_argument(
        "--odometry-topic",
        metavar="TOPIC",
        help="with verification: the pose topic the motion rule reads and whose odometry gives "
        "accepted pairs a metric pose when the log has no depth topic (default: the first "
        "nav_msgs/Odometry topic, else the first topic of another pose type; 'none': no "
        "odometry, images for the motion rule, rotation only)",
    )
    add_parameter_options(parser)
    add_verification_options(parser)


def add_max_pixels_option(parser: argparse.ArgumentParser) -> None:
    """--max-pixels (annotate, batch, evaluate): the pixel cap checked before decoding."""
    parser.add_argument(
        "--max-pixels",
        type=positive_int,
        default=DEFAULT_MAX_PIXELS,
        metavar="N",
        help="skip (count as 'too large') an image whose header claims more than N pixels, "
        f"before decoding it (default {DEFAULT_MAX_PIXELS} = 8192x8192)",
    )


def annotate_options_from_args(args: argparse.Namespace, workers: int) -> AnnotateOptions:
    """The AnnotateOptions of the options add_run_options defines."""
    from ..pipeline.annotate import AnnotateOptions

    return AnnotateOptions(
        topic=args.topic,
        time_source=args.time_source,
        start_ns=args.start,
        end_ns=args.end,
        on_error=args.on_error,
        sidecar=args.sidecar,
        recover=args.recover,
        workers=workers,
        verification=verification_from_args(args),
        intrinsics=intrinsics_from_args(args),
        max_pixels=args.max_pixels,
        visualization=args.visualization,
        output_format=OutputFormat(args.compression, args.chunk_size),
        odometry_topic="" if args.odometry_topic == "none" else args.odometry_topic,
    )


def summary_line(result: AnnotateResult) -> str:
    """The one line printed on success: frames, decisions, every skipped frame by reason, and
    what clock jumps, missing stamps and --recover did."""
    replay, counts = result.replay, result.counts
    by_reason = counts.skipped_by_reason()
    reasons = ", ".join(f"{n} {why}" for why, n in by_reason.items())
    notes = []
    if counts.log_time_fallbacks:
        notes.append(f"{counts.log_time_fallbacks} frames without header stamp used the log time")
    if counts.clock_jumps:
        notes.append(f"{counts.clock_jumps} camera clock jumps bridged with the log time")
    if result.recovery is not None and result.recovery.damaged:
        notes.append(f"recovered: {result.recovery.describe()}")
    if result.promise is not None:
        notes.append(f"{result.promise.count} image messages promised by {result.promise.origin}")
    if result.unattributed:
        notes.append(f"{result.unattributed} messages of undeclared topics (never readable)")
    verification = result.verification
    if verification is not None:
        stats = verification.stats
        pose = f"essential matrix, intrinsics from {verification.intrinsics_source}"
        if verification.intrinsics_assumed:
            pose = "essential matrix, assumed intrinsics"
        model = pose if verification.intrinsics else "fundamental matrix, no intrinsics"
        motion = verification.motion_summary
        checked = verification_summary(stats, verification.wall_s, model, motion)
        notes.insert(0, f"verified {stats.candidates} candidate pairs: {checked}")
        if verification.metric is not None:
            metric = verification.metric.stats
            notes.insert(1, f"metric poses of {metric.summary()}, {metric.wall_s:.1f} s")
    if result.health is not None and result.health.poor:
        notes.append(f"WARNING: {result.health.note()}")
    return (
        f"{result.output_path}: {replay.frames} frames of {result.topic}, "
        f"{len(replay.decisions)} sequences, {result.loop_closures} loop closures, "
        f"{counts.skipped_total} skipped frames{f' ({reasons})' if reasons else ''}, "
        f"{replay.wall_time_s:.1f} s, {replay.frames_per_second:.0f} frames/s"
        + "".join(f"; {note}" for note in notes)
    )


def result_json(result: AnnotateResult) -> dict[str, object]:
    """The summary line's figures for machines: every image message accounted for (promised,
    used, skipped by reason) and what --recover read."""
    counts, promise = result.counts, result.promise
    return {
        "output": str(result.output_path),
        "input": str(result.input_path),
        "topic": result.topic,
        "frames": result.replay.frames,
        "sequences": len(result.replay.decisions),
        "loop_closures": result.loop_closures,
        "image_messages": counts.messages,
        "image_messages_promised": None if promise is None else promise.count,
        "image_messages_promised_by": None if promise is None else promise.origin,
        "frames_used": counts.used,
        "frames_skipped": counts.skipped_total,
        "frames_skipped_by_reason": counts.skipped_by_reason(),
        "unattributed_messages": result.unattributed,
        "log_time_fallbacks": counts.log_time_fallbacks,
        "clock_jumps": counts.clock_jumps,
        "replay_wall_time_s": round(result.replay.wall_time_s, 3),
        "frames_per_second": round(result.replay.frames_per_second, 1),
        "recovered": None if result.recovery is None else result.recovery.as_metadata(),
        "features": None if result.health is None else result.health.to_json(),
        "verification": _verification_json(result),
        "metric": _metric_json(result),
    }


def _metric_json(result: AnnotateResult) -> dict[str, object] | None:
    """What the metric stage gave the accepted pairs (None without verification)."""
    verification = result.verification
    if verification is None or verification.metric is None:
        return None
    stats = verification.metric.stats
    return {
        "pairs": stats.pairs,
        "fitted": stats.fitted,
        "methods": {m or "none": n for m, n in sorted(stats.methods.items())},
        "odometry_topic": stats.odometry_topic or None,
        "odometry_skipped": dict(stats.odometry_skipped),
        "odometry_problem": stats.odometry_problem or None,
        "depth_topic": stats.depth_topic or None,
        "depth_messages": stats.depth_messages,
        "depth_skipped": dict(stats.depth_skipped),
        "wall_time_s": round(stats.wall_s, 3),
    }


def _verification_json(result: AnnotateResult) -> dict[str, object] | None:
    """What the verification stage decided (None when it was off)."""
    verification = result.verification
    if verification is None:
        return None
    stats = verification.stats
    return {
        "candidates": stats.candidates,
        "accepted": stats.accepted,
        "from_alternatives": stats.from_alternatives,
        "rejected_stationary": stats.stationary,
        "rejected_odometry_disagrees": stats.odometry_disagrees,
        "relocated": stats.relocated,
        "placed_unbracketed": stats.placed,
        "motion_evidence": verification.motion_summary,
        "skipped": stats.skipped,
        "frame_pairs": stats.pairs,
        "ms_per_pair": round(stats.ms_per_pair, 3),
        "wall_time_s": round(verification.wall_s, 3),
        "model": "essential" if verification.intrinsics else "fundamental",
        "intrinsics_source": verification.intrinsics_source,
    }


def warnings(result: AnnotateResult) -> list[str]:
    """The first example of each kind of skipped frame, of a clock jump, the feature-poor
    warnings and unusable intrinsics (for stderr)."""
    counts = result.counts
    lines = [f"skipped ({why}), first: {detail}" for why, detail in counts.first_skip.items()]
    if result.health is not None and result.health.poor:
        lines.append(result.health.note())
    verification = result.verification
    if verification is not None and verification.unusable_camera_info:
        k = verification.intrinsics
        how = (
            "verified with the fundamental matrix"
            if k is None
            else f"verified with an assumed pinhole camera (focal length {k.fx:g} px, the "
            "larger image side, principal point at the centre) and no metric poses"
        )
        lines.append(
            f"{verification.unusable_camera_info}; {how}; --intrinsics FX,FY,CX,CY gives the "
            "camera's"
        )
    if counts.first_clock_jump:
        lines.append(
            f"camera clock jump bridged with the log time, first: {counts.first_clock_jump} "
            "(--time-source log uses the log time throughout)"
        )
    return lines


def run(args: argparse.Namespace) -> int:
    from ..pipeline.annotate import annotate_log

    params = run_parameters(args)
    options = annotate_options_from_args(args, args.workers)
    progress = Progress(None, "annotate")

    def expected(total: int | None) -> None:
        progress.total = total

    try:
        result = annotate_log(
            args.log, args.output, params, options, progress, expected, observer=progress
        )
    finally:
        progress.close()
    for line in warnings(result):
        print(f"doseqslam-logs: warning: {args.log}: {' '.join(line.split())}", file=sys.stderr)
    print(json.dumps(result_json(result)) if args.json else summary_line(result))
    return 0
