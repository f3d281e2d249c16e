#!/usr/bin/env python3
"""The verified-results table of docs/research/results-log.md: raw and verified figures per
dataset, method and ground-truth file.

For each dataset and method `evaluate_folder` runs once (what `evaluate --images` runs: the
verified defaults, th = VERIFIED_THRESHOLD); every ground-truth file of the dataset is then
scored on the same decisions (`FolderEvaluation.scored_against`). One markdown row per
(dataset, method, GT file, raw | verified), with the `doseqslam-logs evaluate` command that
prints the same figures.

    python -m reproduce.verified_results                       # RTAB-Map and Lip6 Outdoor, ~15 min
    python -m reproduce.verified_results --datasets rtabmap    # seconds
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from doseqslam_logs.evaluation.folder_run import evaluate_folder
from doseqslam_logs.evaluation.groundtruth import load_ground_truth
from doseqslam_logs.evaluation.metrics import Evaluation
from doseqslam_logs.verification import verified_detector_parameters

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
    truths = [load_ground_truth(data / gt_file) for gt_file, _ in dataset.gts]
    first = evaluate_folder(folder, 1.0, truths[0], params)  # the `evaluate --images` run
    assert first.verification is not None
    stats = first.verification.stats
    print(
        f"{dataset.name}, {method}: {stats.candidates} candidates, {stats.accepted} accepted, "
        f"{stats.pairs} frame pairs, {time.perf_counter() - start:.0f} s",
        file=sys.stderr,
    )
    commands = []
    for (gt_file, label), gt in zip(dataset.gts, truths, strict=True):
        scored = first.scored_against(gt)  # the same decisions, another ground truth
        assert scored.verified is not None
        for kind, figures in (("raw", scored.evaluation), ("verified", scored.verified)):
            print(row(f"{dataset.name}, {method}", label, kind, figures))
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
