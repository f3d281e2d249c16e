"""Verified figures: the detector's decisions reduced to the pairs geometric verification kept.

Each accepted pair is scored at its refined match; rejected pairs and decisions that were not
verified (f >= th) report nothing, so a threshold sweep over the result runs up to the th of
the run (`metrics.evaluate` on the reduced decisions gives the verified curve).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import replace

from ..detector.events import SequenceDecision
from ..verification.stage import VerifiedDecision


def verified_decisions(verified: Iterable[VerifiedDecision]) -> list[SequenceDecision]:
    """Each decision with only its accepted pairs, their match moved to the refined one.

    The match timestamp of a moved pair is not known here and is set to -1 (evaluation
    uses frame indices only).
    """
    reduced = []
    for item in verified:
        kept = tuple(
            replace(
                check.candidate,
                match_index=check.refined_match_index,
                match_timestamp_ns=(
                    check.candidate.match_timestamp_ns
                    if check.refined_match_index == check.candidate.match_index
                    else -1
                ),
            )
            for check in item.checks
            if check.accepted
        )
        reduced.append(replace(item.decision, candidates=kept))
    return reduced
