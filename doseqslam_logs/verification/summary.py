"""The verification part of the summary lines of `annotate` and `evaluate --images`."""

from __future__ import annotations

from .stage import VerificationStats


def verification_summary(stats: VerificationStats, wall_s: float, model: str) -> str:
    """ "N accepted[, K of them on a next-best trajectory][, S skipped (high frame rate)]
    (P frame pairs checked, X ms each, W s; MODEL)"; `model` says which matrix was fitted."""
    alternatives = stats.from_alternatives
    return (
        f"{stats.accepted} accepted"
        f"{f', {alternatives} of them on a next-best trajectory' if alternatives else ''}"
        f"{f', {stats.skipped} skipped (high frame rate)' if stats.skipped else ''} "
        f"({stats.pairs} frame pairs checked, {stats.ms_per_pair:.1f} ms each, "
        f"{wall_s:.1f} s; {model})"
    )
