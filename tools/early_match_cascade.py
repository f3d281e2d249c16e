#!/usr/bin/env python3
"""Would a cascade save verification time? Per checked pair, the ratio-test matches among the
query's K strongest features, beside the pair's real verdict.

A cascade would match the K strongest query features first and reject the pair unfitted when
fewer than t of them pass the ratio test (features are sorted strongest first, and a feature's
test does not depend on the others, so a passing pair would lose nothing). This runs the
verification of a log (annotate's defaults, a sidecar in a temporary folder) or of an image
folder (`evaluate --images`), wraps `verify_pair` to record (K-prefix matches for each K,
matches, inliers, verdict, seconds) and prints, for each K and t, the share of checks the
cascade would reject, the accepted verdicts and the non-hopeless ones (>= 15 inliers, which
steer the window search) it would lose (docs/performance.md, "A cascade, measured").

    python tools/early_match_cascade.py log /tmp/hour/hour.ros2.mcap --end-s 600
    python tools/early_match_cascade.py folder ../shared/data/rtabmap_samples_loop/images \\
        ../shared/data/rtabmap_samples_loop/samples_GT.bmp --kappa 10
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from doseqslam_logs.verification import stage
from doseqslam_logs.verification.geometry import FrameFeatures, Intrinsics, Verdict, verify_pair
from doseqslam_logs.verification.params import VerificationParameters

PREFIXES = (100, 150, 200, 250, 300, 400)
THRESHOLDS = (4, 6, 8, 10, 12, 15)
NOT_HOPELESS = 15  # inliers: half of min_inliers (stage._hopeless)


class Recorder:
    """`verify_pair` as the stage calls it, recording each pair's figures."""

    def __init__(self) -> None:
        self.rows: list[tuple[list[int], int, int, bool, float]] = []
        self.lock = threading.Lock()

    def __call__(
        self,
        query: FrameFeatures,
        match: FrameFeatures,
        params: VerificationParameters,
        intrinsics: Intrinsics | None = None,
    ) -> Verdict:
        start = time.perf_counter()
        verdict = verify_pair(query, match, params, intrinsics)
        seconds = time.perf_counter() - start
        prefixes = prefix_matches(query, match, params.ratio)
        with self.lock:
            self.rows.append(
                (prefixes, verdict.matches_tested, verdict.inliers, verdict.accepted, seconds)
            )
        return verdict


def prefix_matches(query: FrameFeatures, match: FrameFeatures, ratio: float) -> list[int]:
    """For each K of PREFIXES: query features among the K strongest that pass the ratio test."""
    if query.count == 0 or match.count < 2:
        return [0] * len(PREFIXES)
    norm = cv2.NORM_L2 if query.detector == "sift" else cv2.NORM_HAMMING
    a: Any = query.descriptors.astype(np.float32) if norm == cv2.NORM_L2 else query.descriptors
    b: Any = match.descriptors.astype(np.float32) if norm == cv2.NORM_L2 else match.descriptors
    kind = cv2.CV_32F if norm == cv2.NORM_L2 else cv2.CV_32S
    distance, _ = cv2.batchDistance(a, b, kind, normType=norm, K=2)
    passed = np.cumsum(distance[:, 0] < ratio * distance[:, 1])
    return [int(passed[min(k, passed.size) - 1]) for k in PREFIXES]


def run(args: argparse.Namespace, recorder: Recorder) -> None:
    setattr(stage, "verify_pair", recorder)  # noqa: B010 - the name the stage calls
    if args.kind == "log":
        from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
        from doseqslam_logs.sources import open_source, pick_image_topic

        end = None
        if args.end_s is not None:
            with open_source(args.path) as source:
                topic = pick_image_topic(source, None)
                first = next(iter(source.image_messages(topic))).log_time_ns
            end = first + int(args.end_s * 1e9)
        with tempfile.TemporaryDirectory() as tmp:
            options = AnnotateOptions(sidecar=True, end_ns=end)
            annotate_log(args.path, Path(tmp) / "out.mcap", options=options)
        return
    from doseqslam_logs.evaluation.folder_run import evaluate_folder
    from doseqslam_logs.verification import verified_detector_parameters

    extra = {} if args.kappa is None else {"kappa_s": args.kappa}
    evaluate_folder(args.path, 1.0, args.gt, verified_detector_parameters(**extra))


def report(rows: list[tuple[list[int], int, int, bool, float]]) -> None:
    prefixes = np.array([r[0] for r in rows]).reshape(-1, len(PREFIXES))
    inliers = np.array([r[2] for r in rows])
    accepted = np.array([r[3] for r in rows], bool)
    seconds = np.array([r[4] for r in rows])
    print(
        f"{len(rows)} pairs checked, {accepted.sum()} accepted verdicts, "
        f"{seconds.mean() * 1e3:.2f} ms a pair ({seconds[accepted].mean() * 1e3:.2f} accepted)"
    )
    print("| K | " + " | ".join(f"t = {t}" for t in THRESHOLDS) + " |")
    print("|---|" + "---|" * len(THRESHOLDS))
    for column, k in enumerate(PREFIXES):
        cells = []
        for t in THRESHOLDS:
            rejected = prefixes[:, column] < t
            lost = int(np.sum(rejected & accepted))
            steering = int(np.sum(rejected & (inliers >= NOT_HOPELESS)))
            cells.append(f"{100 * rejected.mean():.0f} % / {lost} / {steering}")
        print(f"| {k} | " + " | ".join(cells) + " |")
    print("cells: checks rejected / accepted verdicts lost / verdicts >= 15 inliers lost")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("kind", choices=("log", "folder"))
    parser.add_argument("path", type=Path)
    parser.add_argument("gt", type=Path, nargs="?", help="folder: its ground truth")
    parser.add_argument("--end-s", type=float, help="log: the first this many seconds")
    parser.add_argument("--kappa", type=float, help="folder: kappa_s")
    args = parser.parse_args()
    if args.kind == "folder" and args.gt is None:
        parser.error("a folder needs its ground truth")
    recorder = Recorder()
    run(args, recorder)
    report(recorder.rows)


if __name__ == "__main__":
    main()
