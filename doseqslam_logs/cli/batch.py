"""`doseqslam-logs batch INPUTS... -o OUTDIR`: annotate many logs, in parallel, resumably."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from ..batch.discovery import discover_logs
from ..batch.engine import ENGINES, EngineSettings
from ..batch.manifest import MANIFEST_NAME
from ..errors import ExitCode, OutputError, UsageError
from ..sinks.atomic import check_output_path
from .annotate import add_run_options, annotate_options_from_args, positive_int
from .params_args import run_parameters


def default_jobs() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "batch",
        help="annotate many logs in parallel; a re-run skips the logs already done",
        description="Annotate every log of INPUTS (files, folders searched recursively for "
        ".mcap, .bag, .db3 and rosbag2 folders, glob patterns) into OUTDIR, mirroring their "
        "paths: DIR/a/x.mcap -> OUTDIR/a/x.annotated.mcap. A failing log is reported and the "
        "others go on. OUTDIR/manifest.jsonl records every attempt; a re-run skips logs done "
        "with the same content, options and tool version. Exit code 1 if any log failed.",
    )
    parser.add_argument("inputs", nargs="+", metavar="INPUT", help="log, folder or glob pattern")
    parser.add_argument("-o", "--output", type=Path, required=True, metavar="OUTDIR")
    parser.add_argument(
        "-j",
        "--jobs",
        type=positive_int,
        default=default_jobs(),
        metavar="N",
        help=f"logs annotated at a time (local engine; default: the CPUs, {default_jobs()})",
    )
    parser.add_argument(
        "--engine",
        choices=sorted(ENGINES),
        default="local",
        help="local: worker processes on this machine (default); ray: one Ray task per log "
        "(needs the 'ray' extra; every node must see INPUTS and OUTDIR under the same paths)",
    )
    parser.add_argument(
        "--address", metavar="ADDR", help="Ray cluster address (default: a local Ray instance)"
    )
    parser.add_argument(
        "--force", action="store_true", help="annotate every log again, even those up to date"
    )
    add_run_options(parser)
    parser.set_defaults(run=run)


def _check_outdir(outdir: Path) -> None:
    """OUTDIR is a folder, or does not exist yet (it is created), and its manifest a regular
    file or absent (a FIFO there would block the batch): anything else is exit 6."""
    if outdir.exists() and not outdir.is_dir():
        raise OutputError(f"{outdir}: the output folder exists and is not a folder")
    check_output_path(outdir / MANIFEST_NAME)


def run(args: argparse.Namespace) -> int:
    # Here, not above: the runner imports the pipeline (OpenCV, SciPy), which --help need not.
    from ..batch.report import ConsoleDisplay, summary_table
    from ..batch.runner import plan_batch, run_batch

    if args.address is not None and args.engine != "ray":
        raise UsageError("--address is the address of a Ray cluster: use it with --engine ray")
    _check_outdir(args.output)
    params = run_parameters(args)  # as annotate: the same defaults, the same outputs
    # Per-log frame-preparing threads: 2 as in annotate; the engines use 1 when logs run in
    # parallel (the cores are already busy).
    options = annotate_options_from_args(args, workers=2)
    logs = discover_logs(args.inputs, args.output)
    plan = plan_batch(logs, args.output, params, options, force=args.force)
    settings = EngineSettings(jobs=args.jobs, address=args.address)
    result = run_batch(plan, args.output, args.engine, settings, ConsoleDisplay())
    print(summary_table(result))
    if result.failed:
        manifest = args.output / MANIFEST_NAME
        print(
            f"doseqslam-logs: error: {len(result.failed)} of {len(plan.to_run)} logs failed "
            f"(details in {manifest}); a re-run retries them",
            file=sys.stderr,
        )
        return int(ExitCode.DIFFERENT)
    return int(ExitCode.OK)
