"""`diff --report REPORT.md`: the comparison as a markdown page with pictures beside it.

One picture shows what changed per log (pairs only in A, only in B, different match); one
trajectory picture per log among the three that changed most, when the log has a pose topic
(--gt-topic, else the one annotate would pick), draws the pairs each version alone reports.
matplotlib is the `plot` extra, imported here only.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ..annotations.reader import read_annotations
from ..errors import OutputError, SourceError, UsageError
from ..sinks.atomic import atomic_output, check_output_path
from ..sources import open_source
from ..sources.poses import default_pose_topic, read_poses
from .diff import Pair
from .diff_gate import Gate
from .fleet_diff import BatchRun, Comparison, FleetDiff, LogRow, row_cells
from .pose_ground_truth import frame_poses

TRAJECTORIES = 3  # logs drawn, those that changed most


def write_report(path: Path, result: FleetDiff | Comparison, gate: Gate | None) -> list[Path]:
    """Write REPORT.md and its pictures (REPORT-changes.png, REPORT-trajectory-N.png)
    beside it; returns the files written. Raises as check_report does."""
    check_report(path)
    from matplotlib.figure import Figure

    from .plots import save_png

    fleet = result if isinstance(result, FleetDiff) else _as_fleet(result)
    stem = path.with_suffix("")
    written = [save_png(_changes_figure(Figure, fleet), Path(f"{stem}-changes.png"))]
    drawn: list[tuple[LogRow, Path]] = []
    for row in sorted(fleet.rows, key=lambda r: -r.changed)[:TRAJECTORIES]:
        figure = _trajectory_figure(Figure, row)
        if row.changed and figure is not None:
            drawn.append((row, save_png(figure, Path(f"{stem}-trajectory-{len(drawn) + 1}.png"))))
    written += [p for _, p in drawn]
    text = _markdown(fleet, gate, written[0], drawn)
    with atomic_output(path) as stream:
        stream.write(text.encode())
    return [path, *written]


def check_report(path: Path) -> None:
    """Before the diff's work: UsageError without matplotlib, OutputError when the report
    cannot be written (its folder missing, the name taken by a folder, ...)."""
    try:
        import matplotlib  # noqa: F401
    except ImportError as exc:
        raise UsageError(
            f"--report needs matplotlib ({exc}): pip install 'doseqslam-logs[plot]'"
        ) from exc
    check_output_path(path)
    if not path.absolute().parent.is_dir():
        raise OutputError(f"{path}: cannot create the output: no folder {path.parent}")


def _as_fleet(comparison: Comparison) -> FleetDiff:
    diff = comparison.diff
    a = BatchRun(Path(diff.a.path).name, diff.a.source_sha256, Path(diff.a.path))
    b = BatchRun(Path(diff.b.path).name, diff.b.source_sha256, Path(diff.b.path))
    row = LogRow(Path(diff.a.source_file).name or a.name, a.sha256, "compared", a, b, comparison)
    return FleetDiff(Path(diff.a.path), Path(diff.b.path), [row], comparison.truth is not None)


def _changes_figure(figure_class: Any, fleet: FleetDiff) -> Any:
    rows = fleet.rows
    names = [row.name for row in rows]
    counts = [_class_counts(row) for row in rows]
    figure = figure_class(figsize=(8.0, 1.2 + 0.35 * max(len(rows), 2)), layout="constrained")
    axes = figure.add_subplot()
    y = np.arange(len(rows))
    left = np.zeros(len(rows))
    for index, (label, colour) in enumerate(
        (("only in A", "#e08214"), ("only in B", "#2166ac"), ("different match", "#7b3294"))
    ):
        values = np.array([c[index] for c in counts], dtype=float)
        axes.barh(y, values, left=left, color=colour, label=label)
        left += values
    axes.set_yticks(y, names, fontsize=8)
    axes.invert_yaxis()
    axes.set_xlabel("reported loop closures that differ")
    axes.xaxis.get_major_locator().set_params(integer=True)
    axes.legend(loc="lower right", fontsize=8)
    figure.suptitle(f"A: {fleet.a}  vs  B: {fleet.b}", fontsize=9)
    return figure


def _class_counts(row: LogRow) -> tuple[int, int, int]:
    if row.comparison is None:
        pairs = row.one_side_pairs
        return (pairs, 0, 0) if row.lost else (0, pairs, 0)
    counts = row.comparison.diff.reported.counts
    return counts["only_a"], counts["only_b"], counts["different_match"]


def _trajectory_figure(figure_class: Any, row: LogRow) -> Any:
    comparison = row.comparison
    if comparison is None:
        return None
    truth = comparison.truth
    topic = None if truth is None else truth.ground_truth.get("topic")
    try:
        side_a = _positions(comparison.diff.a.path, topic)
        side_b = _positions(comparison.diff.b.path, topic)
    except (SourceError, UsageError):
        return None  # no pose topic, or a sidecar without its log: no picture
    if side_a is None or side_b is None:
        return None
    (track, frames_a, used), (_, frames_b, _) = side_a, side_b
    matching = comparison.diff.reported
    figure = figure_class(figsize=(7.0, 6.5), layout="constrained")
    axes = figure.add_subplot()
    axes.plot(track[:, 0], track[:, 1], color="#555555", lw=0.8, label="path")
    label = truth.label if truth is not None else None
    groups = (
        ("common", frames_b, [b for _, b in matching.common], "b", "#1a9850", 0.3),
        ("only in A", frames_a, matching.only_a, "a", "#e08214", 0.9),
        ("only in B", frames_b, matching.only_b, "b", "#2166ac", 0.9),
        (
            "B's other match",
            frames_b,
            [b for _, b in matching.different_match],
            "b",
            "#7b3294",
            0.9,
        ),
    )
    for name, frames, pairs, side, colour, emphasis in groups:
        _draw_pairs(axes, frames, pairs, name, colour, emphasis, side, label)
    axes.set(xlabel="x (m)", ylabel="y (m)", aspect="equal")
    axes.grid(alpha=0.3)
    axes.legend(loc="best", fontsize=8)
    figure.suptitle(f"{row.name}: loop closures of A and B on {used}", fontsize=9)
    return figure


def _draw_pairs(
    axes: Any,
    frames: npt.NDArray[np.float64],
    pairs: list[Pair],
    name: str,
    colour: str,
    emphasis: float,
    side: str,
    label: Any,
) -> None:
    from matplotlib.collections import LineCollection

    def segment(pair: Pair) -> Any:
        return (frames[pair.query_index, :2], frames[pair.match_index, :2])

    drawable = [
        p
        for p in pairs
        if max(p.query_index, p.match_index) < len(frames)
        and np.isfinite(frames[[p.query_index, p.match_index], :2]).all()
    ]
    # emphasis 0: the common pairs, faint; 1: a pair one version alone reports, bold.
    axes.add_collection(
        LineCollection(
            [segment(p) for p in drawable],
            colors=colour,
            alpha=0.3 + 0.65 * emphasis,
            lw=1.0 + 1.6 * emphasis,
            label=f"{name} ({len(drawable)})",
        )
    )
    if emphasis and drawable:
        ends = np.array([end for p in drawable for end in segment(p)])
        axes.plot(ends[:, 0], ends[:, 1], "o", color=colour, ms=4)
    false = [p for p in drawable if label is not None and label(side, p) == "false"]
    if false:
        ends = np.array([segment(p)[0] for p in false])
        axes.plot(
            ends[:, 0],
            ends[:, 1],
            "x",
            color="#d73027",
            ms=7,
            label=f"false, {name} ({len(false)})",
        )


def _positions(
    path: str, topic: str | None
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], str] | None:
    log = read_annotations(path)
    if log.frame_times is None:
        return None
    with open_source(path) as source:
        # Ground truth, else the run's recorded odometry, else the log's default pose topic.
        topic = topic or log.metadata.odometry_topic or default_pose_topic(source)
        if topic is None:
            return None
        track = read_poses(source, topic)
    times = log.frame_times.detector_times_ns(log.metadata.time_source)
    return track.positions, frame_poses(track, times).positions, topic


def _markdown(
    fleet: FleetDiff, gate: Gate | None, changes: Path, drawn: list[tuple[LogRow, Path]]
) -> str:
    totals = fleet.totals()
    header = ["log", "state", "common", "only A", "only B", "different match"]
    if fleet.ground_truth:
        header += ["TP/FP A", "TP/FP B"]
    lines = [
        "# doseqslam-logs diff",
        "",
        f"- A: `{fleet.a}`",
        f"- B: `{fleet.b}`",
        f"- {totals['changed_logs']} of {totals['logs']} logs differ; pairs in common "
        f"{totals['common']}, only in A {totals['only_a']}, only in B {totals['only_b']}, "
        f"different match {totals['different_match']}",
        *[f"- warning: {w}" for w in fleet.warnings],
    ]
    if gate is not None:
        failed = gate.failures(fleet.figures())
        lines.append(
            f"- gate `{','.join(gate.limits)}`: "
            + ("**failed**: " + "; ".join(failed) if failed else "passed")
        )
    lines += ["", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row_cells(row, fleet.ground_truth)) + " |" for row in fleet.rows]
    lines += ["", f"![what changed per log]({changes.name})", ""]
    for row, picture in drawn:
        lines += [f"## {row.name}", "", f"![{row.name}]({picture.name})", ""]
    return "\n".join(lines)
