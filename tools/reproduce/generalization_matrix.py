#!/usr/bin/env python3
"""The generalization matrix (issue #35): the defaults on generated logs they were not tuned on.

One factor at a time around a base drive (a 5-minute, 10 Hz, 320x240 colour drive of laps,
sensor noise 2, steady lighting, no stop), over:

    resolution  160x120, 320x240, 640x480, 1280x720
    rate        1, 2, 10, 30 Hz
    duration    2, 5, 20, 60 minutes
    parking     none, 30 s, 3 minutes, three stops of 30 s (moving time kept at 5 minutes)
    lighting    the samples' exposure drift, and 2.5x stronger
    colour      colour, grey
    noise       sigma 2 and 6 grey levels
    clock       steady, variable rate
    route       loops, figure8, outandback

each with --seeds seeds. Every cell's log is generated (tools/loggen/make_sample_logs.py, cached in
--scratch), annotated with the command's defaults (plus what follows `--`), and scored against
its ground truth: verified TP, FP, precision, R@P100 and the share of 1-s and 5-s revisit
windows with a true loop closure. One row per log, then a summary line.

    python -m reproduce.generalization_matrix                       # the whole matrix (hours)
    python -m reproduce.generalization_matrix --axes parking,rate --seeds 1
    python -m reproduce.generalization_matrix --max-minutes 5 -- --odometry-topic none

It is a benchmark, not a test: tests/test_motion_rule.py runs a parked cell in the slow tier.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from doseqslam_logs.cli.main import main as command
from doseqslam_logs.evaluation.log_run import LogEvaluationOptions, evaluate_log
from doseqslam_logs.verification.motion import STATIONARY
from loggen import make_sample_logs as gen

BASE = gen.Config(
    name="base",
    route="loops",
    duration=300.0,
    rate=10.0,
    width=320,
    height=240,
    formats=("ros2mcap",),
)
PARKING_S = {"park30": (30.0, 1), "park180": (180.0, 1), "stops3x30": (30.0, 3)}


@dataclass(frozen=True)
class Cell:
    axis: str
    name: str
    config: gen.Config

    def minutes(self) -> float:
        """Minutes of driving (stops not counted)."""
        return (self.config.duration - self.config.parked * self.config.stops) / 60.0


def _cells() -> list[Cell]:
    """Every cell of the matrix once (the base drive stands for its value on each axis)."""
    cells = [Cell("base", "base", BASE)]
    for width, height in ((160, 120), (640, 480), (1280, 720)):
        cells.append(
            Cell("resolution", f"{width}x{height}", replace(BASE, width=width, height=height))
        )
    for rate in (1.0, 2.0, 30.0):
        cells.append(Cell("rate", f"{rate:g}Hz", replace(BASE, rate=rate)))
    for minutes in (2, 20, 60):
        cells.append(Cell("duration", f"{minutes}min", replace(BASE, duration=60.0 * minutes)))
    for name, (seconds, stops) in PARKING_S.items():
        parked = replace(
            BASE, parked=seconds, stops=stops, duration=BASE.duration + seconds * stops
        )
        cells.append(Cell("parking", name, parked))
    cells.append(Cell("lighting", "light2.5", replace(BASE, lighting=2.5)))
    cells.append(Cell("colour", "grey", replace(BASE, color=False)))
    cells.append(Cell("noise", "noise6", replace(BASE, noise_sigma=6.0)))
    cells.append(Cell("clock", "varrate", replace(BASE, variable_rate=True)))
    for route in ("figure8", "outandback"):
        cells.append(Cell("route", route, replace(BASE, route=route)))
    return cells


def _generated(config: gen.Config, scratch: Path, jobs: int) -> Path:
    log = scratch / f"{config.name}.ros2.mcap"
    if not (log.exists() and (scratch / f"{config.name}.gt.npz").exists()):
        gen.generate(config, scratch, jobs, progress=False)
    return log


def _annotated(log: Path, out: Path, extra: list[str]) -> tuple[float, str]:
    """Runs `annotate` as the command does; its wall time and summary line (not printed)."""
    start = time.perf_counter()
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = command(["annotate", str(log), "-o", str(out), *extra])
    if code != 0:
        raise SystemExit(f"annotate {log} exited {code}")
    return time.perf_counter() - start, printed.getvalue().strip()


def measure(cell: Cell, seed: int, scratch: Path, jobs: int, extra: list[str]) -> dict[str, Any]:
    """One log of a cell: generated, annotated, scored (the verified figures)."""
    config = replace(cell.config, name=f"{cell.name}_seed{seed}", seed=seed)
    log = _generated(config, scratch, jobs)
    out = scratch / f"{config.name}.annotated.mcap"
    wall_s, _ = _annotated(log, out, extra)
    report = evaluate_log(out, LogEvaluationOptions(gt=scratch / f"{config.name}.gt.npz"))
    verified = report.to_json_dict()["verified"]
    coverage = {f"{c['window_s']:g}s": c["share"] for c in verified["coverage"]}
    stationary = sum(lc.rejection_reason == STATIONARY for lc in report.log.loop_closures)
    return {
        "axis": cell.axis,
        "cell": cell.name,
        "seed": seed,
        "frames": verified["frames"],
        "events": verified["gt_loop_events"],
        "tp": verified["tp"],
        "fp": verified["fp"],
        "precision": verified["precision"],
        "r_p100": verified["r_p100"],
        "coverage_1s": coverage.get("1s", float("nan")),
        "coverage_5s": coverage.get("5s", float("nan")),
        "stationary": stationary,
        "annotate_s": round(wall_s, 1),
    }


def _row(r: dict[str, Any]) -> str:
    return (
        f"| {r['axis']} | {r['cell']} | {r['seed']} | {r['frames']} | {r['tp']} | {r['fp']} "
        f"| {100 * r['precision']:.1f} | {100 * r['r_p100']:.1f} | {100 * r['coverage_1s']:.1f} "
        f"| {100 * r['coverage_5s']:.1f} | {r['stationary']} | {r['annotate_s']:.0f} |"
    )


def summary_line(rows: list[dict[str, Any]]) -> str:
    tp, fp = sum(r["tp"] for r in rows), sum(r["fp"] for r in rows)
    with_fp = sorted({f"{r['cell']}/{r['seed']}" for r in rows if r["fp"]})
    worst = min(rows, key=lambda r: r["coverage_1s"])
    return (
        f"{len(rows)} logs: TP {tp}, FP {fp} (precision {100 * tp / max(tp + fp, 1):.2f} %), "
        f"logs with a false pair: {', '.join(with_fp) or 'none'}; lowest 1-s coverage "
        f"{100 * worst['coverage_1s']:.1f} % ({worst['cell']}/{worst['seed']})"
    )


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    own = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--axes", help="comma-separated axes (default: all, with the base)")
    parser.add_argument("--cells", help="comma-separated cell names (e.g. park180,640x480)")
    parser.add_argument("--seeds", type=int, default=2, help="seeds per cell (1, 2, ...)")
    parser.add_argument(
        "--max-minutes", type=float, help="leave out cells that drive longer (stops not counted)"
    )
    parser.add_argument("--scratch", type=Path, default=Path("/tmp/doseqslam-matrix"))
    parser.add_argument("--jobs", type=int, default=2, help="rendering processes")
    parser.add_argument("--json", type=Path, help="also write the rows as JSON lines")
    args = parser.parse_args(own)
    cells = _cells()
    if args.axes:
        axes = set(args.axes.split(",")) | {"base"}
        cells = [c for c in cells if c.axis in axes]
    if args.cells:
        cells = [c for c in cells if c.name in args.cells.split(",")]
    if args.max_minutes is not None:
        cells = [c for c in cells if c.minutes() <= args.max_minutes + 1e-9]
    args.scratch.mkdir(parents=True, exist_ok=True)
    print(f"annotate defaults{' ' + ' '.join(extra) if extra else ''}; {len(cells)} cells")
    print(
        "| axis | cell | seed | frames | TP | FP | precision % | R@P100 % | cov 1 s % "
        "| cov 5 s % | stationary | annotate s |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    rows = []
    for cell in cells:
        for seed in range(1, args.seeds + 1):
            row = measure(cell, seed, args.scratch, args.jobs, extra)
            rows.append(row)
            print(_row(row), flush=True)
            if args.json:
                with args.json.open("a") as stream:
                    stream.write(json.dumps(row) + "\n")
    print(summary_line(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
