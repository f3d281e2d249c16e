"""`doseqslam-logs evaluate`: replay the detector on an image folder, score it on ground truth."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .. import __version__
from ..detector import make_detector
from ..errors import GroundTruthError, UsageError
from ..evaluation.groundtruth import load_ground_truth
from ..evaluation.metrics import evaluate, format_report
from ..replay import replay
from ..sources.folder import folder_frames, list_images
from .params_args import add_parameter_options, parameters_from_args
from .progress import Progress


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "evaluate",
        help="run the detector on an image folder and score it against a ground-truth matrix",
        description="Replay the detector over a folder of images (natural file-name order, "
        "stamped at --fps) and report TP, FP, precision and recall at the configured threshold, "
        "the highest recall at 100%% precision (R@P100) and the threshold that gives it.",
    )
    parser.add_argument("--images", type=Path, required=True, metavar="DIR", help="image folder")
    parser.add_argument("--fps", type=float, required=True, help="frame rate of the folder")
    parser.add_argument(
        "--gt",
        type=Path,
        required=True,
        metavar="GTFILE",
        help="ground-truth matrix (.mat, .bmp/.png, .npy/.npz)",
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
    add_parameter_options(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    params = parameters_from_args(args)
    if args.tolerance < 0:
        raise UsageError(f"--tolerance must be >= 0, got {args.tolerance}")
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
    header = {
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
