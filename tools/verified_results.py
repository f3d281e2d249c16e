#!/usr/bin/env python3
"""The verified-results table of docs/results.md: raw and verified figures per dataset, method
and ground-truth file.

For each dataset and method the detector runs once and its candidates are verified once (the
`evaluate --images` path: th = VERIFIED_THRESHOLD, default VerificationParameters); every
ground-truth file of the dataset is then scored on the same decisions. One markdown row per
(dataset, method, GT file, raw | verified), with the `doseqslam-logs evaluate` command that
prints the same figures.

    python tools/verified_results.py                       # RTAB-Map and Lip6 Outdoor, ~15 min
    python tools/verified_results.py --datasets rtabmap    # seconds
"""

from __future__ import annotations

import argparse
import sys
import time
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

from doseqslam_logs.detector import make_detector
from doseqslam_logs.evaluation.groundtruth import load_ground_truth
from doseqslam_logs.evaluation.metrics import Evaluation, evaluate
from doseqslam_logs.evaluation.verified import verified_decisions
from doseqslam_logs.pipeline.replay import replay
from doseqslam_logs.pipeline.reread import FolderFrameReader
from doseqslam_logs.sources.image_folder import folder_frames, list_images
from doseqslam_logs.verification import DEFAULT_VERIFICATION, verified_detector_parameters
from doseqslam_logs.verification.stage import verify_in_threads

DATA = Path("../shared/data")


@dataclass(frozen=True)
class Dataset:
    name: str
    images: str  # below DATA
    gts: tuple[tuple[str, str], ...]  # (file below DATA, label)
    kappa_s: float | None  # None: the default


DATASETS = {
    "rtabmap": Dataset(
        "RTAB-Map",
        "rtabmap_samples_loop/images",
        (("rtabmap_samples_loop/samples_GT.bmp", "samples_GT.bmp"),),
        10.0,
    ),
    "lip6": Dataset(
        "Lip6 Outdoor",
        "lip6_outdoor/images",
        (
            ("lip6_outdoor/ground_truth/groundTruthLip6O.mat", "groundTruthLip6O.mat (Tsintotas)"),
            (
                "lip6_outdoor/ground_truth/Lip6OutdoorGroundTruth.mat",
                "Lip6OutdoorGroundTruth.mat (original)",
            ),
        ),
        None,
    ),
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--datasets", default="rtabmap,lip6")
    parser.add_argument("--methods", default="doseqslam,seqslam")
    args = parser.parse_args()
    print(
        "| data, method | GT file | | TP at th | FP at th | precision % | recall % "
        "| R@P100 % | th for R@P100 | recall at P >= 0.9 % |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    commands = []
    for key in args.datasets.split(","):
        dataset = DATASETS[key]
        for method in args.methods.split(","):
            commands += rows(args.data, dataset, method)
    print("\nCommands (`D=../shared/data`):\n\n```sh")
    print("\n".join(commands))
    print("```")
    return 0


def rows(data: Path, dataset: Dataset, method: str) -> list[str]:
    extra = {} if dataset.kappa_s is None else {"kappa_s": dataset.kappa_s}
    params = verified_detector_parameters(method=method, **extra)
    folder = data / dataset.images
    start = time.perf_counter()
    decisions = replay(folder_frames(folder, 1.0), make_detector(params), workers=2).decisions
    reader = FolderFrameReader(list_images(folder))
    checked, stats = verify_in_threads(
        decisions, lambda: nullcontext(reader), DEFAULT_VERIFICATION, workers=2
    )
    verified = verified_decisions(checked)
    seconds = time.perf_counter() - start
    print(
        f"{dataset.name}, {method}: {stats.candidates} candidates, {stats.accepted} accepted, "
        f"{stats.pairs} frame pairs, {seconds:.0f} s",
        file=sys.stderr,
    )
    commands = []
    for gt_file, label in dataset.gts:
        gt = load_ground_truth(data / gt_file)
        for kind, chosen in (("raw", decisions), ("verified", verified)):
            print(row(f"{dataset.name}, {method}", label, kind, evaluate(chosen, gt, 0.99)))
        options = "" if dataset.kappa_s is None else f" --set kappa_s={dataset.kappa_s:g}"
        options += "" if method == "doseqslam" else f" --method {method}"
        commands.append(
            f"doseqslam-logs evaluate --images $D/{dataset.images} --fps 1 --gt $D/{gt_file}"
            + options
        )
    return commands


def row(name: str, gt: str, kind: str, e: Evaluation) -> str:
    th = "-" if e.threshold_at_r_p100 is None else f"{e.threshold_at_r_p100:.3f}"
    cells = [
        name,
        gt,
        kind,
        str(e.tp),
        str(e.fp),
        f"{100 * e.precision:.1f}",
        f"{100 * e.recall:.2f}",
        f"{100 * e.r_p100:.2f}",
        th,
        f"{100 * e.recall_at_p90:.2f}",
    ]
    return "| " + " | ".join(cells) + " |"


if __name__ == "__main__":
    sys.exit(main())
