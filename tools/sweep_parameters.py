#!/usr/bin/env python3
"""Evaluate a grid of parameter values on an image folder with ground truth; print a table.

The evidence behind a default: e.g. the segmentation detector chosen on the RTAB-Map samples,

    python tools/sweep_parameters.py --images ../shared/data/rtabmap_samples_loop/images \\
        --fps 1 --gt ../shared/data/rtabmap_samples_loop/samples_GT.bmp --set kappa_s=10 \\
        --grid feature_detector=orb,sift,akaze,brisk,klt --grid feature_image_max_side=160,240,320

Never sweep on a held-out set (Lip6 Outdoor) to choose a default.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

from doseqslam_logs.cli.params_args import add_parameter_options, parameters_from_args
from doseqslam_logs.detector import make_detector
from doseqslam_logs.evaluation.groundtruth import load_ground_truth
from doseqslam_logs.evaluation.metrics import evaluate
from doseqslam_logs.pipeline.replay import replay
from doseqslam_logs.sources.image_folder import folder_frames


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--images", type=Path, required=True)
    parser.add_argument("--fps", type=float, required=True)
    parser.add_argument("--gt", type=Path, required=True)
    parser.add_argument("--grid", action="append", default=[], metavar="NAME=V1,V2,...")
    add_parameter_options(parser)
    args = parser.parse_args()
    fixed = list(args.overrides)
    gt = load_ground_truth(args.gt)
    axes = [(name, values.split(",")) for name, _, values in (g.partition("=") for g in args.grid)]
    names = [name for name, _ in axes]
    print(
        "| "
        + " | ".join([*names, "sequences", "R@P100 %", "TP at R@P100", "TP / FP at th", "s"])
        + " |"
    )
    print("|" + "---|" * (len(names) + 5))
    for combo in itertools.product(*(values for _, values in axes)):
        args.overrides = [*fixed, *(f"{n}={v}" for n, v in zip(names, combo, strict=True))]
        params = parameters_from_args(args)
        start = time.perf_counter()
        result = replay(folder_frames(args.images, args.fps), make_detector(params))
        ev = evaluate(result.decisions, gt, params.threshold)
        best = next((p for p in reversed(ev.curve) if p.fp == 0 and p.tp > 0), None)
        cells = [
            *combo,
            str(ev.sequences),
            f"{ev.r_p100 * 100:.1f}",
            str(best.tp if best else 0),
            f"{ev.tp} / {ev.fp}",
            f"{time.perf_counter() - start:.1f}",
        ]
        print("| " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
