"""Pictures of an evaluated run: precision-recall curve, difference matrix, trajectory.

matplotlib is an optional extra (`pip install 'doseqslam-logs[plot]'`); this module imports it
at import time, so callers import this module lazily and report its absence themselves. Figures
are drawn with the object-oriented API (no pyplot, no backend switch: `Figure.savefig` renders
with Agg) and written atomically as PNG. Each `*_figure` function builds a picture's Figure;
its `plot_*` twin writes it.
"""

from __future__ import annotations

import io
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure

from ..sinks.atomic import atomic_output
from .difference_matrix import DifferenceMatrix
from .groundtruth import LoopTruth
from .metrics import Evaluation

Status = Literal["tp", "fp", "reported", "rejected", "skipped"]

# One colour per status, the same in every picture.
COLOURS: dict[Status, str] = {
    "tp": "#1a9850",
    "fp": "#d73027",
    "reported": "#2166ac",
    "rejected": "#999999",
    "skipped": "#cccccc",
}
LABELS: dict[Status, str] = {
    "tp": "loop closure, true",
    "fp": "loop closure, false",
    "reported": "loop closure",
    "rejected": "rejected by verification",
    "skipped": "not checked (high frame rate)",
}
# Candidates that are not reported: drawn faint, under the reported ones.
FAINT: frozenset[Status] = frozenset({"rejected", "skipped"})
DPI = 110


@dataclass(frozen=True)
class Detection:
    """One pair of the run: query frame, matched frame, and what it turned out to be."""

    query: int
    match: int
    status: Status


def _titles(figure: Figure, axes: Axes, title: str, subtitle: str) -> None:
    """The run (log, topic, parameters) on top; what the picture shows below, wrapped."""
    figure.suptitle(title, fontsize=10)
    axes.set_title("\n".join(textwrap.wrap(subtitle, 95)), fontsize=8.5)


def save_png(figure: Figure, path: Path) -> Path:
    """Write `figure` as a PNG at `path`, atomically."""
    buffer = io.BytesIO()
    # No "Software" entry: the same picture gives the same bytes across matplotlib versions.
    figure.savefig(buffer, format="png", dpi=DPI, metadata={"Software": None})
    with atomic_output(path) as stream:
        stream.write(buffer.getvalue())
    return path


def _by_status(detections: Sequence[Detection]) -> dict[Status, list[Detection]]:
    groups: dict[Status, list[Detection]] = {}
    for detection in detections:
        groups.setdefault(detection.status, []).append(detection)
    # Faint pairs first, so that the reported ones are drawn over them.
    order: list[Status] = ["skipped", "rejected", "reported", "fp", "tp"]
    return {status: groups[status] for status in order if status in groups}


# -- precision-recall ---------------------------------------------------------------------


def _draw_curve(axes: Axes, evaluation: Evaluation, name: str, colour: str) -> None:
    recall = [0.0] + [p.recall for p in evaluation.curve]
    precision = [1.0] + [p.precision for p in evaluation.curve]
    axes.plot(
        recall,
        precision,
        ".-",
        color=colour,
        lw=1.6,
        ms=5,
        label=f"{name}, one point per threshold",
    )
    axes.plot(
        [evaluation.recall],
        [evaluation.precision],
        "o",
        color=colour,
        ms=13,
        mfc="none",
        mew=1.8,
        zorder=5,
        label=f"{name} at th = {evaluation.threshold:g}: "
        f"P {evaluation.precision:.2f}, R {evaluation.recall:.2f}",
    )
    if evaluation.threshold_at_r_p100 is not None:
        axes.plot(
            [evaluation.r_p100],
            [1.0],
            "*",
            color=colour,
            ms=15,
            mec="black",
            mew=0.6,
            zorder=4,
            label=f"{name} R@P100 = {evaluation.r_p100:.2f} "
            f"(th = {evaluation.threshold_at_r_p100:.4g})",
        )


def pr_curve_figure(raw: Evaluation, verified: Evaluation | None, title: str) -> Figure:
    """The precision-recall curve swept over f (raw, and verified when given)."""
    figure = Figure(figsize=(7.5, 6.0), layout="constrained")
    axes = figure.add_subplot()
    _draw_curve(axes, raw, "raw" if verified is None else "raw (all candidates)", "#2166ac")
    if verified is not None:
        _draw_curve(axes, verified, "verified (accepted pairs)", "#e66101")
    axes.set(xlim=(-0.02, 1.02), ylim=(-0.02, 1.05), xlabel="recall", ylabel="precision")
    axes.grid(alpha=0.3)
    axes.legend(loc="lower left", fontsize=8.5, framealpha=0.9)
    _titles(
        figure,
        axes,
        title,
        f"precision-recall over the decision threshold; ground truth {raw.gt_file} "
        f"({raw.gt_loop_events} loop events, tolerance +-{raw.tolerance} frames)",
    )
    return figure


def plot_pr_curve(path: Path, raw: Evaluation, verified: Evaluation | None, title: str) -> Path:
    """Write `pr_curve_figure` as a PNG."""
    return save_png(pr_curve_figure(raw, verified, title), path)


# -- difference matrix --------------------------------------------------------------------


# Markers on the grey matrix: grey (the trajectory's "faint") would vanish there, so pairs that
# are not reported are hollow blue rings (rejected) and smaller paler ones (skipped).
_MATRIX_MARKERS: dict[Status, tuple[str, float]] = {
    "tp": (".", 5),
    "fp": ("x", 7),
    "reported": (".", 5),
    "rejected": ("o", 4),
    "skipped": ("o", 3),
}
_MATRIX_FAINT: dict[Status, str] = {"rejected": "#4fa3e0", "skipped": "#a6cee3"}


def _gt_cells(gt: LoopTruth, matrix: DifferenceMatrix) -> npt.NDArray[np.bool_]:
    """GT cells on the matrix's grid: a kept cell is set when any frame it stands for is."""
    n = matrix.frame_indices.size
    mask = np.zeros((n, n), dtype=bool)
    for frame_rows, frame_cols in gt.cell_batches():
        rows = np.minimum(frame_rows // matrix.stride, n - 1)
        cols = np.minimum(frame_cols // matrix.stride, n - 1)
        mask[rows, cols] = True
    return mask


def difference_matrix_figure(
    matrix: DifferenceMatrix,
    detections: Sequence[Detection],
    gt: LoopTruth | None,
    title: str,
) -> Figure:
    """The difference matrix (query frame down, database frame across) with the ground truth
    shaded and the run's pairs marked."""
    figure = Figure(figsize=(8.0, 7.6), layout="constrained")
    axes = figure.add_subplot()
    # Kept cell k stands for frames k * stride .. (k + 1) * stride - 1.
    side = matrix.frame_indices.size * matrix.stride - 0.5
    extent = (-0.5, side, side, -0.5)
    image = axes.imshow(
        matrix.values, cmap="gray", extent=extent, interpolation="nearest", aspect="equal"
    )
    colourbar = figure.colorbar(image, ax=axes, shrink=0.8)
    colourbar.set_label("enhanced difference" if matrix.enhanced else "SAD difference")
    if gt is not None and gt.nnz:
        shade = np.ma.masked_where(~_gt_cells(gt, matrix), np.ones(matrix.values.shape))
        axes.imshow(
            shade,
            cmap=ListedColormap(["#fdb863"]),
            alpha=0.55,
            extent=extent,
            interpolation="nearest",
        )
        axes.plot([], [], "s", color="#fdb863", alpha=0.8, label="ground-truth loop")
    for status, group in _by_status(detections).items():
        marker, size = _MATRIX_MARKERS[status]
        axes.plot(
            [d.match for d in group],
            [d.query for d in group],
            marker,
            color=_MATRIX_FAINT.get(status, COLOURS[status]),
            ms=size,
            mfc="none" if status in FAINT else None,
            ls="none",
            label=f"{LABELS[status]} ({len(group)})",
        )
    axes.set(xlabel="database frame (match index)", ylabel="query frame index")
    if axes.get_legend_handles_labels()[0]:
        axes.legend(loc="upper right", fontsize=8.5, framealpha=0.9)
    sampled = (
        f"1 frame in {matrix.stride} of {matrix.frames} (subsampled)"
        if matrix.stride > 1
        else f"all {matrix.frames} frames"
    )
    enhanced = f"enhanced (window {matrix.window} cells)" if matrix.enhanced else "raw SAD"
    _titles(
        figure,
        axes,
        title,
        f"{enhanced} difference matrix, {sampled} ({matrix.values.shape[0]} x "
        f"{matrix.values.shape[1]}); dark = similar",
    )
    return figure


def plot_difference_matrix(
    path: Path,
    matrix: DifferenceMatrix,
    detections: Sequence[Detection],
    gt: LoopTruth | None,
    title: str,
) -> Path:
    """Write `difference_matrix_figure` as a PNG."""
    return save_png(difference_matrix_figure(matrix, detections, gt, title), path)


# -- trajectory ---------------------------------------------------------------------------


def trajectory_figure(
    track_positions: npt.NDArray[np.float64],
    frame_positions: npt.NDArray[np.float64],
    detections: Sequence[Detection],
    title: str,
    pose_topic: str,
) -> Figure:
    """The path from the pose topic (x, y) with each pair drawn as a line between the query
    frame's and the matched frame's positions. Pairs whose frames have no pose are left out."""
    figure = Figure(figsize=(8.0, 7.0), layout="constrained")
    axes = figure.add_subplot()
    axes.plot(track_positions[:, 0], track_positions[:, 1], color="#555555", lw=0.9, label="path")
    axes.plot(*track_positions[0, :2], "o", color="black", ms=6, label="start")
    for status, group in _by_status(detections).items():
        segments = [
            (frame_positions[d.query, :2], frame_positions[d.match, :2])
            for d in group
            if np.isfinite(frame_positions[[d.query, d.match], :2]).all()
        ]
        faint = status in FAINT
        lines = LineCollection(
            segments,
            colors=COLOURS[status],
            linewidths=0.8 if faint else 1.4,
            alpha=0.35 if faint else 0.9,
            label=f"{LABELS[status]} ({len(segments)})",
        )
        axes.add_collection(lines)
        ends = np.array([end for segment in segments for end in segment]).reshape(-1, 2)
        axes.plot(
            ends[:, 0], ends[:, 1], ".", color=COLOURS[status], ms=3, alpha=0.35 if faint else 0.9
        )
    axes.set(xlabel="x (m)", ylabel="y (m)", aspect="equal")
    axes.grid(alpha=0.3)
    axes.legend(loc="best", fontsize=8.5, framealpha=0.9)
    _titles(
        figure,
        axes,
        title,
        f"trajectory (x, y) from {pose_topic}; lines join each query frame to its matched frame",
    )
    return figure


def plot_trajectory(
    path: Path,
    track_positions: npt.NDArray[np.float64],
    frame_positions: npt.NDArray[np.float64],
    detections: Sequence[Detection],
    title: str,
    pose_topic: str,
) -> Path:
    """Write `trajectory_figure` as a PNG."""
    return save_png(
        trajectory_figure(track_positions, frame_positions, detections, title, pose_topic), path
    )
