"""A pose graph of an annotated log: camera frames as vertices placed by odometry, odometry
edges between consecutive vertices, and one loop edge per reported loop closure.

docs/export.md describes the measurement model; in short:

* Vertices: the odometry pose (any pose topic) interpolated at each kept frame's detector time
  (header stamp, else log time). Frames outside the odometry's time range are left out.
* Odometry edges: the relative pose between consecutive vertices, with the inverse of the
  odometry covariance (ROS order x, y, z, rot x, rot y, rot z, which is also the order of the
  g2o information) times the number of frames the edge spans; `DEFAULT_ODOMETRY_SIGMAS` when
  the messages carry no covariance, an all-zero one, or one that is not positive definite.
* Loop edges, query vertex -> matched vertex (the refined match when verification recorded
  one). With `loop_model` "metric" (the default) and a metric pose recorded on the pair
  (`metric_method`): that pose, inverted (the match camera in the query camera's frame) and
  turned from optical into body axes, with the inverse of its covariance turned the same way
  (`metric_loop_edge`); a "rotation_only" pose gives zero information on the translation axes (a
  rotation-only factor). Otherwise, and always with "placeholder":
  identity relative pose, translation sigma `loop_translation_sigma_m` on each axis
  (low information: the two cameras saw the same place, from an unknown distance), rotation
  sigma `loop_rotation_sigma_deg`. A placeholder for a geometric measurement. When
  verification recorded the pair's relative rotation, that rotation (camera optical axes
  turned into body axes, x forward, y left, z up) replaces the identity rotation; the
  translation stays zero with the same low information, since its scale is unknown.

Information matrices are over (x, y, z, rotation angle in rad about x, y, z), the way GTSAM
and Ceres read a g2o file (g2o itself reads the rotation block as information on the
quaternion's vector part, about half the angle; there rotations weigh 4 times less).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from ..annotations.reader import AnnotatedLog
from ..annotations.records import DEPTH_PNP, ODOMETRY_PNP, ROTATION_ONLY, LoopClosureRecord
from ..annotations.source_check import check_source_log
from ..errors import SourceError, UsageError
from ..sources import open_source
from ..sources.poses import (
    POSE_TYPES,
    PoseTrack,
    default_pose_topic,
    describe_skipped,
    read_poses,
)
from ..verification.metric_pose import OPTICAL_TO_BODY as OPTICAL_TO_BODY
from ..verification.metric_pose import MetricPose
from .base import ExportOptions
from .loops import frame_times_ns

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

# Odometry edge sigmas when the messages carry no usable covariance: (x, y, z) in metres and
# (rot x, rot y, rot z) in radians, per camera frame.
DEFAULT_ODOMETRY_SIGMAS = (0.1, 0.1, 0.1, 0.02, 0.02, 0.02)

# A variance this large marks an axis the odometry does not measure (ROS: 1e6, 99999).
UNMEASURED_VARIANCE = 1e3


EdgeKind = Literal["odometry", "loop"]
# What a loop edge measures: a recorded metric pose (its method), or the placeholder model.
PLACEHOLDER = "placeholder"
METRIC_MODELS = (DEPTH_PNP, ODOMETRY_PNP, ROTATION_ONLY)


@dataclass(frozen=True)
class Edge:
    """A relative-pose measurement: pose of vertex `to_id` in the frame of vertex `from_id`."""

    kind: EdgeKind
    from_id: int
    to_id: int
    translation: F64  # (3,)
    quaternion_xyzw: F64  # (4,)
    information: F64  # (6, 6) over x, y, z, rot x, rot y, rot z
    model: str = ""  # loop edges: PLACEHOLDER or the metric method (METRIC_MODELS)


@dataclass(frozen=True)
class PoseGraph:
    """Vertices (frame indices and their poses) and edges, plus what was left out."""

    vertex_ids: I64  # frame indices, ascending
    poses: PoseTrack  # the vertices' poses, at their detector times
    odometry_edges: list[Edge]
    loop_edges: list[Edge]
    frames_outside_odometry: int  # frames before the first or after the last odometry pose
    loop_closures_left_out: int  # loop closures with a frame outside the odometry
    default_information_edges: int  # odometry edges without a usable covariance
    odometry_skipped: Mapping[str, int] = field(default_factory=dict)  # unusable pose messages

    @property
    def loop_models(self) -> dict[str, int]:
        """Loop edges by model (PLACEHOLDER or a metric method), in a fixed order."""
        counts = {
            m: sum(e.model == m for e in self.loop_edges) for m in (*METRIC_MODELS, PLACEHOLDER)
        }
        return {model: n for model, n in counts.items() if n}

    @property
    def summary(self) -> str:
        models = ", ".join(f"{n} {model}" for model, n in self.loop_models.items())
        text = (
            f"{len(self.vertex_ids)} vertices, {len(self.odometry_edges)} odometry edges, "
            f"{len(self.loop_edges)} loop edges{f' ({models})' if models else ''}"
        )
        notes = self.notes
        return text + (f" ({'; '.join(notes)})" if notes else "")

    @property
    def notes(self) -> list[str]:
        """What the graph left out or assumed (the export's and optimize's summaries say it)."""
        notes = []
        if skipped := describe_skipped(self.odometry_skipped):
            notes.append(f"odometry: {skipped}")
        if self.frames_outside_odometry:
            notes.append(f"{self.frames_outside_odometry} frames outside the odometry left out")
        if self.loop_closures_left_out:
            notes.append(f"{self.loop_closures_left_out} loop closures on such frames left out")
        if self.default_information_edges:
            notes.append(
                f"{self.default_information_edges} odometry edges without a covariance "
                "use the default information"
            )
        return notes


def with_pose_topic(options: ExportOptions, log: AnnotatedLog) -> ExportOptions:
    """`options` with a pose topic: the one given, else the odometry the annotating run
    recorded, else the one annotate's rule picks (`default_pose_topic`: the first
    nav_msgs/Odometry topic, else the first of another pose type), in the log the poses come
    from (`options.poses_log`, else the annotated log).

    Raises UsageError when that log has none (a sidecar without --poses-from).
    """
    if options.odometry_topic is not None:
        return options
    poses_log = options.poses_log or log.path
    recorded = log.metadata.odometry_topic
    with open_source(poses_log) as source:
        # Not in a sidecar, which holds our channels only: then the rule finds none either.
        present = any(channel.topic == recorded for channel in source.channels())
        topic = recorded if recorded and present else default_pose_topic(source)
    if topic is None:
        raise UsageError(
            f"{poses_log}: no pose topic ({', '.join(POSE_TYPES)}): give --odometry-topic, or "
            "--poses-from the original log for a sidecar"
        )
    return dataclasses.replace(options, odometry_topic=topic)


def build_pose_graph(log: AnnotatedLog, options: ExportOptions) -> PoseGraph:
    """The pose graph of `log` with `options.odometry_topic` from `options.poses_log` (default:
    the annotated log itself).

    Raises SourceError when the log has no frame times, the topic cannot be read, or no frame
    lies within the odometry's time range.
    """
    if options.odometry_topic is None:
        raise ValueError("build_pose_graph needs options.odometry_topic")
    if options.poses_log is not None and options.poses_log_check:
        check_source_log(log, options.poses_log, "--poses-from")
    times = frame_times_ns(log)
    odometry = read_poses(options.poses_log or log.path, options.odometry_topic)
    inside = (times >= odometry.times_ns[0]) & (times <= odometry.times_ns[-1])
    if not inside.any():
        raise SourceError(
            f"{options.poses_log or log.path}: no camera frame lies within the time range of "
            f"{options.odometry_topic} ({len(times)} frames)"
        )
    loops = log.reported_loop_closures
    ids = _kept_frames(inside, loops, options.stride)
    poses = odometry.interpolate(times[ids])
    odometry_edges, defaults = _odometry_edges(ids, poses)
    kept = set(ids.tolist())
    loop_edges = [
        _loop_edge(lc, options)
        for lc in loops
        if lc.query.index in kept and lc.matched.index in kept
    ]
    return PoseGraph(
        vertex_ids=ids,
        poses=poses,
        odometry_edges=odometry_edges,
        loop_edges=loop_edges,
        frames_outside_odometry=int(np.count_nonzero(~inside)),
        loop_closures_left_out=len(loops) - len(loop_edges),
        default_information_edges=defaults,
        odometry_skipped=dict(odometry.skipped),
    )


def _kept_frames(inside: npt.NDArray[np.bool_], loops: list[LoopClosureRecord], stride: int) -> I64:
    """Every stride-th frame, the first and last frame with odometry, and every loop frame."""
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    indices = np.flatnonzero(inside)
    wanted = np.zeros(len(inside), dtype=bool)
    wanted[indices[indices % stride == 0]] = True
    wanted[[indices[0], indices[-1]]] = True
    for lc in loops:
        for index in (lc.query.index, lc.matched.index):
            if 0 <= index < len(wanted):
                wanted[index] = True
    return np.flatnonzero(wanted & inside).astype(np.int64)


# ---------------------------------------------------------------------------------------------
# Edges


def _rotation(quaternion_xyzw: F64) -> Rotation:
    return Rotation.from_quat(quaternion_xyzw)


def relative_pose(
    position_a: F64, quaternion_a: F64, position_b: F64, quaternion_b: F64
) -> tuple[F64, F64]:
    """Pose b in the frame of pose a (T_a^-1 T_b): translation and quaternion xyzw."""
    inverse_a = _rotation(quaternion_a).inv()
    translation = inverse_a.apply(position_b - position_a)
    quaternion = (inverse_a * _rotation(quaternion_b)).as_quat()
    return np.asarray(translation, np.float64), _positive_w(np.asarray(quaternion, np.float64))


def _positive_w(quaternion: F64) -> F64:
    return -quaternion if quaternion[3] < 0 else quaternion


def information_from_covariance(covariance: F64 | None, frames_spanned: int) -> F64 | None:
    """The inverse of `covariance` * frames_spanned; None when it is absent, all zero, not
    finite or not positive definite (the caller uses the default then).

    An axis with a variance of at least `UNMEASURED_VARIANCE` (ROS drivers write 1e6 or 99999
    for an axis they do not measure, e.g. z, roll and pitch of wheel odometry) gets the
    default sigma instead: left almost free, it would let loop edges tilt the graph out of
    the plane the odometry reports.
    """
    if covariance is None or not np.isfinite(covariance).all() or not covariance.any():
        return None
    symmetric = (covariance + covariance.T) / 2
    unmeasured = np.diagonal(symmetric) >= UNMEASURED_VARIANCE
    symmetric[unmeasured, :] = 0.0
    symmetric[:, unmeasured] = 0.0
    defaults = np.square(np.asarray(DEFAULT_ODOMETRY_SIGMAS))
    symmetric[unmeasured, unmeasured] = defaults[unmeasured]
    symmetric *= frames_spanned
    if np.linalg.eigvalsh(symmetric).min() <= 0:
        return None
    information = np.linalg.inv(symmetric)
    return np.asarray((information + information.T) / 2, np.float64)


def default_information(sigmas: tuple[float, ...], frames_spanned: int = 1) -> F64:
    variances = np.square(np.asarray(sigmas, np.float64)) * frames_spanned
    return np.diag(1.0 / variances)


def _odometry_edges(ids: I64, poses: PoseTrack) -> tuple[list[Edge], int]:
    edges, defaults = [], 0
    for k in range(1, len(ids)):
        translation, quaternion = relative_pose(
            poses.positions[k - 1],
            poses.quaternions_xyzw[k - 1],
            poses.positions[k],
            poses.quaternions_xyzw[k],
        )
        span = int(ids[k] - ids[k - 1])
        covariance = None if poses.covariances is None else poses.covariances[k]
        information = information_from_covariance(covariance, span)
        if information is None:
            defaults += 1
            information = default_information(DEFAULT_ODOMETRY_SIGMAS, span)
        edges.append(
            Edge("odometry", int(ids[k - 1]), int(ids[k]), translation, quaternion, information)
        )
    return edges, defaults


def verified_body_rotation(loop_closure: LoopClosureRecord) -> F64 | None:
    """The match camera's orientation in the query camera's frame, in body axes, from the
    verification's R (X_match = R X_query + t, optical axes); None when not recorded."""
    rotation = loop_closure.rotation_xyzw
    if not loop_closure.has_relative_pose or len(rotation) != 4:
        return None
    values = np.asarray(rotation, np.float64)
    if not np.isfinite(values).all() or np.linalg.norm(values) < 1e-9:
        return None
    match_in_query = _rotation(values).inv().as_matrix()  # R^T, optical axes
    body = OPTICAL_TO_BODY @ match_in_query @ OPTICAL_TO_BODY.T
    return _positive_w(np.asarray(Rotation.from_matrix(body).as_quat(), np.float64))


def _loop_edge(loop_closure: LoopClosureRecord, options: ExportOptions) -> Edge:
    if options.loop_model == "metric":
        metric = metric_loop_edge(loop_closure)
        if metric is not None:
            return metric
    return placeholder_loop_edge(loop_closure, options)


def metric_loop_edge(loop_closure: LoopClosureRecord) -> Edge | None:
    """The recorded metric pose as a loop edge (module docstring); None when there is none,
    or it is not finite or its covariance not positive definite (where constrained)."""
    method = loop_closure.metric_method
    if method not in METRIC_MODELS:
        return None
    rotation_xyzw = np.asarray(loop_closure.metric_rotation_xyzw, np.float64)
    translation = np.asarray(loop_closure.metric_translation, np.float64)
    has_translation = method != ROTATION_ONLY
    if not np.isfinite(rotation_xyzw).all() or (
        has_translation and not np.isfinite(translation).all()
    ):
        return None
    pose = MetricPose(
        method,  # type: ignore[arg-type]  # one of METRIC_MODELS
        (
            float(rotation_xyzw[0]),
            float(rotation_xyzw[1]),
            float(rotation_xyzw[2]),
            float(rotation_xyzw[3]),
        ),
        (float(translation[0]), float(translation[1]), float(translation[2]))
        if has_translation
        else None,
        loop_closure.metric_covariance_matrix(),
        loop_closure.metric_inliers,
        loop_closure.metric_residual_px,
    ).match_in_query()
    match_in_query = _rotation(np.asarray(pose.rotation_xyzw)).as_matrix()
    # The covariance perturbs the pose about the query camera's axes (R' = exp(w) R, t + dt);
    # a pose-graph edge (GTSAM, g2o) perturbs it in the match camera's own axes (R exp(w'),
    # t + R v): w' = R^T w, v = R^T dt; then optical axes into body axes.
    turn = OPTICAL_TO_BODY @ match_in_query.T
    information = _information(pose.covariance, turn, has_translation)
    if information is None:
        return None
    body_rotation = OPTICAL_TO_BODY @ match_in_query @ OPTICAL_TO_BODY.T
    quaternion = _positive_w(np.asarray(Rotation.from_matrix(body_rotation).as_quat(), np.float64))
    body_translation = np.zeros(3)
    if pose.translation is not None:
        body_translation = OPTICAL_TO_BODY @ np.asarray(pose.translation, np.float64)
    return Edge(
        "loop",
        loop_closure.query.index,
        loop_closure.matched.index,
        body_translation,
        quaternion,
        information,
        method,
    )


def _information(covariance: F64, turn: F64, has_translation: bool) -> F64 | None:
    """The inverse of `covariance` (ROS order) with both blocks' axes turned by `turn`; without
    a translation, its block is left at zero information. None when not positive definite."""
    jacobian = np.zeros((6, 6))
    jacobian[:3, :3] = jacobian[3:, 3:] = turn
    if has_translation:
        turned = jacobian @ covariance @ jacobian.T
    else:
        turned = np.zeros((6, 6))
        turned[3:, 3:] = turn @ covariance[3:, 3:] @ turn.T
    block = slice(0, 6) if has_translation else slice(3, 6)
    constrained = (turned[block, block] + turned[block, block].T) / 2
    if not np.isfinite(constrained).all() or np.linalg.eigvalsh(constrained).min() <= 0:
        return None
    information = np.zeros((6, 6))
    inverse = np.linalg.inv(constrained)
    information[block, block] = (inverse + inverse.T) / 2
    return information


def placeholder_loop_edge(loop_closure: LoopClosureRecord, options: ExportOptions) -> Edge:
    """The placeholder measurement model (module docstring)."""
    quaternion = np.array([0.0, 0.0, 0.0, 1.0])
    if options.use_verified_rotation:
        verified = verified_body_rotation(loop_closure)
        if verified is not None:
            quaternion = verified
    sigmas = (options.loop_translation_sigma_m,) * 3 + (options.loop_rotation_sigma_rad,) * 3
    return Edge(
        "loop",
        loop_closure.query.index,
        loop_closure.matched.index,
        np.zeros(3),
        quaternion,
        default_information(sigmas),
        PLACEHOLDER,
    )
