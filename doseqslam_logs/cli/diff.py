"""`doseqslam-logs diff A.mcap B.mcap`: compare the loop closures of two annotated logs.

Exit codes follow diff(1): 0 when the reported loop closures are the same (parameter and
metadata differences alone are informational), 1 when they differ, 2 when the comparison
cannot be made: bad arguments, and also an input that is missing, unreadable or not annotated
(exit 3 in the other commands).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from ..errors import ExitCode, SourceError, UsageError
from ..evaluation.diff import diff_logs


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "diff",
        help="compare the loop closures of two annotated logs of the same source",
        description="Pair the reported loop closures of A and B by query time and sort them into "
        "common, only in A, only in B and same query with a different match; list the "
        "parameter and metadata differences and changed verification verdicts. Exit 0 when "
        "the reported loop closures are the same, 1 when they differ, 2 when the logs cannot "
        "be compared (missing, unreadable or not annotated).",
    )
    parser.add_argument("a", type=Path, metavar="A.mcap", help="annotated log (or sidecar)")
    parser.add_argument("b", type=Path, metavar="B.mcap", help="annotated log (or sidecar)")
    parser.add_argument(
        "--tolerance-ms",
        type=float,
        default=0.0,
        metavar="T",
        help="query (and match) times within T ms are the same (default 0: exact); keep it "
        "below half the frame interval",
    )
    parser.add_argument("--json", action="store_true", help="print the full lists as JSON")
    parser.set_defaults(run=run)


def tolerance_ns(milliseconds: float) -> int:
    """Raises UsageError for a negative or non-finite tolerance."""
    if not math.isfinite(milliseconds) or milliseconds < 0:
        raise UsageError(f"--tolerance-ms must be a finite number >= 0, got {milliseconds}")
    return round(milliseconds * 1_000_000)


def run(args: argparse.Namespace) -> int:
    tolerance = tolerance_ns(args.tolerance_ms)
    try:
        # A missing or non-annotated input is a usage error here (exit 2, like diff(1)).
        result = diff_logs(args.a, args.b, tolerance)
    except SourceError as exc:
        raise UsageError(str(exc)) from exc
    if args.json:
        print(json.dumps(result.to_json_dict(), indent=2))
    else:
        print(result.format_table())
    return int(ExitCode.OK if result.equal else ExitCode.DIFFERENT)
