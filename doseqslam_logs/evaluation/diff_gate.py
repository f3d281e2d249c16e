"""`diff --fail-on RULES`: the regressions that stop a release, as a distinct exit code.

RULES is a comma-separated list of `name` or `name=LIMIT`; a rule fails when B's figure
exceeds its limit (default 0). A is the reference, B the candidate version:

- `new-false`: false loop closures B reports that A does not (needs ground truth); a query
  both report with different matches counts when A's match was true and B's is false;
- `lost-true`: true loop closures A reports that B does not, counted the same way;
- `coverage-drop`: percentage points of revisit coverage B loses against A, in any window
  length (needs ground truth);
- `new-pairs`, `lost-pairs`: loop closures only B (only A) reports, a different match
  counted on both sides (no ground truth needed).

Over two batch folders the figures are summed over the logs (coverage pooled over their
windows); a log that only one side annotated counts all its pairs as new or lost.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from ..errors import UsageError

# Rule name -> whether it needs ground truth.
RULES = {
    "new-false": True,
    "lost-true": True,
    "coverage-drop": True,
    "new-pairs": False,
    "lost-pairs": False,
}


@dataclass(frozen=True)
class GateFigures:
    """What the rules look at; the ground-truth figures are None without ground truth."""

    new_pairs: int
    lost_pairs: int
    new_false: int | None = None
    lost_true: int | None = None
    # Percentage points A's coverage is above B's, per window length (s).
    coverage_drop: dict[float, float] = field(default_factory=dict)

    def value(self, rule: str) -> float | None:
        if rule == "coverage-drop":
            return max(self.coverage_drop.values(), default=0.0) if self.coverage_drop else None
        values = {
            "new-false": self.new_false,
            "lost-true": self.lost_true,
            "new-pairs": self.new_pairs,
            "lost-pairs": self.lost_pairs,
        }
        return values[rule]


@dataclass(frozen=True)
class Gate:
    limits: dict[str, float]

    @property
    def needs_ground_truth(self) -> list[str]:
        return [rule for rule in self.limits if RULES[rule]]

    def failures(self, figures: GateFigures) -> list[str]:
        """One line per failed rule, e.g. "new-false: 3 > 0"."""
        failed = []
        for rule, limit in self.limits.items():
            value = figures.value(rule)
            if value is not None and value > limit + 1e-9:
                failed.append(f"{rule}: {_number(value)} > {_number(limit)}")
        return failed

    def to_json_dict(self, figures: GateFigures) -> dict[str, Any]:
        failed = self.failures(figures)
        return {
            "rules": self.limits,
            "figures": {rule: figures.value(rule) for rule in self.limits},
            "failed": failed,
            "passed": not failed,
        }


def parse_gate(text: str) -> Gate:
    """`new-false,lost-true=2,coverage-drop=1.5` -> Gate; UsageError for anything else."""
    limits: dict[str, float] = {}
    for item in (part.strip() for part in text.split(",")):
        if not item:
            continue
        name, _, limit = item.partition("=")
        if name not in RULES:
            raise UsageError(f"--fail-on: unknown rule {name!r} (rules: {', '.join(RULES)})")
        limits[name] = _limit(name, limit) if limit else 0.0
    if not limits:
        raise UsageError(f"--fail-on: no rule given (rules: {', '.join(RULES)})")
    return Gate(limits)


def _limit(name: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or value < 0:
        raise UsageError(f"--fail-on {name}={text}: the limit must be a number >= 0")
    return value


def _number(value: float) -> str:
    return f"{value:g}" if value != int(value) else str(int(value))
