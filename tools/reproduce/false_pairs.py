#!/usr/bin/env python3
"""Each false reported pair of annotated generated drives, with its true geometry.

For every `NAME.annotated.mcap` in a folder that also holds the generator's `NAME.gt.npz` and
`NAME.poses.csv` (tools/reproduce/generalization_matrix.py --scratch), one line per reported
loop closure the ground truth calls false: the true distance and heading difference between
the query and its refined match, the estimated rotation, the inliers, the proposal it came
from, and the frame of the match's pass nearest the query (within 30 frames) with its
distance, which tells a bracketing that ended metres off the place from a wrong place.

    python -m reproduce.false_pairs /tmp/doseqslam-matrix

An investigation aid for issue #35's false pairs, not a benchmark.
"""

from __future__ import annotations

import argparse
import csv
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import numpy.typing as npt

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.evaluation.groundtruth import load_ground_truth

NEAREST_WITHIN = 30  # frames either side of the refined match searched for the nearest


def _poses(path: Path) -> npt.NDArray[np.float64]:
    """(x, y, yaw) per frame, from the generator's .poses.csv."""
    with path.open() as stream:
        rows = [(float(r["x"]), float(r["y"]), float(r["yaw"])) for r in csv.DictReader(stream)]
    return np.array(rows, dtype=np.float64).reshape(-1, 3)


def _truth(gt_path: Path) -> Callable[[int, int], bool]:
    """Whether (query, match) is a loop cell. A CSR matrix (the generator's large logs) is
    looked up row by row: an 8-hour drive has 240 M cells, which `load_ground_truth` would
    expand into coordinates (over 14 GB)."""
    with np.load(gt_path) as stored:
        if "indptr" in stored.files:
            indptr, indices, data = stored["indptr"], stored["indices"], stored["data"]

            def is_true(query: int, match: int) -> bool:
                row = slice(indptr[query], indptr[query + 1])
                return bool(np.any(data[row][indices[row] == match]))

            return is_true
    return load_ground_truth(gt_path).is_true


def false_pairs(annotated: Path, gt_path: Path, poses_path: Path) -> list[str]:
    """One line per reported pair of `annotated` that the ground truth calls false."""
    is_true = _truth(gt_path)
    poses = _poses(poses_path)
    lines = []
    for record in read_annotations(annotated).loop_closures:
        query, match = record.query.index, (record.refined_match or record.match).index
        if not record.reported or is_true(query, match):
            continue
        distance = float(np.hypot(*(poses[query, :2] - poses[match, :2])))
        turn = (poses[query, 2] - poses[match, 2] + math.pi) % (2 * math.pi) - math.pi
        lo, hi = max(0, match - NEAREST_WITHIN), min(len(poses), match + NEAREST_WITHIN + 1)
        around = np.hypot(*(poses[lo:hi, :2] - poses[query, :2]).T)
        nearest = int(np.argmin(around))
        lines.append(
            f"query {query} match {match}: {distance:.2f} m, {math.degrees(turn):+.1f} deg "
            f"(estimated {record.rotation_deg:.1f}), {record.inliers} inliers, proposal "
            f"{record.proposal}; nearest frame {lo + nearest} at {around[nearest]:.2f} m"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, help="annotated logs beside their .gt.npz, .poses.csv")
    args = parser.parse_args(argv)
    for annotated in sorted(args.folder.glob("*.annotated.mcap")):
        stem = annotated.name.removesuffix(".annotated.mcap")
        gt, poses = args.folder / f"{stem}.gt.npz", args.folder / f"{stem}.poses.csv"
        if gt.exists() and poses.exists():
            for line in false_pairs(annotated, gt, poses):
                print(f"{stem}: {line}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
