"""`doseqslam-logs annotate LOG -o OUT.mcap`: replay the detector and write the annotated log."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..annotate import AnnotateOptions, annotate_log, expected_frames
from .params_args import add_parameter_options, parameters_from_args
from .progress import Progress
from .times import parse_time_ns


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "annotate",
        help="replay the detector over a log and write it back with loop closures",
        description="Replay the detector over the camera channel of LOG and write OUT.mcap: "
        "every record of the input unchanged, plus /doseqslam/loop_closures, "
        "/doseqslam/sequences and a 'doseqslam' metadata record.",
    )
    parser.add_argument("log", type=Path, help="MCAP file, ROS 1 .bag, rosbag2 folder or .db3")
    parser.add_argument("-o", "--output", type=Path, required=True, metavar="OUT.mcap")
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
        type=parse_time_ns,
        metavar="TIME",
        help="first log time to use (ns since the epoch, or RFC 3339)",
    )
    parser.add_argument(
        "-E",
        "--end",
        type=parse_time_ns,
        metavar="TIME",
        help="log time to stop before (ns since the epoch, or RFC 3339)",
    )
    parser.add_argument(
        "--on-error",
        choices=["skip", "fail"],
        default="skip",
        help="an undecodable image or a frame stamped before the previous one: skip and count "
        "it (default) or stop with an error",
    )
    parser.add_argument(
        "--sidecar",
        action="store_true",
        help="write only our channels and metadata, not the input's records",
    )
    add_parameter_options(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    params = parameters_from_args(args)
    options = AnnotateOptions(
        topic=args.topic,
        time_source=args.time_source,
        start_ns=args.start,
        end_ns=args.end,
        on_error=args.on_error,
        sidecar=args.sidecar,
    )
    progress = Progress(expected_frames(args.log, args.topic), "annotate")
    try:
        result = annotate_log(args.log, args.output, params, options, progress)
    finally:
        progress.close()
    replay = result.replay
    skipped = result.counts.skipped_total
    reasons = ", ".join(f"{n} {why}" for why, n in sorted(result.counts.skipped.items()))
    print(
        f"{result.output_path}: {replay.frames} frames of {result.topic}, "
        f"{len(replay.decisions)} sequences, {replay.loop_closures} loop closures, "
        f"{skipped} skipped frames{f' ({reasons})' if reasons else ''}, "
        f"{replay.wall_time_s:.1f} s, {replay.frames_per_second:.0f} frames/s"
    )
    return 0
