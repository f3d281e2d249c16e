#!/usr/bin/env python3
"""How long the commands that do nothing heavy take, start to exit: best of N runs each.

Issue #40 item 6: `--version`, `--help`, a usage error and `info LOG` should take well under
0.5 s; before, each paid about 1 s (more on a loaded machine) importing OpenCV, SciPy and faiss
through `doseqslam_logs.cli.main`. Wall time of a fresh process, so the figures move with the
machine's load: compare runs made one after the other.

    python -m bench.startup_time                      # the doseqslam-logs beside python
    python -m bench.startup_time --command /other/venv/bin/doseqslam-logs --runs 10
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

SAMPLE = Path(__file__).resolve().parents[2] / "sample_logs" / "drive_loops.ros2.mcap"

# name -> (arguments, the exit code the command must end with)
CASES: dict[str, tuple[list[str], int]] = {
    "--version": (["--version"], 0),
    "--help": (["--help"], 0),
    "annotate (no arguments)": (["annotate"], 2),
    "annotate --no-such-option": (["annotate", str(SAMPLE), "-o", "x.mcap", "--no-such"], 2),
    "info LOG": (["info", str(SAMPLE)], 0),
}


def best_time(command: list[str], code: int, runs: int) -> float:
    """The shortest wall time of `runs` runs; exits when the command ends otherwise."""
    best = float("inf")
    for _ in range(runs):
        start = time.perf_counter()
        done = subprocess.run(command, capture_output=True, check=False)
        best = min(best, time.perf_counter() - start)
        if done.returncode != code:
            sys.exit(f"{' '.join(command)}: exit {done.returncode}, expected {code}")
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = str(Path(sys.executable).parent / "doseqslam-logs")  # this environment's
    parser.add_argument("--command", default=default, help=f"the executable (default {default})")
    parser.add_argument("--runs", type=int, default=5, help="runs of each command (default 5)")
    args = parser.parse_args()
    print(f"{args.command}, best of {args.runs}:")
    for name, (arguments, code) in CASES.items():
        seconds = best_time([args.command, *arguments], code, args.runs)
        print(f"  {name:<28} {seconds:6.3f} s")


if __name__ == "__main__":
    main()
