"""`doseqslam-logs evaluate`: score a run against ground truth.

Two modes, exactly one per call:
* `evaluate --images DIR --fps F --gt GT`: replay the detector on an image folder, then (unless
  --no-verify) verify its candidate pairs geometrically, and report raw and verified figures
  side by side;
* `evaluate OUT.mcap (--gt GT | --gt-topic TOPIC --radius R)`: score the run an annotated log
  records, from its /doseqslam/sequences, without re-running the detector (optionally with
  pictures, `--plot DIR`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..errors import UsageError
from ..sources.image_folder import FPS_MAX, FPS_MIN, check_fps
from . import evaluate_log
from .annotate import add_max_pixels_option
from .params_args import (
    add_parameter_options,
    add_verification_options,
    intrinsics_from_args,
    run_parameters,
    threshold_given,
    verification_from_args,
)
from .progress import Progress


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "evaluate",
        help="score the detector against ground truth: on an image folder, or the run an "
        "annotated log records",
        description="Report TP, FP, precision and recall at the decision threshold, the highest "
        "recall at 100%% precision (R@P100) and the threshold that gives it, and recall at "
        "precision >= 0.9. Either replay the detector over a folder of images (--images, natural "
        "file-name order, stamped at --fps; its candidate pairs are then verified geometrically, "
        "as annotate does, unless --no-verify), or read the run recorded in an annotated log "
        "(OUT.mcap: no detector run; ground truth from a file, --gt, or from a pose topic of the "
        "log, --gt-topic with --radius).",
    )
    parser.add_argument(
        "log", type=Path, nargs="?", metavar="OUT.mcap", help="annotated log (or sidecar)"
    )
    parser.add_argument("--images", type=Path, metavar="DIR", help="image folder")
    parser.add_argument(
        "--fps",
        type=frame_rate,
        help=f"frame rate of the folder (with --images; {FPS_MIN:g} to {FPS_MAX:g})",
    )
    evaluate_log.add_truth_file_options(parser)
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    add_max_pixels_option(parser)
    evaluate_log.add_log_options(parser)
    add_parameter_options(parser)
    add_verification_options(parser)  # --images only: a log records its own verification
    parser.set_defaults(run=run)


def frame_rate(text: str) -> float:
    """argparse type of --fps: a number check_fps accepts (else exit 2, argparse's message)."""
    try:
        return check_fps(float(text))
    except (ValueError, UsageError):
        raise argparse.ArgumentTypeError(
            f"must be a frame rate from {FPS_MIN:g} to {FPS_MAX:g}, got {text!r}"
        ) from None


def run(args: argparse.Namespace) -> int:
    if (args.log is None) == (args.images is None):
        raise UsageError(
            "evaluate needs exactly one of an annotated log (OUT.mcap) or --images DIR"
        )
    if args.tolerance < 0:
        raise UsageError(f"--tolerance must be >= 0, got {args.tolerance}")
    if args.log is not None:
        used = _verification_options_used(args)
        if used:
            raise UsageError(
                f"{', '.join(used)}: the run's verification comes from {args.log}; "
                "verification options apply to --images only"
            )
        return evaluate_log.run_log(args)
    return _run_images(args)


def _verification_options_used(args: argparse.Namespace) -> list[str]:
    used = [] if args.verify else ["--no-verify"]
    if args.intrinsics is not None:
        used.append("--intrinsics")
    if args.verification_overrides:
        used.append("--vset")
    return used


def _check_images_args(args: argparse.Namespace) -> None:
    if args.fps is None:
        raise UsageError("--images needs --fps")
    if args.gt is None:
        raise UsageError("--images needs --gt GTFILE")
    used = evaluate_log.log_only_options(args)
    if used:
        raise UsageError(f"{', '.join(used)}: only with an annotated log (OUT.mcap)")


def _run_images(args: argparse.Namespace) -> int:
    # Here, not above: the folder's run and ground truth import OpenCV and SciPy, which --help
    # need not.
    from ..evaluation.folder_run import evaluate_folder
    from ..evaluation.groundtruth import load_ground_truth

    _check_images_args(args)
    params = run_parameters(args)  # as annotate: th = VERIFIED_THRESHOLD unless given
    verification = verification_from_args(args)  # bad options fail before the run
    intrinsics = intrinsics_from_args(args)
    gt = load_ground_truth(args.gt, args.gt_variable)
    progress = Progress(None, "evaluate")

    def expected(images: int) -> None:
        progress.total = images

    try:
        run = evaluate_folder(
            args.images,
            args.fps,
            gt,
            params,
            verification,
            intrinsics,
            args.tolerance,
            progress=progress,
            expected=expected,
            max_pixels=args.max_pixels,
            stage=progress.started,
        )
    finally:
        progress.close()
    if args.json:
        print(json.dumps(run.to_json_dict(), indent=2))
    else:
        note = "given" if threshold_given(args) else "default with verification"
        print(run.format_report(note))
    return 0
