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
import time
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .. import __version__
from ..detector import Parameters, make_detector
from ..detector.events import SequenceDecision
from ..errors import GroundTruthError, UsageError
from ..evaluation.groundtruth import load_ground_truth
from ..evaluation.metrics import Evaluation, evaluate, format_report, format_side_by_side
from ..evaluation.verified import verified_decisions
from ..pipeline.replay import ReplayResult, replay
from ..pipeline.reread import FolderFrameReader
from ..sources.image_folder import folder_frames, list_images
from ..verification import Intrinsics, VerificationParameters, VerificationStats
from ..verification.stage import verify_in_threads
from . import evaluate_log
from .params_args import (
    add_parameter_options,
    add_verification_options,
    intrinsics_from_args,
    run_parameters,
    threshold_given,
    verification_from_args,
)
from .progress import Progress
from .verification_summary import verification_summary

# Threads that verify the candidates (each with its own feature cache); results do not depend
# on it.
VERIFY_THREADS = 2


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
    add_verification_options(parser)  # --images only: a log records its own verification
    parser.set_defaults(run=run)


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


@dataclass(frozen=True)
class _FolderVerification:
    """What the verification stage decided over the folder's run, and what it cost."""

    params: VerificationParameters
    intrinsics: Intrinsics | None
    decisions: list[SequenceDecision]  # reduced to their accepted pairs (verified_decisions)
    stats: VerificationStats  # seconds summed over the threads
    wall_s: float  # of the whole stage

    def describe(self) -> str:
        """The header's account: hash, pairs verified and accepted, and the cost."""
        stats = self.stats
        pose = (
            "essential matrix, intrinsics from --intrinsics"
            if self.intrinsics
            else "fundamental matrix, no intrinsics"
        )
        counts = verification_summary(stats, self.wall_s, pose)
        verified = f"{stats.candidates} candidate pairs verified"
        return f"verification {self.params.hash}: {verified}, {counts}"

    def to_json_dict(self) -> dict[str, Any]:
        k, stats = self.intrinsics, self.stats
        return {
            "verification": "on",
            "verification_hash": self.params.hash,
            "verification_parameters": self.params.to_dict(),
            "intrinsics": None if k is None else [k.fx, k.fy, k.cx, k.cy],
            "verification_cost": {
                "candidate_pairs": stats.candidates,
                "accepted_pairs": stats.accepted,
                "accepted_on_alternatives": stats.from_alternatives,
                "frame_pairs_checked": stats.pairs,
                "ms_per_pair": round(stats.ms_per_pair, 3),
                "wall_time_s": round(self.wall_s, 3),
            },
        }


_VERIFICATION_OFF: dict[str, Any] = {
    "verification": "off",
    "verification_hash": None,
    "verification_parameters": None,
    "intrinsics": None,
    "verification_cost": None,
}


def _verify(
    args: argparse.Namespace, images: list[Path], result: ReplayResult
) -> _FolderVerification | None:
    """The verification stage over the folder's decisions (None with --no-verify)."""
    params = verification_from_args(args)
    if params is None:
        return None
    intrinsics = intrinsics_from_args(args)
    start = time.perf_counter()
    reader = FolderFrameReader(images)  # stateless: one for every thread
    verified, stats = verify_in_threads(
        result.decisions, lambda: nullcontext(reader), params, intrinsics, VERIFY_THREADS
    )
    wall_s = time.perf_counter() - start
    return _FolderVerification(params, intrinsics, verified_decisions(verified), stats, wall_s)


def _run_images(args: argparse.Namespace) -> int:
    _check_images_args(args)
    params = run_parameters(args)  # as annotate: th = VERIFIED_THRESHOLD unless given
    verification_from_args(args)  # a bad --vset fails before the run
    intrinsics_from_args(args)
    gt = load_ground_truth(args.gt, args.gt_variable)
    images = list_images(args.images)
    if len(images) != gt.n_frames:  # checked before the run: a wrong GT file is the usual cause
        raise GroundTruthError(
            f"{args.gt}: ground truth has {gt.n_frames} frames but {args.images} has "
            f"{len(images)} images"
        )
    detector = make_detector(params)
    progress = Progress(len(images), "evaluate")
    try:
        result = replay(folder_frames(args.images, args.fps), detector, progress)
    finally:
        progress.close()
    verification = _verify(args, images, result)
    evaluation = evaluate(result.decisions, gt, params.threshold, args.tolerance)
    verified = None
    if verification is not None:
        verified = evaluate(verification.decisions, gt, params.threshold, args.tolerance)
    if args.json:
        print(
            json.dumps(
                _json_document(args, params, result, evaluation, verified, verification), indent=2
            )
        )
        return 0
    headline = (
        f"{params.method} on {args.images} at {args.fps:g} fps "
        f"(features: {result.feature_detector}, parameters {params.hash}, "
        f"{result.frames_per_second:.0f} frames/s)"
    )
    if verification is None:  # the paper's report, unchanged
        print(headline)
        print(format_report(evaluation))
        return 0
    print(f"{headline}; {verification.describe()}")
    note = "given" if threshold_given(args) else "default with verification"
    print(format_side_by_side(evaluation, verified, note))
    return 0


def _json_document(
    args: argparse.Namespace,
    params: Parameters,
    result: ReplayResult,
    evaluation: Evaluation,
    verified: Evaluation | None,
    verification: _FolderVerification | None,
) -> dict[str, Any]:
    return {
        "tool_version": __version__,
        "images": str(args.images),
        "fps": args.fps,
        "method": params.method,
        "feature_detector": result.feature_detector,
        "parameters_hash": params.hash,
        "wall_time_s": round(result.wall_time_s, 3),
        "parameters": params.to_dict(),
        **(_VERIFICATION_OFF if verification is None else verification.to_json_dict()),
        **evaluation.to_json_dict(),
        "verified": None if verified is None else verified.to_json_dict(),
    }
