#!/usr/bin/env python3
"""The feature-poor tables of docs/research/results-log.md (issue #22): small grey versions of
the RTAB-Map samples, our sample logs and Lip6 Outdoor, annotated with the defaults and with
`--no-verify --method seqslam`, scored against each one's ground-truth matrix.

Each source is shrunk to each size (tools/loggen/shrink_log.py, area-averaged grey, a ROS 2 MCAP of
mono8 images in a temporary folder), then annotated (`annotate_log`, what `annotate` runs) and
scored (`evaluate_log`, what `evaluate OUT.mcap --gt GT` runs): the defaults by their verified
pairs, the unverified SeqSLAM by every pair at its th. Lip6 Outdoor is held out: it is
reported, never tuned on (`--datasets` leaves it out by default). `--dark F` multiplies the
pixels by F after shrinking: the night / low-contrast version. `--log LOG` adds a generated
drive (tools/loggen/make_sample_logs.py), scored against the .gt.npz beside it; one generated with
--season-change also gets its true pairs across the change counted ("true (A across)").

How small frames are enlarged for features (issue #22 item 2) was chosen with the options
that vary it: `--enlarge-below N` (segmentation.SMALL_FRAME_SIDE; 0: never), `--working-size
T` (the size they are enlarged to: feature_image_max_side and image_max_side), and the two
ideas tried for 64x32: `--min-inliers K` and `--runs seqslam-verified` (SeqSLAM's decisions,
checked).

    python -m reproduce.feature_poor_table                            # RTAB-Map and samples, ~2 min
    python -m reproduce.feature_poor_table --datasets lip6 --sizes 64x32,128x64
    python -m reproduce.feature_poor_table --dark 0.25                # the dark version
    python -m reproduce.feature_poor_table --sizes 160x120,192x144 --enlarge-below 0 --runs defaults
    python -m reproduce.feature_poor_table --datasets none --log /tmp/s/season.ros2.mcap \\
        --sizes 64x32
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from statistics import median
from typing import Any

import doseqslam_logs.detector.segmentation as segmentation
from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.detector import Parameters
from doseqslam_logs.evaluation.groundtruth import load_ground_truth
from doseqslam_logs.evaluation.log_run import LogEvaluationOptions, evaluate_log
from doseqslam_logs.evaluation.metrics import Evaluation
from doseqslam_logs.pipeline.annotate import AnnotateOptions, AnnotateResult, annotate_log
from doseqslam_logs.pipeline.feature_health import FeatureHealth
from doseqslam_logs.verification import (
    DEFAULT_VERIFICATION,
    VerificationParameters,
    verified_detector_parameters,
)
from loggen import shrink_log

DATA = Path("../shared/data")
SAMPLES = Path("sample_logs")


@dataclass(frozen=True)
class Source:
    name: str
    path: Path  # a log, or a folder of images at 1 fps
    gt: Path
    kappa_s: float | None = None  # None: the default
    season_start: int | None = None  # a generated drive's first frame of the other season

    def frames(self) -> Iterator[tuple[int, shrink_log.Gray]]:
        if self.path.is_dir():
            return shrink_log.folder_frames(self.path, 1.0)
        return shrink_log.log_frames(self.path)


def sources(data: Path) -> dict[str, list[Source]]:
    samples = [
        Source(name, SAMPLES / f"{name}.{ext}", SAMPLES / f"{name}.gt.npz")
        for name, ext in (
            ("drive_loops", "ros2.mcap"),
            ("drive_parked", "ros2.mcap"),
            ("drive_varrate", "bag"),
        )
    ]
    rtabmap = data / "rtabmap_samples_loop"
    lip6 = data / "lip6_outdoor"
    return {
        "rtabmap": [Source("RTAB-Map", rtabmap / "images", rtabmap / "samples_GT.bmp", 10.0)],
        "samples": samples,
        "lip6": [
            Source(
                "Lip6 Outdoor (held out)",
                lip6 / "images",
                lip6 / "ground_truth" / "groundTruthLip6O.mat",
            )
        ],
    }


def generated(log: Path) -> Source:
    """A drive of tools/loggen/make_sample_logs.py: NAME.ros2.mcap beside NAME.gt.npz and
    NAME.json."""
    stem = log.name.split(".")[0]
    info = json.loads((log.parent / f"{stem}.json").read_text())
    season = info.get("season_change")
    start = None if season is None else int(season["first_frame"])
    return Source(stem, log, log.parent / f"{stem}.gt.npz", season_start=start)


def true_cell(source: Source, out: Path, e: Evaluation) -> str:
    """The true pairs, and of them those across a season change (query after it, match
    before)."""
    if source.season_start is None:
        return str(e.tp)
    start, gt = source.season_start, load_ground_truth(source.gt)
    pairs = [
        (lc.query.index, lc.matched.index) for lc in read_annotations(out).reported_loop_closures
    ]
    across = [(q, m) for q, m in pairs if q >= start > m and gt.is_true(q, m)]
    return f"{e.tp} ({len(across)} across)"


def stationary_cell(result: AnnotateResult) -> str:
    """Pairs the motion rule turned down ('-' without verification)."""
    return "-" if result.verification is None else str(result.verification.stats.stationary)


RUNS = ("defaults", "--no-verify --method seqslam")
# Runs by their --runs name.
KINDS = {
    "defaults": "defaults",
    "seqslam": "--no-verify --method seqslam",
    "seqslam-verified": "--method seqslam",
}


@dataclass(frozen=True)
class Variant:
    """What the options change in the verified runs (None: the default)."""

    working_size: int | None = None
    min_inliers: int | None = None

    def note(self) -> str:
        """The row's words for what changed ('' for the defaults)."""
        small = segmentation.SMALL_FRAME_SIDE
        words = [] if small == 160 else [f"enlarged below {small} px" if small else "not enlarged"]
        if self.working_size is not None:
            words.append(f"to {self.working_size} px")
        if self.min_inliers is not None:
            words.append(f"min_inliers {self.min_inliers}")
        return ", ".join(words)

    def detector(self) -> dict[str, object]:
        if self.working_size is None:
            return {}
        return {"feature_detector": "orb", "feature_image_max_side": self.working_size}

    def verification(self) -> VerificationParameters:
        changes: dict[str, object] = {}
        if self.working_size is not None:
            changes["image_max_side"] = self.working_size
        if self.min_inliers is not None:  # for every pair, enlarged or not
            changes["min_inliers"] = self.min_inliers
            changes["small_frame_min_inliers"] = self.min_inliers
        return DEFAULT_VERIFICATION.replace(**changes)


def run(
    log: Path, out: Path, source: Source, kind: str, variant: Variant = Variant()
) -> tuple[AnnotateResult, Evaluation]:
    kappa: dict[str, Any] = {} if source.kappa_s is None else {"kappa_s": source.kappa_s}
    if kind in ("defaults", "--method seqslam"):
        method = "doseqslam" if kind == "defaults" else "seqslam"
        params = verified_detector_parameters(method=method, **variant.detector(), **kappa)
        options = AnnotateOptions(verification=variant.verification(), sidecar=True)
    else:
        params = Parameters(method="seqslam", **kappa)
        options = AnnotateOptions(verification=None, sidecar=True)
    result = annotate_log(log, out, params, options)
    scored = evaluate_log(out, LogEvaluationOptions(gt=source.gt, source=log)).result
    figures = scored.verified if scored.verified is not None else scored.raw
    return result, figures


def warning_cell(health: FeatureHealth | None) -> str:
    """Which warning the run gave, with its share."""
    if health is None or not health.poor:
        return "no"
    seg, checks = health.segmentation, health.checks
    parts = [f"frames {100 * seg.share_below:.0f} %"] if seg.poor else []
    if checks is not None and checks.poor:
        parts.append(f"checks {100 * checks.share:.0f} %")
    return "**yes**: " + ", ".join(parts)


def row(
    source: Source, size: str, kind: str, result: AnnotateResult, e: Evaluation, note: str = ""
) -> str:
    lengths = [d.length for d in result.replay.decisions]
    cells = [
        source.name,
        size,
        (f"`{kind}`" if kind.startswith("-") else kind) + (f" ({note})" if note else ""),
        f"{len(lengths)} ({median(lengths):g})",
        str(result.loop_closures),
        true_cell(source, result.output_path, e),
        str(e.fp),
        f"{100 * e.r_p100:.1f}",
        stationary_cell(result),
        warning_cell(result.health),
    ]
    return "| " + " | ".join(cells) + " |"


def measure(
    source: Source,
    size: str,
    folder: Path,
    dark: float = 1.0,
    runs: tuple[str, ...] = RUNS,
    variant: Variant = Variant(),
) -> None:
    """Packs the source at `size` (pixels times `dark`) and prints a row per run."""
    start = time.perf_counter()
    log = folder / "log.mcap"
    shape = None if size == "full" else shrink_log.parse_size(size)
    camera = None if source.path.is_dir() else shrink_log.scaled_camera(source.path, shape)
    shrink_log.write_small_log(source.frames(), log, shape, dark, camera)
    label = size if dark == 1.0 else f"{size}, dark x{dark:g}"
    for kind in runs:
        result, figures = run(log, folder / "out.mcap", source, kind, variant)
        note = "" if kind.startswith("--no-verify") else variant.note()
        print(row(source, label, kind, result, figures, note), flush=True)
    print(f"{source.name} {size}: {time.perf_counter() - start:.0f} s", file=sys.stderr)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--datasets", default="rtabmap,samples", help="or none")
    parser.add_argument("--log", type=Path, action="append", default=[], help="a generated drive")
    parser.add_argument("--sizes", default="full,128x64,64x32", help="full keeps the size")
    parser.add_argument("--dark", type=float, default=1.0, help="pixel factor, 0 < F <= 1")
    parser.add_argument("--runs", default="defaults,seqslam", help=", ".join(KINDS))
    parser.add_argument("--enlarge-below", type=int, help="px (default SMALL_FRAME_SIDE)")
    parser.add_argument("--working-size", type=int, help="px small frames are enlarged to")
    parser.add_argument("--min-inliers", type=int, help="verification's, for the verified runs")
    args = parser.parse_args()
    if args.enlarge_below is not None:
        segmentation.SMALL_FRAME_SIDE = args.enlarge_below  # feature_image reads it per call
    runs = tuple(KINDS[name] for name in args.runs.split(","))
    variant = Variant(args.working_size, args.min_inliers)
    print(
        "| data | frames | run | sequences (median length) | reported | true | false "
        "| R@P100 % | stationary | feature-poor warning |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    every = {**sources(args.data), "none": []}
    chosen = [s for key in args.datasets.split(",") for s in every[key]]
    chosen += [generated(log) for log in args.log]
    with tempfile.TemporaryDirectory() as scratch:
        for source in chosen:
            for size in args.sizes.split(","):
                measure(source, size, Path(scratch), args.dark, runs, variant)
    return 0


if __name__ == "__main__":
    sys.exit(main())
