#!/usr/bin/env python3
"""Why revisit windows go uncovered: each 1-s window that revisits a place (ground truth) and
has no true reported loop closure, classified by the best check of its queries.

For every such window the check kept is one whose match the ground truth calls true, if any
(then verification turned a true place down: "true match, <reason>"), else any checked one
("wrong match, <reason>": the proposal missed); windows whose candidates were all skipped, or
that had no candidate at all, are counted apart. With the generator's poses (.poses.csv), the
true pairs turned down for their rotation are listed with their true distance and heading.

    python -m reproduce.coverage_losses OUT.mcap --gt LOG.gt.npz [--poses LOG.poses.csv]

An investigation aid for issue #35's coverage targets, not a benchmark: it reads one annotated
log of a generated drive (tools/loggen/make_sample_logs.py, tools/reproduce/generalization_matrix.py
--scratch).
"""

from __future__ import annotations

import argparse
import csv
import math
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.annotations.records import LoopClosureRecord
from doseqslam_logs.evaluation.groundtruth import GroundTruth, load_ground_truth


def _matched(record: LoopClosureRecord) -> int:
    return (record.refined_match or record.match).index


def _reason(record: LoopClosureRecord) -> str:
    """The rejection reason without its figures ("rotation over 10 deg (12.3)" -> its head)."""
    return str(record.rejection_reason or "reported").split(" (")[0]


def window_losses(
    records: list[LoopClosureRecord], gt: GroundTruth, times_ns: np.ndarray, window_s: float
) -> tuple[int, int, Counter[str]]:
    """(windows revisiting a place, covered ones, the uncovered ones counted by cause)."""
    width = round(window_s * 1e9)

    def window(frame: int) -> int:
        return int((times_ns[frame] - times_ns[0]) // width)

    holding = {window(f) for f in gt.query_rows() if f < len(times_ns)}
    by_window: defaultdict[int, list[LoopClosureRecord]] = defaultdict(list)
    for record in records:
        by_window[window(record.query.index)].append(record)
    covered = {
        w
        for w, found in by_window.items()
        if any(r.reported and gt.is_true(r.query.index, _matched(r)) for r in found)
    }
    causes: Counter[str] = Counter()
    for w in sorted(holding - covered):
        checked = [r for r in by_window.get(w, []) if r.verification != "skipped"]
        if not by_window.get(w):
            causes["no candidate"] += 1
        elif not checked:
            causes["only skipped"] += 1
        else:
            true = [r for r in checked if gt.is_true(r.query.index, _matched(r))]
            kept = (true or checked)[0]
            causes[f"{'true' if true else 'wrong'} match, {_reason(kept)}"] += 1
    return len(holding), len(holding & covered), causes


def turned_for_rotation(
    records: list[LoopClosureRecord], gt: GroundTruth, poses: np.ndarray
) -> list[tuple[float, float, int]]:
    """(true heading difference deg, true distance m, inliers) of each true pair rejected for
    its rotation, sorted by heading."""
    rows = []
    for record in records:
        if not str(record.rejection_reason or "").startswith("rotation over"):
            continue
        q, m = record.query.index, _matched(record)
        if gt.is_true(q, m):
            turn = (poses[q, 2] - poses[m, 2] + math.pi) % (2 * math.pi) - math.pi
            distance = float(np.hypot(*(poses[q, :2] - poses[m, :2])))
            rows.append((abs(math.degrees(turn)), distance, record.inliers))
    return sorted(rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("annotated", type=Path, help="an annotated log")
    parser.add_argument("--gt", type=Path, required=True, help="its ground-truth matrix")
    parser.add_argument("--poses", type=Path, help="the generator's .poses.csv (x, y, yaw)")
    parser.add_argument("--window", type=float, default=1.0, help="window seconds (1)")
    args = parser.parse_args(argv)
    log = read_annotations(args.annotated)
    gt = load_ground_truth(args.gt)
    records = list(log.loop_closures)
    times = log.detector_times_ns()
    if times is None:
        raise SystemExit(f"{args.annotated}: no frame times recorded")
    windows, covered, causes = window_losses(records, gt, times, args.window)
    share = 100 * covered / max(windows, 1)
    print(
        f"{windows} windows of {args.window:g} s revisit a place, {covered} covered ({share:.1f} %)"
    )
    for cause, count in causes.most_common():
        print(f"  {count:5d}  {cause}")
    if args.poses is not None:
        with args.poses.open() as stream:
            rows = [(float(r["x"]), float(r["y"]), float(r["yaw"])) for r in csv.DictReader(stream)]
        turned = turned_for_rotation(records, gt, np.array(rows))
        print(f"true pairs rejected for their rotation: {len(turned)}")
        for heading, distance, inliers in turned:
            print(f"  {heading:5.1f} deg  {distance:5.2f} m  {inliers:4d} inliers")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
