#!/usr/bin/env python3
"""Issue #22 item 2, a measured candidate check: SeqSLAM's pairs (`--no-verify --method
seqslam`) on the small logs, kept only when the k queries before each were reported too with
a match moving along (match - d within +-SLACK frames). Prints true / false pairs per k.

    python tools/feature_poor_consistency.py --datasets rtabmap,samples
    python tools/feature_poor_consistency.py --datasets none --log /tmp/s/season.ros2.mcap
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import feature_poor_table as fpt
from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.detector import Parameters
from doseqslam_logs.evaluation.groundtruth import load_ground_truth
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from loggen import shrink_log

SLACK = 2  # frames
KS = (0, 1, 2, 4)

Pair = tuple[int, int]


def consistent(pairs: list[Pair], k: int) -> list[Pair]:
    """The pairs whose k previous queries were reported with the match moving along."""
    match_of = dict(pairs)
    return [
        (q, m)
        for q, m in pairs
        if all(
            q - d in match_of and abs(match_of[q - d] - (m - d)) <= SLACK for d in range(1, k + 1)
        )
    ]


def seqslam_pairs(log: Path, out: Path, source: fpt.Source, threshold: float) -> list[Pair]:
    kappa = {} if source.kappa_s is None else {"kappa_s": source.kappa_s}
    params = Parameters(method="seqslam", threshold=threshold, **kappa)
    annotate_log(log, out, params, AnnotateOptions(verification=None, sidecar=True))
    return [(lc.query.index, lc.match.index) for lc in read_annotations(out).loop_closures]


def true_false(pairs: list[Pair], gt: Path) -> str:
    if not pairs:
        return "0 / 0"
    true = int(load_ground_truth(gt).are_true([q for q, _ in pairs], [m for _, m in pairs]).sum())
    return f"{true} / {len(pairs) - true}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=fpt.DATA)
    parser.add_argument("--datasets", default="rtabmap,samples", help="or none")
    parser.add_argument("--log", type=Path, action="append", default=[], help="a generated drive")
    parser.add_argument("--sizes", default="full,128x64,64x32")
    parser.add_argument("--thresholds", default="0.75,0.9")
    args = parser.parse_args()
    print("| data | frames | th | " + " | ".join(f"k = {k}" for k in KS) + " |")
    print("|---|---|---|" + "---|" * len(KS))
    every = {**fpt.sources(args.data), "none": []}
    chosen = [s for key in args.datasets.split(",") for s in every[key]]
    chosen += [fpt.generated(log) for log in args.log]
    with tempfile.TemporaryDirectory() as scratch:
        log, out = Path(scratch) / "log.mcap", Path(scratch) / "out.mcap"
        for source in chosen:
            for size in args.sizes.split(","):
                shape = None if size == "full" else shrink_log.parse_size(size)
                shrink_log.write_small_log(source.frames(), log, shape)
                for th in map(float, args.thresholds.split(",")):
                    pairs = seqslam_pairs(log, out, source, th)
                    cells = [true_false(consistent(pairs, k), source.gt) for k in KS]
                    print(f"| {source.name} | {size} | {th:g} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
