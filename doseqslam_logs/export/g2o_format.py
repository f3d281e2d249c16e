"""g2o: the pose graph of `pose_graph` in the g2o text format (3-D, quaternions).

    VERTEX_SE3:QUAT id x y z qx qy qz qw
    EDGE_SE3:QUAT id1 id2 x y z qx qy qz qw I11 I12 .. I16 I22 .. I66
    FIX id

The file starts with `#` comment lines stating the loop edges' measurement model (the metric
pose recorded on the pair, else the placeholder; docs/export.md); g2o and GTSAM's readG2o skip
them. g2o needs a positive definite information matrix: a rotation-only loop edge (zero
information on its translation in GTSAM terms) gets G2O_UNCONSTRAINED_INFORMATION on the
translation diagonal instead, with a zero translation that it leaves free. Vertex ids are
frame indices. Odometry edges come first, then loop edges (in log order). The information is
the upper triangle of the 6 x 6 matrix, row by row. `FIX` holds the first vertex in g2o;
GTSAM's readG2o ignores it (add a prior there). With `calibrate_odometry`, the odometry edges
and the vertices are those of the odometry calibrated from the metric loop edges (its bias
and factor in a `#` line), as `optimize` builds its graph.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import TYPE_CHECKING

import numpy as np

from ..annotations.reader import AnnotatedLog
from ..annotations.records import ROTATION_ONLY
from .base import Exporter, ExportOptions, ExportResult

if TYPE_CHECKING:
    from .odometry_calibration import OdometryCalibration
    from .pose_graph import Edge, PoseGraph

_UPPER = np.triu_indices(6)
_INFORMATION_LINE = (
    "# Information: upper triangle of the 6 x 6 matrix over x, y, z, rot x, rot y, rot z.\n"
)
# Information per m^2 standing for "unconstrained" on a rotation-only edge's translation axes
# (a sigma of 1 km): g2o refuses a singular matrix; the zero translation then weighs nothing.
G2O_UNCONSTRAINED_INFORMATION = 1e-6


def _numbers(values: Iterable[float]) -> str:
    return " ".join(f"{value:.17g}" for value in values)


def edge_line(edge: Edge) -> str:
    measurement = _numbers([*edge.translation, *edge.quaternion_xyzw])
    matrix = edge.information
    if edge.model == ROTATION_ONLY:
        matrix = matrix.copy()
        matrix[:3, :3] = np.diag([G2O_UNCONSTRAINED_INFORMATION] * 3)
    information = _numbers(matrix[_UPPER])
    return f"EDGE_SE3:QUAT {edge.from_id} {edge.to_id} {measurement} {information}\n"


def header_lines(options: ExportOptions, graph: PoseGraph | None = None) -> list[str]:
    """`#` lines: the loop edges' measurement models (metric, placeholder) and their counts."""
    if options.loop_model == "metric":
        models = {} if graph is None else graph.loop_models
        counts = ", ".join(f"{n} {model}" for model, n in models.items()) or "none"
        return [
            "# doseqslam-logs pose graph. Loop edges (EDGE_SE3:QUAT after the odometry edges)\n",
            f"# by model: {counts} (docs/export.md):\n",
            "#   depth_pnp, odometry_pnp: the metric pose recorded on the pair, information =\n",
            "#     its inverse covariance, in body axes (x forward, y left, z up)\n",
            "#   rotation_only: its rotation; translation unconstrained (zero in GTSAM terms),\n",
            f"#     written as zero with information {G2O_UNCONSTRAINED_INFORMATION:g} per m^2 "
            "(g2o needs a positive definite matrix)\n",
            *_placeholder_lines(options, "#   placeholder (no metric pose recorded): "),
            _INFORMATION_LINE,
        ]
    return [
        "# doseqslam-logs pose graph. Loop edges (EDGE_SE3:QUAT after the odometry edges) use a\n",
        "# placeholder measurement model, not a measured relative pose (docs/export.md):\n",
        *_placeholder_lines(options, "#   "),
        _INFORMATION_LINE,
    ]


def _placeholder_lines(options: ExportOptions, prefix: str) -> list[str]:
    if options.use_verified_rotation:
        rotation = "from geometric verification when recorded, else identity"
    else:
        rotation = "identity (--identity-loop-rotation)"
    translation_sigma = f"{options.loop_translation_sigma_m:g} m"
    rotation_sigma = f"{options.loop_rotation_sigma_deg:g} deg"
    return [
        f"{prefix}translation: zero, low information (sigma {translation_sigma} on x, y, z)\n",
        f"{prefix}rotation: {rotation} (sigma {rotation_sigma} on each axis)\n",
    ]


def g2o_lines(
    graph: PoseGraph, options: ExportOptions, calibration: OdometryCalibration | None = None
) -> Iterator[str]:
    yield from header_lines(options, graph)
    if calibration is not None:
        yield f"# odometry edges: {calibration.summary()} (docs/export.md)\n"
    for k, vertex_id in enumerate(graph.vertex_ids):
        pose = [*graph.poses.positions[k], *graph.poses.quaternions_xyzw[k]]
        yield f"VERTEX_SE3:QUAT {vertex_id} {_numbers(pose)}\n"
    for edge in [*graph.odometry_edges, *graph.loop_edges]:
        yield edge_line(edge)
    yield f"FIX {graph.vertex_ids[0]}\n"


def export(log: AnnotatedLog, options: ExportOptions) -> ExportResult:
    # Here, not above: the pose graph imports SciPy, FORMATS (the command line) needs none.
    from .odometry_calibration import calibrate_odometry, calibrated_graph
    from .pose_graph import build_pose_graph, with_pose_topic

    options = with_pose_topic(options, log)
    graph = build_pose_graph(log, options)
    if not options.calibrate_odometry:
        return ExportResult(g2o_lines(graph, options), graph.summary)
    calibration = calibrate_odometry(graph)
    graph = calibrated_graph(graph, calibration)
    return ExportResult(
        g2o_lines(graph, options, calibration), f"{graph.summary}; {calibration.summary()}"
    )


EXPORTER = Exporter(
    "g2o",
    "pose graph: vertices at camera frames, odometry and loop edges",
    True,
    export,
)
