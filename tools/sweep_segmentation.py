#!/usr/bin/env python3
"""The segmentation with verification on: verified TP / FP per setting, end to end.

Each setting (`LABEL=--set a=b --set c=d`) runs the real commands, with verification on:
`annotate --sidecar` + `evaluate --gt` on our sample logs, `evaluate --images` on the RTAB-Map
samples (the tuning sets), and `annotate --end` + `evaluate --gt-topic` on the first minutes
of the generated hour log (held out), whose CPU seconds (user + sys of the annotate process)
give the cost. One markdown row per setting. The setting behind VERIFIED_SEGMENTATION:

    python tools/sweep_segmentation.py \\
        "sift 240 (auto)=--set feature_detector=auto" \\
        "sift 200=--set feature_detector=sift --set feature_image_max_side=200" \\
        "orb 320=--set feature_detector=orb --set feature_image_max_side=320"   # ~2 min each

Choose on the tuning columns; the hour's minutes (and Lip6 Outdoor, `evaluate --images`) are
held out.
"""

from __future__ import annotations

import argparse
import json
import resource
import shlex
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from loggen.make_sample_logs import START_NS  # the generated hour's first stamp

SAMPLES = (
    "sample_logs/drive_loops.ros2.mcap",
    "sample_logs/drive_varrate.bag",
    "sample_logs/drive_parked.ros2.mcap",
)
RTABMAP = "rtabmap_samples_loop"
# The ground truth of docs/results.md's hour rows (as the sample logs' .gt.npz).
HOUR_GT = [
    "--gt-topic",
    "/ground_truth/pose",
    "--radius",
    "2",
    "--max-heading",
    "20",
    "--min-travel",
    "20",
]


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n")[0], formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("settings", nargs="+", metavar="LABEL=OPTIONS")
    parser.add_argument("--data", type=Path, default=Path("../shared/data"))
    parser.add_argument("--hour", type=Path, default=Path("/tmp/hour/hour.ros2.mcap"))
    parser.add_argument("--minutes", type=float, default=10.0, help="of the hour log")
    args = parser.parse_args()
    cli = shutil.which("doseqslam-logs")
    if cli is None:
        sys.exit("doseqslam-logs is not on PATH: pip install -e . first")
    names = [Path(s).name.split(".")[0] for s in SAMPLES]
    hour = f"hour, first {args.minutes:g} min"
    header = ["setting", *names, "RTAB-Map", "RTAB-Map raw R@P100 %", hour, "CPU s"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    with tempfile.TemporaryDirectory(prefix="sweep_segmentation_") as tmp:
        for setting in args.settings:
            label, _, options = setting.partition("=")
            row = measure(cli, shlex.split(options), Path(tmp), args)
            print("| " + " | ".join([label, *row]) + " |", flush=True)
    return 0


def measure(cli: str, options: list[str], tmp: Path, args: argparse.Namespace) -> list[str]:
    cells = []
    for log in SAMPLES:
        out = tmp / "sample.mcap"
        run([cli, "annotate", log, "-o", str(out), "--sidecar", *options])
        gt = log.split(".")[0] + ".gt.npz"
        cells.append(tp_fp(run_json([cli, "evaluate", str(out), "--gt", gt])["verified"]))
    images = args.data / RTABMAP / "images"
    gt_bmp = args.data / RTABMAP / "samples_GT.bmp"
    folder = ["--images", str(images), "--fps", "1", "--gt", str(gt_bmp), "--set", "kappa_s=10"]
    rtab = run_json([cli, "evaluate", *folder, *options])
    cells.append(tp_fp(rtab["verified"]))
    cells.append(f"{100 * rtab['r_p100']:.2f}")
    out = tmp / "hour.mcap"
    end = START_NS + round(args.minutes * 60e9)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    run([cli, "annotate", str(args.hour), "-o", str(out), "--sidecar", "--end", str(end), *options])
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    hour = run_json([cli, "evaluate", str(out), "--source", str(args.hour), *HOUR_GT])
    cells += [tp_fp(hour["verified"]), f"{cpu:.1f}"]
    return cells


def tp_fp(figures: dict[str, Any]) -> str:
    return f"{figures['tp']} / {figures['fp']}"


def run(command: list[str]) -> str:
    """The command's standard output; exits with its error when it fails."""
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode:
        sys.exit(f"{shlex.join(command)} failed ({done.returncode}): {done.stderr.strip()}")
    return done.stdout


def run_json(command: list[str]) -> dict[str, Any]:
    result: dict[str, Any] = json.loads(run([*command, "--json"]))
    return result


if __name__ == "__main__":
    sys.exit(main())
