#!/usr/bin/env python3
"""Geometric verification after the detector: raw vs verified figures over a parameter grid.

Runs the detector once over an image folder with ground truth, then checks every candidate
pair of every decision (or only decisions with f below --ceiling) with
doseqslam_logs.verification, and prints one table row per (detector, method, min_inliers,
refine_radius). Without grid options it evaluates the default VerificationParameters only.

"Verified" at a threshold th: a pair is reported when its decision has f < th AND the pair
(with its match moved to the frame with the most inliers within +-refine_radius, clipped to
the sequence's database) reaches min_inliers. Columns: R@P100 over the th sweep (with its TP
and th), recall at P >= 0.9, TP / FP at the detector threshold (params.threshold) and with
every candidate verified (th = inf), time per verified pair (features cached, matching +
RANSAC) and per candidate ((2r+1) pairs), and feature extraction time per frame.

Inliers are computed once per detector and method for the largest radius, with min_inliers
at its floor (8); smaller radii and higher min_inliers are derived from the same verdicts
(`best_verdict` ranks frames by inliers, independently of min_inliers).

Choosing defaults (RTAB-Map samples, never Lip6 Outdoor):

    python tools/sweep_verification.py --images ../shared/data/rtabmap_samples_loop/images \\
        --fps 1 --gt ../shared/data/rtabmap_samples_loop/samples_GT.bmp --set kappa_s=10 \\
        --detectors sift,orb,akaze --methods ransac,magsac \\
        --min-inliers 12,15,20,25,30,40 --radii 0,1,2,3,5

Held-out check with the defaults only:

    python tools/sweep_verification.py --images ../shared/data/lip6_outdoor/images --fps 1 \\
        --gt ../shared/data/lip6_outdoor/ground_truth/groundTruthLip6O.mat
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from doseqslam_logs.cli.params_args import add_parameter_options, parameters_from_args
from doseqslam_logs.detector import SequenceDecision, make_detector
from doseqslam_logs.errors import SourceError
from doseqslam_logs.evaluation.groundtruth import GroundTruth, load_ground_truth
from doseqslam_logs.evaluation.metrics import Evaluation, evaluate
from doseqslam_logs.pipeline.replay import replay
from doseqslam_logs.sources.image_folder import folder_frames, list_images
from doseqslam_logs.verification import (
    DEFAULT_VERIFICATION,
    FrameFeatures,
    Verdict,
    VerificationParameters,
    best_verdict,
    extract_features,
    verify_pair,
)

Pair = tuple[int, int]  # (query frame, match frame)


@dataclass
class Verified:
    """Every verdict of one (detector, method), and what computing them cost."""

    verdicts: dict[Pair, Verdict]
    verify_s: float
    frames: int
    extract_s: float


def main() -> int:
    args = _parse_args()
    params = parameters_from_args(args)
    gt = load_ground_truth(args.gt)
    start = time.perf_counter()
    decisions = replay(folder_frames(args.images, args.fps), make_detector(params)).decisions
    print(f"detector: {params.hash} ({time.perf_counter() - start:.1f} s), GT {args.gt.name}")
    base = VerificationParameters.from_dict(dict(args.vset))
    considered = [d for d in decisions if d.f < args.ceiling]
    radii, floors = _ints(args.radii), _ints(args.min_inliers)
    pairs = _pairs_to_verify(considered, max(radii))
    print(f"{sum(len(d.candidates) for d in considered)} candidates, {len(pairs)} pairs to verify")
    images = list_images(args.images)
    _print_header()
    _print_row(["raw", "-", "-", "-"], decisions, gt, params.threshold, args.tolerance, None)
    for detector, method in itertools.product(args.detectors.split(","), args.methods.split(",")):
        vparams = base.replace(feature_detector=detector, method=method, min_inliers=8)
        done = _verify_all(pairs, images, vparams)
        for radius, floor in itertools.product(radii, floors):
            kept = _verified_decisions(decisions, done.verdicts, radius, floor, args)
            cost = _cost_cells(done, radius, considered)
            cells = [detector, method, str(floor), str(radius)]
            _print_row(cells, kept, gt, params.threshold, args.tolerance, cost)
    return 0


def _parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--images", type=Path, required=True)
    parser.add_argument("--fps", type=float, required=True)
    parser.add_argument("--gt", type=Path, required=True)
    parser.add_argument("--tolerance", type=int, default=0, help="GT match tolerance (frames)")
    parser.add_argument(
        "--ceiling",
        type=float,
        default=math.inf,
        help="verify only decisions with f below this (default: every decision)",
    )
    d = DEFAULT_VERIFICATION
    parser.add_argument("--detectors", default=d.feature_detector, metavar="A,B")
    parser.add_argument("--methods", default=d.method, metavar="ransac,magsac")
    parser.add_argument("--min-inliers", default=str(d.min_inliers), metavar="N1,N2")
    parser.add_argument("--radii", default=str(d.refine_radius), metavar="R1,R2")
    parser.add_argument(
        "--vset",
        action="append",
        default=[],
        type=_name_value,
        metavar="NAME=VALUE",
        help="fix another verification parameter, e.g. --vset ransac_threshold_px=2",
    )
    add_parameter_options(parser)
    return parser.parse_args()


def _name_value(text: str) -> tuple[str, object]:
    name, _, value = text.partition("=")
    for kind in (int, float):
        try:
            return name, kind(value)
        except ValueError:
            continue
    return name, value


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",")]


# -- verification -------------------------------------------------------------------------


def _window(match: int, radius: int, database_size: int) -> range:
    """Frames within +-radius of the match that belong to the sequence's database."""
    return range(max(0, match - radius), min(database_size, match + radius + 1))


def _pairs_to_verify(decisions: Sequence[SequenceDecision], radius: int) -> list[Pair]:
    """Every (query, frame) pair any candidate's refinement window needs, each once."""
    pairs: set[Pair] = set()
    for d in decisions:
        for c in d.candidates:
            window = _window(c.match_index, radius, d.database_size)
            pairs.update((c.query_index, m) for m in window)
    return sorted(pairs)


def _verify_all(pairs: list[Pair], images: list[Path], params: VerificationParameters) -> Verified:
    """Verdicts for all pairs; each frame's features are extracted once and cached."""
    cache: dict[int, FrameFeatures] = {}
    extract_s = 0.0

    def features(index: int) -> FrameFeatures:
        nonlocal extract_s
        if index not in cache:
            gray = cv2.imread(str(images[index]), cv2.IMREAD_GRAYSCALE)
            if gray is None:
                raise SourceError(f"{images[index]}: cannot decode image")
            start = time.perf_counter()
            cache[index] = extract_features(np.asarray(gray, dtype=np.uint8), params)
            extract_s += time.perf_counter() - start
        return cache[index]

    verdicts: dict[Pair, Verdict] = {}
    verify_s = 0.0
    for q, m in pairs:
        query, match = features(q), features(m)
        start = time.perf_counter()
        verdicts[(q, m)] = verify_pair(query, match, params)
        verify_s += time.perf_counter() - start
    return Verified(verdicts, verify_s, len(cache), extract_s)


def _verified_decisions(
    decisions: Sequence[SequenceDecision],
    verdicts: dict[Pair, Verdict],
    radius: int,
    min_inliers: int,
    args: argparse.Namespace,
) -> list[SequenceDecision]:
    """Each decision keeps only its accepted pairs, with the refined match in place."""
    kept_decisions = []
    for d in decisions:
        kept = []
        for c in d.candidates if d.f < args.ceiling else ():
            window = _window(c.match_index, radius, d.database_size)
            scored = [(m, verdicts[(c.query_index, m)]) for m in window]
            best, verdict = best_verdict(scored, original=c.match_index)
            if verdict.inliers >= min_inliers:
                stamp = round(best * 1e9 / args.fps)  # folder frames: i / fps seconds
                kept.append(replace(c, match_index=best, match_timestamp_ns=stamp))
        kept_decisions.append(replace(d, candidates=tuple(kept)))
    return kept_decisions


# -- report -------------------------------------------------------------------------------


def _cost_cells(done: Verified, radius: int, decisions: Sequence[SequenceDecision]) -> list[str]:
    per_pair_ms = 1000 * done.verify_s / max(1, len(done.verdicts))
    windows = [
        len(_window(c.match_index, radius, d.database_size))
        for d in decisions
        for c in d.candidates
    ]
    per_candidate_ms = per_pair_ms * sum(windows) / max(1, len(windows))
    per_frame_ms = 1000 * done.extract_s / max(1, done.frames)
    return [f"{per_pair_ms:.1f}", f"{per_candidate_ms:.1f}", f"{per_frame_ms:.1f}"]


def _print_header() -> None:
    names = [
        "detector",
        "method",
        "min_inliers",
        "r",
        "R@P100 % (TP)",
        "th at R@P100",
        "R@P90 %",
        "TP / FP at th",
        "TP / FP all",
        "ms / pair",
        "ms / candidate",
        "ms / frame (features)",
    ]
    print("| " + " | ".join(names) + " |")
    print("|" + "---|" * len(names))


def _print_row(
    cells: list[str],
    decisions: Sequence[SequenceDecision],
    gt: GroundTruth,
    threshold: float,
    tolerance: int,
    cost: list[str] | None,
) -> None:
    at_th = evaluate(decisions, gt, threshold, tolerance)
    everything = evaluate(decisions, gt, math.inf, tolerance)
    th = "-" if at_th.threshold_at_r_p100 is None else f"{at_th.threshold_at_r_p100:.3f}"
    cells = [
        *cells,
        f"{100 * at_th.r_p100:.1f} ({_tp_at_r_p100(at_th)})",
        th,
        f"{100 * at_th.recall_at_p90:.1f}",
        f"{at_th.tp} / {at_th.fp}",
        f"{everything.tp} / {everything.fp}",
        *(cost or ["-", "-", "-"]),
    ]
    print("| " + " | ".join(cells) + " |", flush=True)


def _tp_at_r_p100(evaluation: Evaluation) -> int:
    clean = [p for p in evaluation.curve if p.fp == 0 and p.tp > 0]
    return clean[-1].tp if clean else 0


if __name__ == "__main__":
    sys.exit(main())
