"""Ground truth in `diff`: each version scored as `evaluate` scores it alone, and every pair
that differs between them labelled true or false.

Each side is labelled with its own ground truth (`evaluate_log` on that file), so the labels
agree with what `evaluate` says of each file: a pair counts as true when the ground truth has a
loop event at its query frame and refined match (within the frame tolerance).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from .diff import LogDiff, Pair
from .log_run import LogReport
from .metrics import RevisitCoverage


@dataclass(frozen=True)
class VersionScore:
    """What `evaluate` reports of one version's loop closures."""

    tp: int
    fp: int
    precision: float
    recall: float
    coverage: tuple[RevisitCoverage, ...]

    @classmethod
    def of(cls, report: LogReport) -> VersionScore:
        figures = report.reported
        return cls(figures.tp, figures.fp, figures.precision, figures.recall, figures.coverage)

    def coverage_share(self, window_s: float) -> float | None:
        return next((c.share for c in self.coverage if c.window_s == window_s), None)

    def to_json_dict(self) -> dict[str, Any]:
        return {
            "tp": self.tp,
            "fp": self.fp,
            "precision": self.precision,
            "recall": self.recall,
            "coverage": [
                {
                    "window_s": c.window_s,
                    "windows": c.windows,
                    "covered": c.covered,
                    "share": c.share,
                }
                for c in self.coverage
            ],
        }


@dataclass(frozen=True)
class LabelledPair:
    pair: Pair
    true: bool

    def to_json_dict(self) -> dict[str, Any]:
        return {**self.pair.to_json_dict(), "true": self.true}


@dataclass(frozen=True)
class TruthDiff:
    """The two versions' scores and the differing pairs of each side, labelled."""

    ground_truth: dict[str, Any]  # what the ground truth was (as `evaluate --json` says)
    a: VersionScore
    b: VersionScore
    only_a: list[LabelledPair]
    only_b: list[LabelledPair]
    different_match: list[tuple[LabelledPair, LabelledPair]]

    def side_pairs(self, side: str) -> list[LabelledPair]:
        """The pairs one side reports and the other does not (its own match where they differ)."""
        if side == "a":
            return self.only_a + [a for a, _ in self.different_match]
        return self.only_b + [b for _, b in self.different_match]

    def _turned_false(self) -> int:
        """Queries both report whose true match became a false one in B."""
        return sum(a.true and not b.true for a, b in self.different_match)

    @property
    def new_false(self) -> int:
        """False pairs B reports that A does not: only in B, or a true match of A's made false
        (a different match that stays false, or stays true, is no change at that query)."""
        return sum(not p.true for p in self.only_b) + self._turned_false()

    @property
    def lost_true(self) -> int:
        """True pairs A reports that B does not: only in A, or made false by B's match."""
        return sum(p.true for p in self.only_a) + self._turned_false()

    def label(self, side: str, pair: Pair) -> str:
        """ "true" or "false" for a differing pair of that side (the very object `diff`
        listed), "" for any other."""
        found = [p.true for p in self.side_pairs(side) if p.pair is pair]
        return ("true" if found[0] else "false") if found else ""

    def side_json(self, side: str) -> dict[str, Any]:
        score = self.a if side == "a" else self.b
        only = self.only_a if side == "a" else self.only_b
        index = 0 if side == "a" else 1
        return {
            **score.to_json_dict(),
            "only_here": [p.to_json_dict() for p in only],
            "different_match": [pair[index].to_json_dict() for pair in self.different_match],
        }

    def to_json_dict(self) -> dict[str, Any]:
        return {
            "ground_truth": self.ground_truth,
            "new_false": self.new_false,
            "lost_true": self.lost_true,
        }

    def format_lines(self) -> list[str]:
        rows = [("A", self.a, self.only_a, 0), ("B", self.b, self.only_b, 1)]
        lines = [f"ground truth: {_describe(self.ground_truth)}"]
        for name, score, only, index in rows:
            changed = [pair[index] for pair in self.different_match]
            lines.append(
                f"  {name}: TP {score.tp}, FP {score.fp}, precision {score.precision:.1%}, "
                f"recall {score.recall:.1%}{_coverage_text(score)}; only in {name}: "
                f"{_true_false(only)}; its other match: {_true_false(changed)}"
            )
        lines.append(
            f"  B reports {self.new_false} false pairs A does not, and misses "
            f"{self.lost_true} true pairs A reports"
        )
        return lines


def label_diff(
    diff: LogDiff, report_a: LogReport, report_b: LogReport, tolerance: int
) -> TruthDiff:
    """`diff`'s differing pairs labelled with each side's ground truth (`evaluate_log`)."""

    def labelled(report: LogReport, pairs: list[Pair]) -> list[LabelledPair]:
        truth = report.truth.are_true(
            [p.query_index for p in pairs], [p.match_index for p in pairs], tolerance
        )
        return [LabelledPair(p, bool(t)) for p, t in zip(pairs, truth, strict=True)]

    matching = diff.reported
    changed_a = labelled(report_a, [a for a, _ in matching.different_match])
    changed_b = labelled(report_b, [b for _, b in matching.different_match])
    return TruthDiff(
        report_a.ground_truth,
        VersionScore.of(report_a),
        VersionScore.of(report_b),
        labelled(report_a, matching.only_a),
        labelled(report_b, matching.only_b),
        list(zip(changed_a, changed_b, strict=True)),
    )


def _true_false(pairs: list[LabelledPair]) -> str:
    true = sum(p.true for p in pairs)
    return f"{len(pairs)} ({true} true, {len(pairs) - true} false)"


def _coverage_text(score: VersionScore) -> str:
    shares = ", ".join(f"{c.share:.1%} of {c.window_s:g} s windows" for c in score.coverage)
    return f", revisit coverage {shares}" if shares else ""


def _describe(info: dict[str, Any]) -> str:
    if info.get("kind") == "file":
        return str(info.get("file"))
    return f"pose topic {info.get('topic')} (radius {info.get('radius_m')} m)"
