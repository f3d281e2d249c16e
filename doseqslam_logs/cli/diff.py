"""`doseqslam-logs diff A B`: compare the loop closures of two annotated logs, or of two batch
output folders log by log; with ground truth, say which differing pairs are true.

Exit codes follow diff(1): 0 when the reported loop closures are the same (parameter and
metadata differences alone are informational), 1 when they differ, 2 when the comparison
cannot be made: bad arguments, and also an input that is missing, unreadable or not annotated
(exit 3 in the other commands). With --fail-on, 7 when a rule fails and 0 otherwise (a
difference that breaks no rule passes the gate).
"""

from __future__ import annotations

import argparse
import json
import math
import re
from pathlib import Path
from typing import Any

from ..errors import ExitCode, SourceError, UsageError
from ..evaluation.diff_gate import Gate, GateFigures, parse_gate
from .evaluate_log import (
    add_pose_truth_options,
    add_source_check_option,
    add_truth_file_options,
)

_TRUTH_FLAGS = {
    "gt_variable": "--gt-variable",
    "radius": "--radius",
    "max_heading": "--max-heading",
    "min_travel": "--min-travel",
    "source": "--source",
    "no_source_check": "--no-source-check",
}


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "diff",
        help="compare the loop closures of two annotated logs (or two batch folders) of the "
        "same sources",
        description="Pair the reported loop closures of A and B by query time and sort them into "
        "common, only in A, only in B and same query with a different match; list the "
        "parameter and metadata differences and changed verification verdicts. A and B may be "
        "two batch output folders (or their manifest.jsonl): their logs are matched by source "
        "(sha256, else name) and compared one by one. With ground truth (--gt or --gt-topic, "
        "as evaluate takes it) each version is scored as evaluate scores it and every differing "
        "pair is labelled true or false. Exit 0 when the reported loop closures are the same, "
        "1 when they differ, 2 when they cannot be compared (missing, unreadable or not "
        "annotated); with --fail-on, 7 when a rule fails, else 0.",
    )
    parser.add_argument("a", type=Path, metavar="A", help="annotated log (or sidecar), or folder")
    parser.add_argument("b", type=Path, metavar="B", help="annotated log (or sidecar), or folder")
    parser.add_argument(
        "--tolerance-ms",
        type=float,
        default=0.0,
        metavar="T",
        help="query (and match) times within T ms are the same (default 0: exact); keep it "
        "below half the frame interval",
    )
    parser.add_argument("--json", action="store_true", help="print the full lists as JSON")
    _add_truth_options(parser)
    parser.add_argument(
        "--fail-on",
        metavar="RULES",
        help="exit 7 when B regresses against A: comma-separated rules, each NAME or "
        "NAME=LIMIT (default limit 0): new-false, lost-true, coverage-drop (percentage "
        "points; these three need ground truth), new-pairs, lost-pairs",
    )
    parser.add_argument(
        "--report",
        type=Path,
        metavar="REPORT.md",
        help="also write a markdown report with a picture of what changed per log and the "
        "trajectories of the logs that changed most (beside it; needs matplotlib)",
    )
    parser.set_defaults(run=run)


def _add_truth_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group(
        "ground truth", "as evaluate OUT.mcap takes it: --gt FILE, or --gt-topic with --radius"
    )
    add_truth_file_options(group)
    add_pose_truth_options(group)
    group.add_argument(
        "--source",
        type=Path,
        metavar="LOG",
        help="the log A and B were annotated from, when they are sidecars",
    )
    add_source_check_option(group)


def tolerance_ns(milliseconds: float) -> int:
    """Raises UsageError for a negative or non-finite tolerance."""
    if not math.isfinite(milliseconds) or milliseconds < 0:
        raise UsageError(f"--tolerance-ms must be a finite number >= 0, got {milliseconds}")
    return round(milliseconds * 1_000_000)


def truth_options(args: argparse.Namespace, folders: bool) -> Any:
    """The ground-truth options for both sides (a fleet_diff.TruthOptions), or None."""
    from ..evaluation.fleet_diff import TruthOptions
    from ..evaluation.log_run import LogEvaluationOptions, check_options

    if args.tolerance < 0:
        raise UsageError(f"--tolerance must be >= 0, got {args.tolerance}")
    if args.gt is None and args.gt_topic is None:
        given = [
            flag for name, flag in _TRUTH_FLAGS.items() if getattr(args, name) not in (None, False)
        ]
        if given:
            raise UsageError(f"{', '.join(given)}: only with --gt or --gt-topic")
        return None
    if folders and args.gt is not None:
        raise UsageError("--gt: one matrix is one log's; compare folders with --gt-topic")
    if folders and args.source is not None:
        raise UsageError("--source: batch folders hold full copies; not with folders")
    options = LogEvaluationOptions(
        gt=args.gt,
        gt_variable=args.gt_variable,
        gt_topic=args.gt_topic,
        radius=args.radius,
        max_heading=args.max_heading,
        min_travel=args.min_travel,
        tolerance=args.tolerance,
        source=args.source,
        source_check=not args.no_source_check,
    )
    check_options(options)
    return TruthOptions(options, options, args.tolerance)


def run(args: argparse.Namespace) -> int:
    from ..evaluation import fleet_diff

    tolerance = tolerance_ns(args.tolerance_ms)
    folders = args.a.is_dir() or args.b.is_dir() or _is_manifest(args.a) or _is_manifest(args.b)
    truth = truth_options(args, folders)
    gate = _gate(args.fail_on, truth is not None)
    if args.report is not None:
        from ..evaluation.diff_report import check_report

        check_report(args.report)
    try:
        # A missing or non-annotated input is a usage error here (exit 2, like diff(1)).
        if folders:
            result: Any = fleet_diff.diff_folders(args.a, args.b, tolerance, truth)
        else:
            result = fleet_diff.compare(args.a, args.b, tolerance, truth)
    except SourceError as exc:
        raise UsageError(str(exc)) from exc
    figures: GateFigures = result.figures()
    document = result.to_json_dict()
    if gate is not None:
        document["gate"] = gate.to_json_dict(figures)
    if args.report is not None:
        from ..evaluation.diff_report import write_report

        document["report"] = [str(p) for p in write_report(args.report, result, gate)]
    print(json.dumps(document, indent=2) if args.json else _text(result, gate, figures, document))
    if gate is not None:
        return int(ExitCode.REGRESSION if gate.failures(figures) else ExitCode.OK)
    return int(ExitCode.OK if result.equal else ExitCode.DIFFERENT)


def _is_manifest(path: Path) -> bool:
    return path.suffix == ".jsonl"


def _gate(rules: str | None, ground_truth: bool) -> Gate | None:
    if rules is None:
        return None
    gate = parse_gate(rules)
    if gate.needs_ground_truth and not ground_truth:
        raise UsageError(
            f"--fail-on {', '.join(gate.needs_ground_truth)}: needs ground truth "
            "(--gt or --gt-topic)"
        )
    return gate


def _text(result: Any, gate: Gate | None, figures: GateFigures, document: dict[str, Any]) -> str:
    lines = [result.format_table()]
    if gate is not None:  # the gate's verdict is the exit code, not the result line's
        lines = [re.sub(r" \(exit [01]\)$", "", lines[0], flags=re.MULTILINE)]
        failed = gate.failures(figures)
        verdict = "FAILED: " + "; ".join(failed) + " (exit 7)" if failed else "passed (exit 0)"
        lines.append(f"gate {', '.join(gate.limits)}: {verdict}")
    lines += [f"wrote {path}" for path in document.get("report", [])]
    return "\n".join(lines)
