"""Whether a run's frames held enough features for the segmentation and the verification.

On small or texture-poor frames (thumbnails, SeqSLAM's 64x32 benchmarks, night, fog) ORB
finds almost nothing: the segmentation then cuts sequences only at the length cap, and
verification rejects every candidate because it cannot even try ("too few features", "too
few matches"). Such a run ends with 0 loop closures like a run on a route that never comes
back. `FeatureHealth` measures it per run and words a warning for the summary line, `--json`,
the metadata, `evaluate` and `batch`, so that "could not check" never reads as "found nothing".

Thresholds: healthy frames leave a few of a run's frames under the segmentation's need and a
few of its checks impossible ("too few features"); thumbnails leave nearly all of them. A run is
called feature-poor from half of its frames or half of its checks on, far from both sides.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass
from statistics import median
from typing import Any

from ..detector import Parameters
from ..verification.stage import SKIPPED_REASONS, VerifiedDecision
from .replay import ReplayResult

# Shares from which a run is called feature-poor: far from healthy and from thumbnail runs
# alike (module docstring).
POOR_FRAME_SHARE = 0.5
IMPOSSIBLE_CHECK_SHARE = 0.5
# The verdict reasons of a check whose robust fit was never attempted.
IMPOSSIBLE_REASONS = ("too few features", "too few matches")
ADVICE = (
    "try --method seqslam --no-verify (SeqSLAM needs no features; without verification "
    "there is no precision check: read its pairs with care)"
)


@dataclass(frozen=True)
class SegmentationFeatures:
    """Features per frame of the segmentation detector, and how many frames had too few."""

    detector: str
    need: int  # min_features: a frame with fewer cannot end or seed a sequence
    frames: int  # frames measured (0: the method has no feature segmentation)
    below_need: int
    median: float
    image_size: str  # "WxH" of the first frame ("" when unknown)

    @classmethod
    def of(
        cls, detector: str, need: int, counts: Iterable[int], image_size: str
    ) -> SegmentationFeatures:
        measured = [count for count in counts if count >= 0]
        below = sum(count < need for count in measured)
        middle = float(median(measured)) if measured else 0.0
        return cls(detector, need, len(measured), below, middle, image_size)

    @property
    def share_below(self) -> float:
        return self.below_need / self.frames if self.frames else 0.0

    @property
    def poor(self) -> bool:
        return self.frames > 0 and self.share_below >= POOR_FRAME_SHARE

    def warning(self, sequences: int, at_cap: int, cap: int) -> str:
        size = f" at {self.image_size}" if self.image_size else ""
        cut = f"; {at_cap} of the {sequences} sequences end only at the {cap}-frame cap" * bool(
            at_cap
        )
        return (
            f"feature-poor frames: {self.below_need} of {self.frames} frames "
            f"({100 * self.share_below:.0f} %) have fewer than the {self.need} "
            f"{self.detector} features the segmentation needs (median {self.median:g} "
            f"a frame{size}), so sequences are not where the places change{cut}"
        )


@dataclass(frozen=True)
class CheckFeasibility:
    """How many of the checked candidates verification could not even try.

    Only "too few features" (a frame of the pair has fewer than the fit needs) says the
    frames were too poor; "too few matches" is also what a wrong candidate gives on healthy
    frames (often a large share of their checks), so it is counted and reported but does not
    make a run feature-poor.
    """

    checked: int  # candidates checked (not skipped at a high frame rate)
    too_few_features: int = 0
    too_few_matches: int = 0

    @classmethod
    def of(cls, reasons: Iterable[str], skipped: Iterable[str] = ()) -> CheckFeasibility:
        """From the verdict reason of every candidate; those in `skipped` were not checked."""
        left_out = set(skipped)
        counter = Counter(reason for reason in reasons if reason not in left_out)
        features, matches = (counter[reason] for reason in IMPOSSIBLE_REASONS)
        return cls(sum(counter.values()), features, matches)

    @property
    def share(self) -> float:
        """The share of the checks that the frames' features made impossible."""
        return self.too_few_features / self.checked if self.checked else 0.0

    @property
    def poor(self) -> bool:
        return self.checked > 0 and self.share >= IMPOSSIBLE_CHECK_SHARE

    def warning(self, accepted: int) -> str:
        return (
            f"verification could not check {self.too_few_features} of the {self.checked} "
            f"candidate pairs it tried ({100 * self.share:.0f} %: a frame had too few "
            f"features; {self.too_few_matches} more had too few matches), so its {accepted} "
            "accepted do not mean the route holds no more loops"
        )


@dataclass(frozen=True)
class FeatureHealth:
    """A run's feature measurements and, when the frames were too poor, its warnings."""

    segmentation: SegmentationFeatures
    checks: CheckFeasibility | None  # None: verification was off
    warnings: tuple[str, ...]

    @property
    def poor(self) -> bool:
        return bool(self.warnings)

    def note(self) -> str:
        """The warnings and the advice as one clause of a summary line ("" when healthy)."""
        return "; ".join(self.warnings) + f"; {ADVICE}" if self.warnings else ""

    def to_json(self) -> dict[str, Any]:
        seg, checks = self.segmentation, self.checks
        return {
            "feature_poor": self.poor,
            "warnings": list(self.warnings),
            "advice": ADVICE if self.poor else "",
            "segmentation_detector": seg.detector,
            "image_size": seg.image_size,
            "frames_measured": seg.frames,
            "features_needed": seg.need,
            "frames_below_need": seg.below_need,
            "median_features": seg.median,
            "checks_tried": None if checks is None else checks.checked,
            "checks_too_few_features": None if checks is None else checks.too_few_features,
            "checks_too_few_matches": None if checks is None else checks.too_few_matches,
        }

    def metadata_json(self) -> str:
        """The `feature_poor` metadata entry ("" when healthy: the entry is then left out)."""
        return json.dumps(self.to_json(), sort_keys=True) if self.poor else ""


def feature_health(
    segmentation: SegmentationFeatures,
    checks: CheckFeasibility | None,
    sequence_lengths: Iterable[int],
    cap: int,
    accepted: int,
) -> FeatureHealth:
    """The warnings of a run: frames poorer than the segmentation needs, checks impossible."""
    lengths = list(sequence_lengths)
    at_cap = sum(length >= cap for length in lengths) if cap > 0 else 0
    warnings = []
    if segmentation.poor:
        warnings.append(segmentation.warning(len(lengths), at_cap, cap))
    if checks is not None and checks.poor:
        warnings.append(checks.warning(accepted))
    return FeatureHealth(segmentation, checks, tuple(warnings))


def check_feasibility(verified: Iterable[VerifiedDecision]) -> CheckFeasibility:
    """`CheckFeasibility` of the verification stage's decisions."""
    reasons = (check.verdict.reason for item in verified for check in item.checks)
    return CheckFeasibility.of(reasons, SKIPPED_REASONS)


def run_feature_health(
    params: Parameters,
    result: ReplayResult,
    checks: CheckFeasibility | None,
    accepted: int,
    image_size: str = "",
) -> FeatureHealth:
    """`feature_health` of a replay and, when verification was on, of its checks."""
    segmentation = SegmentationFeatures.of(
        result.feature_detector, params.min_features, result.feature_counts, image_size
    )
    lengths = (decision.length for decision in result.decisions)
    return feature_health(segmentation, checks, lengths, params.max_sequence_length, accepted)
