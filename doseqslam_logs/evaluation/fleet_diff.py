"""`diff DIR_A DIR_B`: two batch output folders (the same logs annotated by two versions)
compared log by log, and one comparison of two annotated logs with ground truth.

The logs of the two folders are matched by their source: the sha256 of the log that was
annotated (as the manifest, or each output's metadata, records it), else its file name. Each
matched pair is compared as `diff A.mcap B.mcap` compares two files; a log that only one side
annotated (or that failed on the other) is listed as such.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..annotations.reader import read_annotations
from ..batch.manifest import MANIFEST_NAME, last_entries
from ..errors import SourceError, UsageError
from .diff import LogDiff, diff_logs
from .diff_gate import GateFigures
from .diff_truth import TruthDiff, VersionScore, label_diff
from .log_run import LogEvaluationOptions, evaluate_log
from .metrics import COVERAGE_WINDOWS_S


@dataclass(frozen=True)
class TruthOptions:
    """evaluate's ground-truth options, for each side (`source` differs for sidecars)."""

    a: LogEvaluationOptions
    b: LogEvaluationOptions
    tolerance: int  # frames, as evaluate --tolerance


@dataclass(frozen=True)
class Comparison:
    """Two annotated logs of one source compared, labelled when ground truth was given."""

    diff: LogDiff
    truth: TruthDiff | None

    @property
    def equal(self) -> bool:
        return self.diff.equal

    def figures(self) -> GateFigures:
        matching = self.diff.reported
        changed = len(matching.different_match)
        truth = self.truth
        return GateFigures(
            new_pairs=len(matching.only_b) + changed,
            lost_pairs=len(matching.only_a) + changed,
            new_false=None if truth is None else truth.new_false,
            lost_true=None if truth is None else truth.lost_true,
            coverage_drop={} if truth is None else _coverage_drop([truth.a], [truth.b]),
        )

    def to_json_dict(self) -> dict[str, Any]:
        document = self.diff.to_json_dict()
        if self.truth is not None:
            truth = self.truth
            document.update(truth.to_json_dict())
            document["a"] = {**document["a"], **truth.side_json("a")}
            document["b"] = {**document["b"], **truth.side_json("b")}
            for side, key in (("a", "only_a"), ("b", "only_b")):
                document[key] = truth.side_json(side)["only_here"]
            document["different_match"] = [
                {"a": x.to_json_dict(), "b": y.to_json_dict()} for x, y in truth.different_match
            ]
        return document

    def format_table(self) -> str:
        truth = self.truth
        table = self.diff.format_table(label=None if truth is None else truth.label)
        if truth is None:
            return table
        body, _, result = table.rpartition("\n\n")
        return "\n".join([body, "", *truth.format_lines(), "", result])


def compare(a: Path, b: Path, tolerance_ns: int, truth: TruthOptions | None) -> Comparison:
    """`diff A B`: the reported loop closures paired by time; with `truth`, each version
    scored as `evaluate` scores it alone and every differing pair labelled."""
    log_a, log_b = read_annotations(a), read_annotations(b)  # once each, for both uses
    diff = diff_logs(log_a, log_b, tolerance_ns)
    if truth is None:
        return Comparison(diff, None)
    report_a, report_b = evaluate_log(log_a, truth.a), evaluate_log(log_b, truth.b)
    return Comparison(diff, label_diff(diff, report_a, report_b, truth.tolerance))


# -- two folders --------------------------------------------------------------------------


@dataclass(frozen=True)
class BatchRun:
    """One log of a batch folder: its source and its output (None when it failed)."""

    name: str  # the annotated log's file name
    sha256: str  # of the annotated log ("" when unknown)
    output: Path | None
    error: str = ""

    @property
    def key(self) -> str:
        return self.sha256 or f"name:{self.name}"


def batch_runs(folder: Path) -> list[BatchRun]:
    """The logs of a batch output folder (or of its manifest.jsonl): the last attempt of each
    log from the manifest; without a manifest, every annotated MCAP below the folder.

    Raises UsageError when `folder` is neither a folder nor a manifest.
    """
    manifest = folder / MANIFEST_NAME if folder.is_dir() else folder
    if manifest.is_file() and manifest.name.endswith(".jsonl"):
        return [
            BatchRun(
                Path(entry.input).name,
                entry.sha256,
                Path(entry.output) if entry.status == "ok" else None,
                entry.error,
            )
            for entry in last_entries(manifest).values()
        ]
    if not folder.is_dir():
        raise UsageError(f"{folder}: not a batch output folder, a manifest or an annotated log")
    return [_scanned(path) for path in sorted(folder.rglob("*.mcap")) if _visible(path, folder)]


def _visible(path: Path, folder: Path) -> bool:
    """Not a hidden or partial file (an atomic write in progress)."""
    return not any(part.startswith(".") for part in path.relative_to(folder).parts)


def _scanned(path: Path) -> BatchRun:
    try:
        meta = read_annotations(path).metadata
    except SourceError as exc:
        return BatchRun(path.name, "", None, str(exc))
    return BatchRun(Path(meta.source_file).name or path.name, meta.source_sha256, path)


@dataclass(frozen=True)
class LogRow:
    """One source log of the fleet: compared, or present (or annotated) on one side only."""

    name: str
    sha256: str
    state: str  # "compared", "only in A", "only in B", "failed in A", "failed in B", ...
    a: BatchRun | None
    b: BatchRun | None
    comparison: Comparison | None = None
    # Of a log that only one side annotated: its reported pairs and, with ground truth, score.
    one_side_pairs: int = 0
    one_side_score: VersionScore | None = None
    present_side: str = ""  # "a" or "b": the side that annotated a one-side log

    @property
    def lost(self) -> bool:
        """Only A annotated it: B lost its pairs (else B's are new)."""
        return self.present_side == "a"

    @property
    def changed(self) -> int:
        """Pairs that differ: only in A + only in B + different match (all of a one-side log)."""
        if self.comparison is None:
            return self.one_side_pairs
        counts = self.comparison.diff.reported.counts
        return counts["only_a"] + counts["only_b"] + counts["different_match"]

    def figures(self) -> GateFigures:
        if self.comparison is not None:
            return self.comparison.figures()
        score, lost = self.one_side_score, self.lost
        pairs = self.one_side_pairs
        coverage: dict[float, float] = {}
        if score is not None:
            empty = VersionScore(0, 0, 1.0, 0.0, ())
            coverage = _coverage_drop([score], [empty]) if lost else {}
        return GateFigures(
            new_pairs=0 if lost else pairs,
            lost_pairs=pairs if lost else 0,
            new_false=None if score is None else (0 if lost else score.fp),
            lost_true=None if score is None else (score.tp if lost else 0),
            coverage_drop=coverage,
        )

    def scores(self) -> tuple[VersionScore | None, VersionScore | None]:
        if self.comparison is not None and self.comparison.truth is not None:
            return self.comparison.truth.a, self.comparison.truth.b
        if self.one_side_score is None:
            return None, None
        return (self.one_side_score, None) if self.lost else (None, self.one_side_score)

    def to_json_dict(self) -> dict[str, Any]:
        a, b = self.scores()
        return {
            "name": self.name,
            "sha256": self.sha256,
            "state": self.state,
            "a": None if self.a is None else _run_json(self.a),
            "b": None if self.b is None else _run_json(self.b),
            "counts": None if self.comparison is None else self.comparison.diff.reported.counts,
            "one_side_pairs": self.one_side_pairs,
            "tp_fp": {
                side: None if s is None else {"tp": s.tp, "fp": s.fp}
                for side, s in (("a", a), ("b", b))
            },
            "comparison": None if self.comparison is None else self.comparison.to_json_dict(),
        }


def _run_json(run: BatchRun) -> dict[str, Any]:
    return {"output": None if run.output is None else str(run.output), "error": run.error}


_SAME_STATES = ("compared", "failed in both")  # a log that failed in both runs is no change


@dataclass(frozen=True)
class FleetDiff:
    a: Path
    b: Path
    rows: list[LogRow]
    ground_truth: bool = False
    warnings: list[str] = field(default_factory=list)

    @property
    def equal(self) -> bool:
        """Every log has the same pairs on both sides; one that failed in both is no change."""
        return all(row.state in _SAME_STATES and row.changed == 0 for row in self.rows)

    def figures(self) -> GateFigures:
        """The gate's figures summed over the logs, coverage pooled over their windows."""
        parts = [row.figures() for row in self.rows]
        known = [p for p in parts if p.new_false is not None]
        return GateFigures(
            new_pairs=sum(p.new_pairs for p in parts),
            lost_pairs=sum(p.lost_pairs for p in parts),
            new_false=sum(p.new_false or 0 for p in known) if self.ground_truth else None,
            lost_true=sum(p.lost_true or 0 for p in known) if self.ground_truth else None,
            coverage_drop=self.pooled_coverage_drop() if self.ground_truth else {},
        )

    def pooled_coverage_drop(self) -> dict[float, float]:
        """Coverage of A minus B (points) over every window of every log; a side that did not
        annotate a log covers none of its windows."""
        sides: list[list[VersionScore]] = [[], []]
        for row in self.rows:
            a, b = row.scores()
            reference = a or b
            if reference is None:
                continue
            empty = VersionScore(0, 0, 1.0, 0.0, _uncovered(reference))
            sides[0].append(a or empty)
            sides[1].append(b or empty)
        return _coverage_drop(sides[0], sides[1])

    def totals(self) -> dict[str, int]:
        compared = [r.comparison for r in self.rows if r.comparison is not None]
        counts = [c.diff.reported.counts for c in compared]
        totals = {
            key: sum(c[key] for c in counts)
            for key in ("common", "only_a", "only_b", "different_match")
        }
        totals["logs"] = len(self.rows)
        totals["compared"] = len(compared)
        totals["changed_logs"] = sum(
            1 for r in self.rows if r.changed or r.state not in _SAME_STATES
        )
        return totals

    def to_json_dict(self) -> dict[str, Any]:
        return {
            "equal": self.equal,
            "a": str(self.a),
            "b": str(self.b),
            "warnings": self.warnings,
            "totals": self.totals(),
            "logs": [row.to_json_dict() for row in self.rows],
            "only_a": [row.name for row in self.rows if row.state == "only in A"],
            "only_b": [row.name for row in self.rows if row.state == "only in B"],
        }

    def format_table(self) -> str:
        header = ["log", "state", "common", "only A", "only B", "diff match"]
        if self.ground_truth:
            header += ["TP/FP A", "TP/FP B"]
        rows = [header] + [row_cells(row, self.ground_truth) for row in self.rows]
        totals = self.totals()
        total = ["total", f"{totals['compared']} of {totals['logs']} compared"]
        total += [str(totals[k]) for k in ("common", "only_a", "only_b", "different_match")]
        if self.ground_truth:
            total += [_tp_fp(_summed(self.rows, 0)), _tp_fp(_summed(self.rows, 1))]
        lines = [f"A: {self.a}", f"B: {self.b}", *[f"warning: {w}" for w in self.warnings], ""]
        lines += _table([*rows, total])
        verdict = "the same" if self.equal else "different"
        lines += [
            "",
            f"result: {totals['changed_logs']} of {totals['logs']} logs differ; "
            f"the fleet's loop closures are {verdict} (exit {0 if self.equal else 1})",
        ]
        return "\n".join(lines)


def diff_folders(
    a: Path, b: Path, tolerance_ns: int = 0, truth: TruthOptions | None = None
) -> FleetDiff:
    """Compare two batch output folders log by log (see the module docstring)."""
    runs_a, runs_b = _by_key(batch_runs(a)), _by_key(batch_runs(b))
    rows = [
        _row(runs_a.get(key), runs_b.get(key), tolerance_ns, truth)
        for key in sorted(set(runs_a) | set(runs_b), key=lambda k: _sort_name(runs_a, runs_b, k))
    ]
    warnings = _name_warnings(rows)
    return FleetDiff(a, b, rows, truth is not None, warnings)


def _by_key(runs: list[BatchRun]) -> dict[str, BatchRun]:
    return {run.key: run for run in runs}


def _sort_name(
    runs_a: dict[str, BatchRun], runs_b: dict[str, BatchRun], key: str
) -> tuple[str, str]:
    run = runs_a.get(key) or runs_b[key]
    return (run.name, key)


def _row(
    a: BatchRun | None, b: BatchRun | None, tolerance_ns: int, truth: TruthOptions | None
) -> LogRow:
    run = a or b
    assert run is not None
    if a is not None and b is not None and a.output is not None and b.output is not None:
        comparison = compare(a.output, b.output, tolerance_ns, truth)
        return LogRow(run.name, run.sha256, "compared", a, b, comparison)
    state = _one_side_state(a, b)
    side = "a" if a is not None and a.output is not None else ""
    side = side or ("b" if b is not None and b.output is not None else "")
    present = a if side == "a" else b
    if present is None or present.output is None:
        return LogRow(run.name, run.sha256, state, a, b)
    log = read_annotations(present.output)
    pairs = len(log.reported_loop_closures)
    score = None
    if truth is not None:
        score = VersionScore.of(evaluate_log(log, truth.a if side == "a" else truth.b))
    return LogRow(run.name, run.sha256, state, a, b, None, pairs, score, side)


def _one_side_state(a: BatchRun | None, b: BatchRun | None) -> str:
    if a is None or b is None:
        return "only in A" if b is None else "only in B"
    if a.output is None and b.output is None:
        return "failed in both"
    return "failed in A" if a.output is None else "failed in B"


def _name_warnings(rows: list[LogRow]) -> list[str]:
    """Same file name, different content: the logs changed between the two runs."""
    one_side = [r for r in rows if r.state.startswith("only")]
    names: dict[str, int] = {}
    for row in one_side:
        names[row.name] = names.get(row.name, 0) + 1
    return [
        f"{name}: on both sides with different content (sha256 differs): not compared"
        for name, count in sorted(names.items())
        if count > 1
    ]


def _coverage_drop(a: list[VersionScore], b: list[VersionScore]) -> dict[float, float]:
    drop = {}
    for window in COVERAGE_WINDOWS_S:
        share_a, share_b = _pooled_share(a, window), _pooled_share(b, window)
        if share_a is not None and share_b is not None:
            drop[window] = 100.0 * (share_a - share_b)
        elif share_a is not None:
            drop[window] = 100.0 * share_a
    return drop


def _pooled_share(scores: list[VersionScore], window: float) -> float | None:
    cells = [c for s in scores for c in s.coverage if c.window_s == window]
    windows = sum(c.windows for c in cells)
    return sum(c.covered for c in cells) / windows if windows else None


def _uncovered(score: VersionScore) -> tuple[Any, ...]:
    from .metrics import RevisitCoverage

    return tuple(RevisitCoverage(c.window_s, c.windows, 0) for c in score.coverage)


def row_cells(row: LogRow, ground_truth: bool) -> list[str]:
    if row.comparison is not None:
        counts = row.comparison.diff.reported.counts
        cells = [str(counts[k]) for k in ("common", "only_a", "only_b", "different_match")]
    else:
        pairs = str(row.one_side_pairs)
        cells = ["-"] * 4
        if row.present_side:
            cells[1 if row.lost else 2] = pairs
    cells = [row.name, row.state, *cells]
    if ground_truth:
        a, b = row.scores()
        cells += [_tp_fp(a), _tp_fp(b)]
    return cells


def _summed(rows: list[LogRow], side: int) -> VersionScore | None:
    scores = [s for s in (row.scores()[side] for row in rows) if s is not None]
    if not scores:
        return None
    return VersionScore(sum(s.tp for s in scores), sum(s.fp for s in scores), 0.0, 0.0, ())


def _tp_fp(score: VersionScore | None) -> str:
    return "-" if score is None else f"{score.tp}/{score.fp}"


def _table(rows: list[list[str]]) -> list[str]:
    widths = [max(len(row[c]) for row in rows) for c in range(len(rows[0]))]
    return [
        "  " + "  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip()
        for row in rows
    ]
