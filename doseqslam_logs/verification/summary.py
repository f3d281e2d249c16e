"""The verification part of the summary lines of `annotate` and `evaluate --images`."""

from __future__ import annotations

from typing import TYPE_CHECKING

from .motion import ODOMETRY_DISAGREES, STATIONARY

if TYPE_CHECKING:  # the stage imports the pair checks (OpenCV, SciPy); a summary needs none
    from .stage import VerificationStats


def verification_summary(
    stats: VerificationStats, wall_s: float, model: str, motion: str = ""
) -> str:
    """ "N accepted[, K of them on a next-best trajectory][, T rejected as stationary (E)][, D
    rejected (odometry disagrees)][, M moved to a nearer frame][, U placed by the
    odometry][, S skipped (high frame rate)] (P frame pairs checked, X ms each, W s;
    MODEL)"; `model` says which matrix was fitted, `motion` the motion rule's evidence (e.g.
    "odometry /odom")."""
    alternatives = stats.from_alternatives
    evidence = f" ({motion})" if motion else ""
    stationary = (
        f", {stats.stationary} rejected as {STATIONARY}{evidence}" if stats.stationary else ""
    )
    disagrees = stats.odometry_disagrees
    turned = f", {disagrees} rejected ({ODOMETRY_DISAGREES})" if disagrees else ""
    moved = f", {stats.relocated} moved to a nearer frame" if stats.relocated else ""
    placed = f", {stats.placed} placed by the odometry" if stats.placed else ""
    return (
        f"{stats.accepted} accepted"
        f"{f', {alternatives} of them on a next-best trajectory' if alternatives else ''}"
        f"{stationary}"
        f"{turned}"
        f"{moved}"
        f"{placed}"
        f"{f', {stats.skipped} skipped (high frame rate)' if stats.skipped else ''} "
        f"({stats.pairs} frame pairs checked, {stats.ms_per_pair:.1f} ms each, "
        f"{wall_s:.1f} s; {model})"
    )
