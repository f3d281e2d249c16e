"""`doseqslam-logs evaluate`: score a run against ground truth.

Two modes, exactly one per call:
* `evaluate --images DIR --fps F --gt GT`: replay the detector on an image folder;
* `evaluate OUT.mcap (--gt GT | --gt-topic TOPIC --radius R)`: score the run an annotated log
  records, from its /doseqslam/sequences, without re-running the detector (optionally with
  pictures, `--plot DIR`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from .. import __version__
from ..detector import make_detector
from ..errors import GroundTruthError, UsageError
from ..evaluation.groundtruth import load_ground_truth
from ..evaluation.metrics import evaluate, format_report
from ..replay import replay
from ..sources.folder import folder_frames, list_images
from . import evaluate_log
from .params_args import add_parameter_options, parameters_from_args
from .progress import Progress


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "evaluate",
        help="score the detector against ground truth: on an image folder, or the run an "
        "annotated log records",
        description="Report TP, FP, precision and recall at the decision threshold, the highest "
        "recall at 100%% precision (R@P100) and the threshold that gives it, and recall at "
        "precision >= 0.9. Either replay the detector over a folder of images (--images, natural "
        "file-name order, stamped at --fps), or read the run recorded in an annotated log "
        "(OUT.mcap: no detector run; ground truth from a file, --gt, or from a pose topic of the "
        "log, --gt-topic with --radius).",
    )
    parser.add_argument(
        "log", type=Path, nargs="?", metavar="OUT.mcap", help="annotated log (or sidecar)"
    )
    parser.add_argument("--images", type=Path, metavar="DIR", help="image folder")
    parser.add_argument("--fps", type=float, help="frame rate of the folder (with --images)")
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
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    evaluate_log.add_log_options(parser)
    add_parameter_options(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if (args.log is None) == (args.images is None):
        raise UsageError(
            "evaluate needs exactly one of an annotated log (OUT.mcap) or --images DIR"
        )
    if args.tolerance < 0:
        raise UsageError(f"--tolerance must be >= 0, got {args.tolerance}")
    if args.log is not None:
        return evaluate_log.run_log(args)
    return _run_images(args)


def _check_images_args(args: argparse.Namespace) -> None:
    if args.fps is None:
        raise UsageError("--images needs --fps")
    if args.gt is None:
        raise UsageError("--images needs --gt GTFILE")
    used = evaluate_log.log_only_options(args)
    if used:
        raise UsageError(f"{', '.join(used)}: only with an annotated log (OUT.mcap)")


def _run_images(args: argparse.Namespace) -> int:
    _check_images_args(args)
    params = parameters_from_args(args)
    gt = load_ground_truth(args.gt, args.gt_variable)
    total = len(list_images(args.images))
    if total != gt.n_frames:  # checked before the run: a wrong GT file is the usual cause
        raise GroundTruthError(
            f"{args.gt}: ground truth has {gt.n_frames} frames but {args.images} has {total} images"
        )
    detector = make_detector(params)
    progress = Progress(total, "evaluate")
    try:
        result = replay(folder_frames(args.images, args.fps), detector, progress)
    finally:
        progress.close()
    evaluation = evaluate(result.decisions, gt, params.threshold, args.tolerance)
    header: dict[str, Any] = {
        "tool_version": __version__,
        "images": str(args.images),
        "fps": args.fps,
        "method": params.method,
        "feature_detector": result.feature_detector,
        "parameters_hash": params.hash,
        "wall_time_s": round(result.wall_time_s, 3),
    }
    if args.json:
        print(
            json.dumps(
                {**header, "parameters": params.to_dict(), **evaluation.to_json_dict()}, indent=2
            )
        )
    else:
        print(
            f"{params.method} on {args.images} at {args.fps:g} fps "
            f"(features: {result.feature_detector}, parameters {params.hash}, "
            f"{result.frames_per_second:.0f} frames/s)"
        )
        print(format_report(evaluation))
    return 0
