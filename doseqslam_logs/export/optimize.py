"""`optimize`: the pose graph of an annotated log optimized, and written back as a pose topic.

The graph is `pose_graph.build_pose_graph`'s (the g2o export's), optimized by
`gtsam_graph.optimize_pose_graph` (robust loop edges, outlier check, Levenberg-Marquardt). The
output holds every record of the annotated log (or sidecar) plus `OPTIMIZED_POSE_TOPIC`: one
pose per vertex, stamped at the vertex's detector time, logged at its image's log time, in the
odometry's frame_id and frame (body poses, like the odometry), typed for the log's profile
(`sinks.pose_topic`); and the same vertices as two whole paths at the log's first message,
`OPTIMIZED_PATH_TOPIC` and `ODOMETRY_PATH_TOPIC` (the graph's initial poses: the odometry at
the vertices), which a viewer draws as lines.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ..annotations.reader import AnnotatedLog, read_annotations
from ..errors import OutputError
from ..sinks.atomic import check_output_path
from ..sinks.pose_topic import FoxgloveEncoding, PathMessage, PoseStream, write_with_poses
from ..sources import open_source
from .base import (
    ODOMETRY_PATH_TOPIC,
    OPTIMIZED_PATH_TOPIC,
    OPTIMIZED_POSE_TOPIC,
    ExportOptions,
    OptimizeOptions,
)
from .gtsam_graph import OptimizedGraph, import_gtsam, optimize_pose_graph
from .loops import frame_times_ns
from .pose_graph import PoseGraph, build_pose_graph, with_pose_topic

I64 = npt.NDArray[np.int64]


@dataclass(frozen=True)
class OptimizeResult:
    """The graph, its optimization, and what was written."""

    output_path: Path
    graph: PoseGraph
    optimized: OptimizedGraph
    frame_id: str
    pose_messages: int

    @property
    def summary(self) -> str:
        notes = self.graph.notes
        text = f"{self.output_path}: {self.optimized.summary(self.graph)}"
        return text + (f" ({'; '.join(notes)})" if notes else "")

    def to_json(self) -> dict[str, Any]:
        """The summary line's figures."""
        optimized = self.optimized
        return {
            "output": str(self.output_path),
            "topic": OPTIMIZED_POSE_TOPIC,
            "path_topics": [OPTIMIZED_PATH_TOPIC, ODOMETRY_PATH_TOPIC],
            "frame_id": self.frame_id,
            "vertices": len(self.graph.vertex_ids),
            "odometry_edges": len(self.graph.odometry_edges),
            "loop_edges": len(self.graph.loop_edges),
            "loop_edges_by_model": self.graph.loop_models,
            "iterations": optimized.iterations,
            "rounds": optimized.rounds,
            "error_before": optimized.error_before,
            "error_after": optimized.error_after,
            "loop_edges_kept": optimized.loop_edges_kept,
            "loop_edges_rejected": len(optimized.rejected_loop_edges),
            "odometry_calibration": optimized.calibration.to_json(),
            "frames_outside_odometry": self.graph.frames_outside_odometry,
            "loop_closures_left_out": self.graph.loop_closures_left_out,
            "default_information_edges": self.graph.default_information_edges,
            "odometry_skipped": dict(self.graph.odometry_skipped),
        }


def odometry_channel(path: Path, topic: str) -> tuple[str, FoxgloveEncoding]:
    """The frame_id of the topic's first message ("" when it has none) and the encoding a
    Foxglove pose beside it takes (protobuf when the topic is protobuf, else JSON)."""
    with open_source(path) as source:
        encodings = [c.message_encoding for c in source.channels() if c.topic == topic]
        first = next(iter(source.messages(topic)), None)
    encoding: FoxgloveEncoding = "protobuf" if "protobuf" in encodings else "json"
    message = None if first is None else first.message
    header = _get(message, "header")
    frame_id = _get(header, "frame_id") if header is not None else _get(message, "frame_id")
    return (frame_id if isinstance(frame_id, str) else ""), encoding


def _get(value: Any, name: str) -> Any:
    return value.get(name) if isinstance(value, dict) else getattr(value, name, None)


def optimize_log(
    log: str | Path,
    output: str | Path,
    options: ExportOptions,
    optimize_options: OptimizeOptions | None = None,
) -> OptimizeResult:
    """Optimize the pose graph of the annotated log (or sidecar) `log` and write `output`:
    its records plus `OPTIMIZED_POSE_TOPIC` and the two paths. `options` are the g2o
    export's (odometry topic, `poses_log` for a sidecar, stride, loop-edge model).

    Raises UsageError (no odometry topic, GTSAM not installed), SourceError (not an annotated
    log; the pose topic missing, empty or not a pose type), OutputError (an output that would
    replace the input or is not a regular file).
    """
    log, output = Path(log), Path(output)
    check_output_path(output)
    for source in (log, options.poses_log):
        if source is not None and output.exists() and output.resolve() == source.resolve():
            raise OutputError(f"{output}: the output would replace the input {source}")
    import_gtsam()  # before any reading: say at once that the extra is missing
    annotated = read_annotations(log)
    options = with_pose_topic(options, annotated)
    graph = build_pose_graph(annotated, options)
    optimized = optimize_pose_graph(graph, optimize_options)
    poses_log = options.poses_log or log
    assert options.odometry_topic is not None  # with_pose_topic set it
    frame_id, encoding = odometry_channel(poses_log, options.odometry_topic)
    ids = graph.vertex_ids
    stamps = frame_times_ns(annotated)[ids]
    stream = PoseStream(
        topic=OPTIMIZED_POSE_TOPIC,
        frame_id=frame_id,
        log_times_ns=_log_times(annotated, ids),
        stamps_ns=stamps,
        positions=optimized.positions,
        quaternions_xyzw=optimized.quaternions_xyzw,
        foxglove_encoding=encoding,
    )
    odometry = graph.poses
    paths = (
        PathMessage(
            OPTIMIZED_PATH_TOPIC, frame_id, stamps, optimized.positions, optimized.quaternions_xyzw
        ),
        PathMessage(
            ODOMETRY_PATH_TOPIC, frame_id, stamps, odometry.positions, odometry.quaternions_xyzw
        ),
    )
    written = write_with_poses(log, output, stream, paths=paths)
    return OptimizeResult(output, graph, optimized, frame_id, written.pose_messages)


def _log_times(annotated: AnnotatedLog, ids: I64) -> I64:
    """The log times of the vertices' images (build_pose_graph read the frame times)."""
    frame_times = annotated.frame_times
    assert frame_times is not None
    return np.asarray(frame_times.log_times_ns, np.int64)[ids]
