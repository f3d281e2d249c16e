"""tum: the trajectory of the pose-graph vertices in the TUM RGB-D format, for evo & co.

    # timestamp x y z qx qy qz qw
    1700000000.000000000 0.0 0.0 0.0 0.0 0.0 0.0 1.0

One line per vertex of `pose_graph` (every camera frame with a pose, every --stride-th one
plus the loop-closure frames with --stride): the pose topic interpolated at the frame's
detector time (header stamp, else log time), in seconds with 9 decimals. Any pose topic works:
--odometry-topic /ground_truth/pose gives the reference for `evo_ape tum`.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

from ..annotations.reader import AnnotatedLog
from ..annotations.records import NANOS_PER_SECOND
from .base import Exporter, ExportOptions, ExportResult

if TYPE_CHECKING:
    from .pose_graph import PoseGraph

HEADER = "# timestamp x y z qx qy qz qw\n"


def tum_time(time_ns: int) -> str:
    """Nanoseconds as seconds with 9 decimals, exactly (no float rounding)."""
    seconds, nanos = divmod(time_ns, NANOS_PER_SECOND)
    return f"{seconds}.{nanos:09d}"


def tum_lines(graph: PoseGraph) -> Iterator[str]:
    yield HEADER
    poses = graph.poses
    for k in range(len(poses)):
        values = [*poses.positions[k], *poses.quaternions_xyzw[k]]
        numbers = " ".join(f"{value:.17g}" for value in values)
        yield f"{tum_time(int(poses.times_ns[k]))} {numbers}\n"


def export(log: AnnotatedLog, options: ExportOptions) -> ExportResult:
    # Here, not above: the pose graph imports SciPy, FORMATS (the command line) needs none.
    from .pose_graph import build_pose_graph, with_pose_topic

    options = with_pose_topic(options, log)
    graph = build_pose_graph(log, options)
    summary = f"{len(graph.vertex_ids)} poses of {options.odometry_topic} at camera times"
    if graph.frames_outside_odometry:
        summary += f" ({graph.frames_outside_odometry} frames outside its time range left out)"
    return ExportResult(tum_lines(graph), summary)


EXPORTER = Exporter(
    "tum",
    "trajectory 't x y z qx qy qz qw' of a pose topic at camera times",
    True,
    export,
)
