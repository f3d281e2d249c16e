#!/usr/bin/env python3
"""Time and memory of `annotate` on real logs, against reading + decoding the camera alone.

Each measurement runs in a fresh Python process, so its peak resident memory (ru_maxrss of that
process) is its own:

* decode: the camera channel read and decoded, nothing else (sources + log_frames.decoded_frames,
  the same path annotate uses);
* full: `annotate_log` with the `annotate` command's defaults: geometric verification on (th
  raised to VERIFIED_THRESHOLD, next-best trajectories on) and the whole input copied into the
  output;
* unverified: the same with verification off (`--no-verify`, the paper's decision, th 0.75);
* sidecar (--sidecar): `full` with AnnotateOptions(sidecar=True);
* cli (--cli): the `doseqslam-logs annotate LOG -o OUT` command with its own defaults.

Outputs go to a temporary directory (--tmp-dir, default: beside the hour log, so on the same
disk) and are removed. Prints a markdown table; --json FILE also writes every figure.

    python -m bench.annotate                              # sample log + 1-hour log
    python -m bench.annotate --sidecar --cli
    python -m bench.annotate --no-sample --minutes 10,30,60  # growth with log length
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "sample_logs" / "drive_loops.ros2.mcap"
HOUR = Path("/tmp/hour/hour.ros2.mcap")
HOUR_COMMAND = (
    "PYTHONPATH=tools python -m loggen.make_sample_logs --out /tmp/hour --name hour "
    "--duration 3600 --rate 10 "
    "--width 640 --height 480 --formats ros2mcap --jobs 2"
)
STAGES = (
    "wait",
    "features",
    "preprocess",
    "segmentation",
    "sad",
    "enhance",
    "trajectory",
    "verify",
)
KINDS = ("decode", "full", "unverified", "sidecar")


# ---------------------------------------------------------------------------------------------
# Child side: one measurement, printed as one JSON line


def _usage() -> dict[str, float]:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return {"cpu_s": usage.ru_utime + usage.ru_stime, "peak_rss_mb": usage.ru_maxrss / 1024.0}


def _end_ns(log: Path, minutes: float | None) -> tuple[str, int | None]:
    """The camera topic and the end time `minutes` after its first message (None: whole log)."""
    from doseqslam_logs.sources import open_source, pick_image_topic

    with open_source(log) as source:
        topic = pick_image_topic(source, None)
        if minutes is None:
            return topic, None
        first = next(c.first_log_time_ns for c in source.channels() if c.topic == topic)
        assert first is not None
        return topic, first + round(minutes * 60e9)


def _module(name: str, before_the_layout: str) -> ModuleType:
    """A module of this package, or of a --compare package from before the pipeline/ layout."""
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError:
        return importlib.import_module(before_the_layout)


def _frame_span_s(first_ns: int | None, last_ns: int | None, frames: int) -> float:
    """The log time the frames cover, one frame period included."""
    if first_ns is None or last_ns is None or frames < 2:
        return 0.0
    span = (last_ns - first_ns) / 1e9
    return span * frames / (frames - 1)


def measure_decode(log: Path, minutes: float | None) -> dict[str, Any]:
    from doseqslam_logs.sources import open_source

    decode = _module("doseqslam_logs.pipeline.decode", "doseqslam_logs.log_frames")
    decoded_frames = decode.decoded_frames
    topic, end_ns = _end_ns(log, minutes)
    counts = decode.FrameCounts()
    first = last = None
    start = time.perf_counter()
    with open_source(log) as source:
        for frame in decoded_frames(source.image_messages(topic, None, end_ns), counts):
            first = frame.log_time_ns if first is None else first
            last = frame.log_time_ns
    wall = time.perf_counter() - start
    span = _frame_span_s(first, last, counts.used)
    return {"frames": counts.used, "wall_s": wall, "log_s": span, "stages": {}, "output_mb": 0.0}


def measure_annotate(
    log: Path, minutes: float | None, sidecar: bool, verify: bool, out: Path
) -> dict[str, Any]:
    from doseqslam_logs.detector import Parameters

    pipeline = _module("doseqslam_logs.pipeline.annotate", "doseqslam_logs.annotate")
    AnnotateOptions, annotate_log = pipeline.AnnotateOptions, pipeline.annotate_log
    topic, end_ns = _end_ns(log, minutes)
    extra: dict[str, Any] = {"verification": None}  # --no-verify unless `verify`
    params = Parameters()
    if verify:  # what the annotate command does by default
        from doseqslam_logs import verification

        extra["verification"] = verification.DEFAULT_VERIFICATION
        if hasattr(verification, "verified_detector_parameters"):
            params = verification.verified_detector_parameters()
        else:  # a --compare package from before next-best trajectories
            params = Parameters(threshold=verification.VERIFIED_THRESHOLD)
    options = AnnotateOptions(topic=topic, end_ns=end_ns, sidecar=sidecar, **extra)
    start = time.perf_counter()
    result = annotate_log(log, out, params, options)
    wall = time.perf_counter() - start
    times = result.replay
    span = 0.0
    frames = times.frames
    if result.replay.decisions:
        first = min(d.first_timestamp_ns for d in result.replay.decisions)
        last = max(d.last_timestamp_ns for d in result.replay.decisions)
        span = _frame_span_s(first, last, frames)
    stages = dict(getattr(times, "stage_seconds", {}))  # older versions lack it
    stages["detector"] = times.wall_time_s
    verified = getattr(result, "verification", None)
    verify_s = getattr(verified, "wall_s", 0.0) if verified is not None else 0.0
    if verified is not None:
        stages["verify"] = verify_s
    # The rest: hashing the input, writing the output.
    stages["write"] = wall - times.wall_time_s - verify_s
    return {
        "frames": frames,
        "wall_s": wall,
        "log_s": span,
        "stages": stages,
        "output_mb": out.stat().st_size / 1e6,
        "sequences": len(times.decisions),
        "loop_closures": result.loop_closures if hasattr(result, "loop_closures") else 0,
    }


def child(args: argparse.Namespace) -> None:
    log = Path(args.log)
    out = Path(args.out) if args.out else Path(tempfile.gettempdir()) / "bench.mcap"
    if args.child == "decode":
        figures = measure_decode(log, args.cut)
    else:
        verify = args.child in ("full", "sidecar")
        figures = measure_annotate(log, args.cut, args.child == "sidecar", verify, out)
    figures.update(_usage())
    print(json.dumps(figures))


# ---------------------------------------------------------------------------------------------
# Parent side: one fresh process per measurement


def load_average() -> float:
    return os.getloadavg()[0]


def run_child(
    kind: str, log: Path, minutes: float | None, tmp: Path, tree: Path | None = None
) -> dict[str, Any]:
    """One measurement in a fresh process; `tree`: import doseqslam_logs from there instead."""
    out = tmp / f"{log.stem}.{kind}.mcap"
    load = load_average()
    command = [sys.executable, __file__, "--child", kind, "--log", str(log), "--out", str(out)]
    if minutes is not None:
        command += ["--cut", str(minutes)]
    env = dict(os.environ)
    if tree is not None:  # PYTHONPATH comes before the installed (editable) package
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(tree), env.get("PYTHONPATH")]))
    done = subprocess.run(command, capture_output=True, text=True, check=False, env=env)
    if done.returncode != 0:
        raise SystemExit(f"{kind} on {log} failed:\n{done.stderr[-3000:]}")
    figures: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    out.unlink(missing_ok=True)
    figures["load"] = (load + load_average()) / 2
    return figures


def run_cli(log: Path, tmp: Path) -> dict[str, Any]:
    """`doseqslam-logs annotate LOG -o OUT` with the command's defaults."""
    out = tmp / f"{log.stem}.cli.mcap"
    exe = Path(sys.executable).with_name("doseqslam-logs")
    command = [str(exe), "annotate", str(log), "-o", str(out)]
    load = load_average()
    start = time.perf_counter()
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(process.pid, 0)
    wall = time.perf_counter() - start
    stdout, stderr = process.communicate()
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{stderr.decode()[-3000:]}")
    summary = stdout.decode().strip().splitlines()[-1] if stdout.strip() else ""
    found = re.search(r"(\d+) frames of", summary)
    figures = {
        "frames": int(found.group(1)) if found else 0,
        "wall_s": wall,
        "log_s": 0.0,
        "stages": {},
        "output_mb": out.stat().st_size / 1e6,
        "cpu_s": usage.ru_utime + usage.ru_stime,
        "peak_rss_mb": usage.ru_maxrss / 1024.0,
        "summary": summary,
        "load": (load + load_average()) / 2,
    }
    out.unlink(missing_ok=True)
    return figures


# ---------------------------------------------------------------------------------------------
# Table


def _row(label: str, kind: str, figures: dict[str, Any], decode_cpu: float | None) -> str:
    """One table row; `decode_cpu`: the CPU seconds of decoding the same log with the same
    version, for the ratio issue #37 sets its target on (annotate CPU / decode CPU)."""
    frames, wall, span = figures["frames"], figures["wall_s"], figures["log_s"]
    cpu = figures["cpu_s"]
    ratio = f"{cpu / decode_cpu:.1f}" if decode_cpu and _kind(kind) != "decode" else ""
    stages = figures["stages"]
    cells = [
        label,
        kind,
        f"{frames:,}",
        f"{wall:.1f}",
        f"{frames / wall:.0f}" if wall > 0 else "",
        f"{span / wall:.1f}x" if span and wall > 0 else "",
        ratio,
        f"{cpu:.1f}",
        f"{figures['peak_rss_mb']:.0f}",
        *(f"{stages[s]:.1f}" if s in stages else "" for s in (*STAGES, "write")),
        f"{figures['output_mb']:.1f}" if figures["output_mb"] else "",
        f"{figures['load']:.1f}",
    ]
    return "| " + " | ".join(cells) + " |"


HEADER = (
    "| log | run | frames | wall s | frames/s | x real time | CPU / decode CPU | CPU s | "
    "peak RSS MB | " + " | ".join(f"{s} s" for s in (*STAGES, "write")) + " | output MB | load |"
)


def _kind(run: str) -> str:
    return run.split(" ")[0]


def _version(run: str) -> str:
    return run.partition(" ")[2]


def table(rows: list[tuple[str, str, dict[str, Any]]]) -> str:
    lines = [HEADER, "|" + "---|" * HEADER.count(" | ") + "---|"]
    decode_cpu = {
        (label, _version(run)): f["cpu_s"] for label, run, f in rows if _kind(run) == "decode"
    }
    for label, run, figures in rows:
        lines.append(_row(label, run, figures, decode_cpu.get((label, _version(run)))))
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sample", type=Path, default=SAMPLE, help="a committed sample log")
    parser.add_argument("--no-sample", action="store_true", help="skip the sample log")
    parser.add_argument("--hour", type=Path, default=HOUR, help="the generated 1-hour log")
    parser.add_argument("--sidecar", action="store_true", help="also measure --sidecar")
    parser.add_argument("--cli", action="store_true", help="also run the annotate command")
    parser.add_argument(
        "--minutes", default="", help="comma-separated cuts of the hour log, e.g. 10,30,60"
    )
    parser.add_argument(
        "--kinds",
        default="decode,full,unverified",
        help="measurements per log: decode, full, unverified, sidecar (none: only --cli)",
    )
    parser.add_argument(
        "--compare",
        type=Path,
        action="append",
        default=[],
        help="also measure the package in this folder (e.g. `git archive HEAD doseqslam_logs "
        "schemas | tar -x -C DIR`), each of its runs right after the same run of this one; "
        "repeat for more folders",
    )
    parser.add_argument("--tmp-dir", type=Path, default=None, help="where outputs go")
    parser.add_argument("--json", type=Path, default=None, help="write every figure here")
    # Child side (internal)
    parser.add_argument("--child", choices=KINDS, help=argparse.SUPPRESS)
    parser.add_argument("--log", help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    parser.add_argument("--cut", type=float, default=None, help=argparse.SUPPRESS)
    return parser.parse_args(argv)


def plan(args: argparse.Namespace) -> list[tuple[str, Path, float | None]]:
    """(label, log, minutes) for every log to measure."""
    logs: list[tuple[str, Path, float | None]] = []
    if not args.no_sample:
        logs.append((args.sample.name, args.sample, None))
    if not args.hour.exists():
        print(f"skipping the 1-hour log: {args.hour} is missing; make it with\n  {HOUR_COMMAND}")
        return logs
    cuts: list[float | None] = [float(m) for m in args.minutes.split(",") if m.strip()]
    for minutes in cuts or [None]:
        label = f"{args.hour.name}" if minutes is None else f"{args.hour.name}, {minutes:g} min"
        logs.append((label, args.hour, minutes))
    return logs


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    if args.child:
        child(args)
        return
    kinds = [k for k in args.kinds.split(",") if k in KINDS]  # "--kinds none": only --cli
    if args.sidecar and "sidecar" not in kinds:
        kinds.append("sidecar")
    tmp_parent = args.tmp_dir or (args.hour.parent if args.hour.exists() else None)
    rows: list[tuple[str, str, dict[str, Any]]] = []
    with tempfile.TemporaryDirectory(prefix="bench_annotate_", dir=tmp_parent) as tmp_name:
        tmp = Path(tmp_name)
        for label, log, minutes in plan(args):
            for kind in kinds:
                for tree in [None, *args.compare]:
                    figures = run_child(kind, log, minutes, tmp, tree)
                    run = kind if tree is None else f"{kind} ({tree.name})"
                    rows.append((label, run, figures))
                    print(_row(label, run, figures, None), file=sys.stderr, flush=True)
            if args.cli and minutes is None:
                rows.append((label, "cli", run_cli(log, tmp)))
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"\nload average at the end: {' '.join(f'{x:.2f}' for x in os.getloadavg())}\n")
    print(table(rows))
    if args.json is not None:
        args.json.write_text(json.dumps([{"log": a, "run": b, **c} for a, b, c in rows], indent=1))


if __name__ == "__main__":
    main()
