"""Compare the loop closures of two annotated logs of the same source (the `diff` command).

Pairs are matched by time, not by frame index, so that runs over different ranges or with
skipped frames still line up. The time of a frame is its image's header stamp when it has one,
else its log time (whatever `--time-source` the runs used). Each log reports at most one match
per query frame; the queries of A and B are paired one to one:

1. pairs with the same query time and the same match time (exactly) first;
2. then the remaining queries in time order: the earliest unpaired query of A and of B are
   paired when their times are within the tolerance; otherwise the earlier one stays unpaired.

Step 2 pairs as many of the remaining queries as possible (for points on a line with a
tolerance, this greedy matching is maximum) and both steps treat A and B alike, so swapping the
logs swaps only in A and only in B. A paired query is *common* when the match times are within
the tolerance too, else a *different match*. Keep the tolerance below half the frame interval:
then every query has at most one partner and the pairing is unambiguous.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..annotations.reader import AnnotatedLog, read_annotations
from ..annotations.records import NANOS_PER_SECOND, NOT_RECORDED, LoopClosureRecord

# Metadata differences listed first, in this order; the others follow by name.
FIRST_METADATA = (
    "tool_version",
    "parameters_hash",
    "verification_hash",
    "method",
    "feature_detector",
    "source_file",
)
SHOWN_PAIRS = 5  # differing pairs listed per class in the table
# (side "a" or "b", pair) -> a label shown beside the pair ("true", "false").
Labeller = Callable[[str, "Pair"], str]


@dataclass(frozen=True, order=True)
class Pair:
    """One loop closure, placed in time: query (newer) frame and matched (older) frame."""

    query_time_ns: int
    match_time_ns: int
    query_index: int
    match_index: int
    verification: str | None = field(default=None, compare=False)  # None: not recorded

    def to_json_dict(self) -> dict[str, Any]:
        return {
            "query_time_ns": self.query_time_ns,
            "query_index": self.query_index,
            "match_time_ns": self.match_time_ns,
            "match_index": self.match_index,
            "verification": self.verification,
        }


@dataclass(frozen=True)
class Matching:
    """The pairs of A and B sorted into the four classes."""

    common: list[tuple[Pair, Pair]]
    different_match: list[tuple[Pair, Pair]]
    only_a: list[Pair]
    only_b: list[Pair]

    @property
    def counts(self) -> dict[str, int]:
        return {
            "common": len(self.common),
            "only_a": len(self.only_a),
            "only_b": len(self.only_b),
            "different_match": len(self.different_match),
        }

    @property
    def equal(self) -> bool:
        return not (self.only_a or self.only_b or self.different_match)


@dataclass(frozen=True)
class ValueDifference:
    """One parameter or metadata value that differs; None where a log lacks it."""

    name: str
    a: Any
    b: Any

    def to_json_dict(self) -> dict[str, Any]:
        return {"name": self.name, "a": self.a, "b": self.b}


@dataclass(frozen=True)
class VerdictChanges:
    """Geometric-verification verdicts of the candidate pairs both logs hold."""

    compared: int  # candidate pairs (same query, same match) present in both logs
    changed: list[tuple[Pair, Pair]]

    @property
    def by_change(self) -> dict[str, int]:
        """{"accepted -> rejected": count, ...}, sorted by name."""
        counts = Counter(f"{a.verification} -> {b.verification}" for a, b in self.changed)
        return dict(sorted(counts.items()))


@dataclass(frozen=True)
class LogSummary:
    path: str
    tool_version: str
    parameters_hash: str
    source_file: str
    source_sha256: str
    loop_closures: int  # every pair decided on, rejected and skipped ones included
    reported: int

    def to_json_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class LogDiff:
    """Everything `diff` reports about two annotated logs."""

    a: LogSummary
    b: LogSummary
    tolerance_ns: int
    reported: Matching
    verdicts: VerdictChanges | None  # None when a log does not record verification
    parameter_differences: list[ValueDifference]
    metadata_differences: list[ValueDifference]
    warnings: list[str]

    @property
    def equal(self) -> bool:
        """The reported loop closures are the same (within the tolerance); metadata aside."""
        return self.reported.equal

    def to_json_dict(self) -> dict[str, Any]:
        return {
            "equal": self.equal,
            "tolerance_ms": self.tolerance_ns / 1e6,
            "a": self.a.to_json_dict(),
            "b": self.b.to_json_dict(),
            "same_source": self.a.source_sha256 == self.b.source_sha256 != "",
            "warnings": self.warnings,
            "counts": self.reported.counts,
            "common": _pairs_json(self.reported.common),
            "only_a": [p.to_json_dict() for p in self.reported.only_a],
            "only_b": [p.to_json_dict() for p in self.reported.only_b],
            "different_match": _pairs_json(self.reported.different_match),
            "verdict_changes": _verdicts_json(self.verdicts),
            "parameter_differences": [d.to_json_dict() for d in self.parameter_differences],
            "metadata_differences": [d.to_json_dict() for d in self.metadata_differences],
        }

    def format_table(self, shown: int = SHOWN_PAIRS, label: Labeller | None = None) -> str:
        """The human report: logs, counts per class, differences, the first differing pairs
        (with `label(side, pair)`, "a" or "b", in a column of their own: "true", "false")."""
        lines = [_log_line("A", self.a), _log_line("B", self.b)]
        lines += [f"warning: {w}" for w in self.warnings]
        lines += ["", *_counts_lines(self)]
        lines += ["", _verdicts_line(self.verdicts)]
        lines += _differences_lines("parameters", "name", self.parameter_differences)
        lines += _differences_lines("metadata", "key", self.metadata_differences)
        lines += _pair_lines(self.reported, shown, label)
        verdict = "the same" if self.equal else "different"
        lines += [
            "",
            f"result: reported loop closures are {verdict} (exit {0 if self.equal else 1})",
        ]
        return "\n".join(lines)


def candidate_pair(loop_closure: LoopClosureRecord) -> Pair:
    """The pair as the detector proposed it (the match before any refinement)."""
    return Pair(
        loop_closure.query.time_ns,
        loop_closure.match.time_ns,
        loop_closure.query.index,
        loop_closure.match.index,
        loop_closure.verification or None,  # None: not recorded (before verification)
    )


def reported_pair(loop_closure: LoopClosureRecord) -> Pair:
    """The pair as the run reports it: with the refined match when verification refined it."""
    pair = candidate_pair(loop_closure)
    refined = loop_closure.matched
    return Pair(
        pair.query_time_ns, refined.time_ns, pair.query_index, refined.index, pair.verification
    )


def match_pairs(a: Sequence[Pair], b: Sequence[Pair], tolerance_ns: int = 0) -> Matching:
    """Pair the queries of A and B (see the module docstring) and classify every pair."""
    if tolerance_ns < 0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance_ns} ns")
    exact, rest_a, rest_b = _exactly_equal(sorted(a), sorted(b))
    common = list(exact)
    different: list[tuple[Pair, Pair]] = []
    only_a: list[Pair] = []
    only_b: list[Pair] = []
    i = j = 0
    while i < len(rest_a) and j < len(rest_b):
        pair_a, pair_b = rest_a[i], rest_b[j]
        if abs(pair_a.query_time_ns - pair_b.query_time_ns) <= tolerance_ns:
            same_match = abs(pair_a.match_time_ns - pair_b.match_time_ns) <= tolerance_ns
            (common if same_match else different).append((pair_a, pair_b))
            i, j = i + 1, j + 1
        elif pair_a.query_time_ns < pair_b.query_time_ns:
            only_a.append(pair_a)
            i += 1
        else:
            only_b.append(pair_b)
            j += 1
    only_a += rest_a[i:]
    only_b += rest_b[j:]
    common.sort()
    return Matching(common, different, only_a, only_b)


def _exactly_equal(
    a: list[Pair], b: list[Pair]
) -> tuple[list[tuple[Pair, Pair]], list[Pair], list[Pair]]:
    """Pairs with equal query and match times (a merge of two sorted lists), and the rest."""
    key = _time_key
    equal: list[tuple[Pair, Pair]] = []
    rest_a: list[Pair] = []
    rest_b: list[Pair] = []
    i = j = 0
    while i < len(a) and j < len(b):
        if key(a[i]) == key(b[j]):
            equal.append((a[i], b[j]))
            i, j = i + 1, j + 1
        elif key(a[i]) < key(b[j]):
            rest_a.append(a[i])
            i += 1
        else:
            rest_b.append(b[j])
            j += 1
    return equal, rest_a + a[i:], rest_b + b[j:]


def _time_key(pair: Pair) -> tuple[int, int]:
    return (pair.query_time_ns, pair.match_time_ns)


def verdict_changes(a: AnnotatedLog, b: AnnotatedLog, tolerance_ns: int) -> VerdictChanges | None:
    """Verdicts of the candidate pairs both logs hold; None unless both record verification."""
    if not (_records_verification(a) and _records_verification(b)):
        return None
    matching = match_pairs(
        [candidate_pair(lc) for lc in a.loop_closures],
        [candidate_pair(lc) for lc in b.loop_closures],
        tolerance_ns,
    )
    changed = [(x, y) for x, y in matching.common if x.verification != y.verification]
    return VerdictChanges(len(matching.common), changed)


def _records_verification(log: AnnotatedLog) -> bool:
    """Logs annotated before verification existed lack the field on every pair."""
    return any(lc.verification != NOT_RECORDED for lc in log.loop_closures)


def parameter_differences(a: AnnotatedLog, b: AnnotatedLog) -> list[ValueDifference]:
    """Every recorded parameter that differs, by dotted name (see `recorded_parameters`)."""
    params_a = recorded_parameters(a.metadata.recorded)
    params_b = recorded_parameters(b.metadata.recorded)
    return [
        ValueDifference(name, params_a.get(name), params_b.get(name))
        for name in sorted(set(params_a) | set(params_b))
        if params_a.get(name) != params_b.get(name)
    ]


def recorded_parameters(metadata: Mapping[str, str]) -> dict[str, Any]:
    """The JSON parameter sets of the metadata, flat: "parameters" by name, any other
    "X_parameters" record (e.g. of the verification stage) as "X.name"."""
    flat: dict[str, Any] = {}
    for key in sorted(metadata):
        if _is_parameters_key(key):
            prefix = "" if key == "parameters" else key.removesuffix("_parameters") + "."
            _flatten(prefix, _json_or_text(metadata[key]), flat)
    return flat


def _is_parameters_key(key: str) -> bool:
    return key == "parameters" or key.endswith("_parameters")


def _json_or_text(text: str) -> Any:
    try:
        return json.loads(text)
    except ValueError:
        return text


def _flatten(prefix: str, value: Any, into: dict[str, Any]) -> None:
    if isinstance(value, dict):
        for name, item in value.items():
            _flatten(f"{prefix}{name}.", item, into)
    else:
        into[prefix.removesuffix(".") or "parameters"] = value


def metadata_differences(a: AnnotatedLog, b: AnnotatedLog) -> list[ValueDifference]:
    """Every other metadata value that differs (the source's hash goes into a warning)."""
    entries_a, entries_b = a.metadata.recorded, b.metadata.recorded
    keys = set(entries_a) | set(entries_b)
    compared = [k for k in keys if not _is_parameters_key(k) and k != "source_sha256"]
    ordered = sorted(compared, key=_metadata_rank)
    return [
        ValueDifference(key, entries_a.get(key), entries_b.get(key))
        for key in ordered
        if entries_a.get(key) != entries_b.get(key)
    ]


def _metadata_rank(key: str) -> tuple[int, str]:
    first = FIRST_METADATA.index(key) if key in FIRST_METADATA else len(FIRST_METADATA)
    return (first, key)


def source_warnings(a: LogSummary, b: LogSummary) -> list[str]:
    """A warning, not an error: comparing runs over different sources is allowed but suspect."""
    if not a.source_sha256 or not b.source_sha256:
        missing = " and ".join(name for name, s in (("A", a), ("B", b)) if not s.source_sha256)
        return [f"the source of {missing} is not recorded: cannot tell whether the sources match"]
    if a.source_sha256 == b.source_sha256:
        return []
    return [
        f"different sources: A was annotated from {a.source_file} (sha256 "
        f"{a.source_sha256[:12]}...), B from {b.source_file} (sha256 {b.source_sha256[:12]}...); "
        "loop closures are compared by time only"
    ]


def summarize(log: AnnotatedLog, reported: int) -> LogSummary:
    meta = log.metadata
    return LogSummary(
        str(log.path),
        meta.tool_version,
        meta.parameters_hash,
        meta.source_file,
        meta.source_sha256,
        len(log.loop_closures),
        reported,
    )


def diff_logs(
    a: AnnotatedLog | str | Path, b: AnnotatedLog | str | Path, tolerance_ns: int = 0
) -> LogDiff:
    """Compare the reported loop closures, verdicts, parameters and metadata of two logs
    (annotated logs or sidecars, as paths or already read), as the `diff` command does.

    Raises ValueError for a negative tolerance, SourceError for an input that is not an
    annotated log, or a loop closure that lacks the fields of the contract or names a frame
    outside the log's frame times.
    """
    a = a if isinstance(a, AnnotatedLog) else read_annotations(a)
    b = b if isinstance(b, AnnotatedLog) else read_annotations(b)
    reported_a, reported_b = _reported_pairs(a), _reported_pairs(b)
    summary_a, summary_b = summarize(a, len(reported_a)), summarize(b, len(reported_b))
    return LogDiff(
        summary_a,
        summary_b,
        tolerance_ns,
        match_pairs(reported_a, reported_b, tolerance_ns),
        verdict_changes(a, b, tolerance_ns),
        parameter_differences(a, b),
        metadata_differences(a, b),
        source_warnings(summary_a, summary_b),
    )


def _reported_pairs(log: AnnotatedLog) -> list[Pair]:
    return [reported_pair(lc) for lc in log.reported_loop_closures]


# --- JSON and table helpers -------------------------------------------------------------


def _pairs_json(pairs: list[tuple[Pair, Pair]]) -> list[dict[str, Any]]:
    return [{"a": x.to_json_dict(), "b": y.to_json_dict()} for x, y in pairs]


def _verdicts_json(verdicts: VerdictChanges | None) -> dict[str, Any] | None:
    if verdicts is None:
        return None
    return {
        "compared": verdicts.compared,
        "changed": len(verdicts.changed),
        "by_change": verdicts.by_change,
        "pairs": _pairs_json(verdicts.changed),
    }


def _seconds(time: int) -> str:
    return f"{time / NANOS_PER_SECOND:.3f}"


def _log_line(name: str, log: LogSummary) -> str:
    return (
        f"{name}: {log.path} (doseqslam-logs {log.tool_version or '?'}, parameters "
        f"{log.parameters_hash or '?'}, {log.reported} reported of {log.loop_closures} "
        f"loop closures, source {log.source_file or '?'})"
    )


def _table(rows: list[list[str]], indent: str = "  ") -> list[str]:
    """Left-aligned columns; a column of numbers only is right-aligned."""
    widths = [max(len(row[c]) for row in rows) for c in range(len(rows[0]))]
    numeric = [all(row[c].isdigit() for row in rows[1:]) for c in range(len(rows[0]))]
    return [
        indent
        + "  ".join(
            cell.rjust(w) if num else cell.ljust(w)
            for cell, w, num in zip(row, widths, numeric, strict=True)
        ).rstrip()
        for row in rows
    ]


def _counts_lines(diff: LogDiff) -> list[str]:
    tolerance = f"within {diff.tolerance_ns / 1e6:g} ms" if diff.tolerance_ns else "exact times"
    counts = diff.reported.counts
    rows = [
        ["class", "pairs"],
        ["common", str(counts["common"])],
        ["only in A", str(counts["only_a"])],
        ["only in B", str(counts["only_b"])],
        ["different match", str(counts["different_match"])],
    ]
    return [f"reported loop closures, paired by query time ({tolerance}):", *_table(rows)]


def _verdicts_line(verdicts: VerdictChanges | None) -> str:
    if verdicts is None:
        return "verification verdicts: not compared (not recorded in both logs)"
    changes = ", ".join(f"{name}: {count}" for name, count in verdicts.by_change.items())
    return (
        f"verification verdicts: {len(verdicts.changed)} changed of {verdicts.compared} "
        f"candidate pairs in both logs" + (f" ({changes})" if changes else "")
    )


def _value(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float) and math.isfinite(value):
        return repr(value)
    return str(value) if value != "" else '""'


def _differences_lines(title: str, column: str, diffs: list[ValueDifference]) -> list[str]:
    if not diffs:
        return [f"{title}: no difference"]
    rows = [[column, "A", "B"], *([d.name, _value(d.a), _value(d.b)] for d in diffs)]
    verb = "differs" if len(diffs) == 1 else "differ"
    return [f"{title}: {len(diffs)} {verb}", *_table(rows)]


def _frame(time: int, index: int) -> str:
    return f"{_seconds(time)} (#{index})"


def _pair_lines(matching: Matching, shown: int, label: Labeller | None) -> list[str]:
    lines: list[str] = []
    truth = [] if label is None else ["ground truth"]
    sides = (("only in A", "a", matching.only_a), ("only in B", "b", matching.only_b))
    for name, side, pairs in sides:
        if pairs:
            lines += ["", f"{name} (first {min(shown, len(pairs))} of {len(pairs)}):"]
            rows = [["query time (index)", "match time (index)", *truth]]
            rows += [
                [
                    _frame(p.query_time_ns, p.query_index),
                    _frame(p.match_time_ns, p.match_index),
                    *([] if label is None else [label(side, p)]),
                ]
                for p in pairs[:shown]
            ]
            lines += _table(rows)
    if matching.different_match:
        count = len(matching.different_match)
        lines += ["", f"different match (first {min(shown, count)} of {count}):"]
        both = [] if label is None else ["A is", "B is"]
        rows = [["query time (index A, B)", "match in A", "match in B", *both]]
        rows += [
            [
                f"{_seconds(x.query_time_ns)} (#{x.query_index}, #{y.query_index})",
                _frame(x.match_time_ns, x.match_index),
                _frame(y.match_time_ns, y.match_index),
                *([] if label is None else [label("a", x), label("b", y)]),
            ]
            for x, y in matching.different_match[:shown]
        ]
        lines += _table(rows)
    return lines
