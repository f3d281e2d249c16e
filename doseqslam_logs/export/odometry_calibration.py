"""Odometry self-calibration from the metric loop edges: heading drift and a covariance scale.

Wheel odometry drifts by a bias, not by white noise: a wheel a little larger than the other
turns the robot's heading a fraction of a degree a second, the same way the whole drive. The
pose graph's odometry edges are white noise with the covariance the /odom messages state, and
that covariance is rarely honest (drivers often write a fixed covariance many times the real
error). With it too loose the loop edges alone shape the trajectory and each loop edge's error
goes into it unfiltered; made tighter by hand, the bias the white noise cannot explain bends
the trajectory between loops. Calibrating both from the data solves the two at once
(docs/export.md, "The odometry calibrated from the loop edges"):

1. For every loop edge with a measured translation (`depth_pnp`, `odometry_pnp`), the
   discrepancy between its measurement and the odometry chain between its two vertices, in
   the tangent space at the chain's end (translation, rotation vector; ROS order), with the
   chain's covariance propagated along it (adjoints, prefix sums: linear in the graph).
2. The heading's drift: the heading part of the discrepancies is linear in the time the
   odometry reported motion along the chain (a yaw-rate bias b, a gyroscope's or a wheel's a
   little larger than the other) and in the angle it turned (a yaw scale k: a wheelbase or a
   gyroscope's scale a little off, which a U-turn shows and a constant turn hides in b); b and
   k are their robust (Cauchy, IRLS) weighted fit, k with a weak prior (`YAW_SCALE_PRIOR`),
   and k only when it earns its place: on a drive whose turns keep pace with time the two
   regressors are one, and k would fit noise.
3. The covariance scale s: with the bias removed, the median of each discrepancy's squared
   Mahalanobis norm under s * chain covariance + loop-edge covariance equals chi-square's
   median for 6 degrees of freedom (the loop edges' covariances are calibrated against
   ground truth: `verification.metric_pose`). Bisection on log s within
   [`MIN_COVARIANCE_SCALE`, `MAX_COVARIANCE_SCALE`]. The median ignores wrong loop edges as
   long as they are fewer than half.

Steps 2 and 3 alternate `ROUNDS` times with the bias alone, then `ROUNDS` more with the yaw
scale if a likelihood-ratio test takes it (`YAW_SCALE_EVIDENCE`). `calibrated_graph` then
turns every odometry edge's heading back by b * dt (dt while it moved) + k * its turn,
divides its information by s and integrates the vertices again. A graph with fewer than
`MIN_LOOP_EDGES` such loop edges is left as it is (b = k = 0, s = 1).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from ..annotations.records import DEPTH_PNP, ODOMETRY_PNP
from .pose_graph import Edge, PoseGraph

F64 = npt.NDArray[np.float64]

# Fewer loop edges with a translation than this give no calibration: a median of a handful.
MIN_LOOP_EDGES = 5
# The scale's search range. The floor keeps the odometry from becoming rigid when even a tiny
# odometry covariance explains the discrepancies; where it lies matters little (the bias does
# the work).
MIN_COVARIANCE_SCALE = 1e-4
MAX_COVARIANCE_SCALE = 1e3
ROUNDS = 3
CHI2_6_MEDIAN = 5.348  # scipy.stats.chi2.ppf(0.5, 6)
# An odometry edge moved when it translated or turned more than this (m, rad): a wheel that
# does not turn reports nothing, and its bias does not act.
MOTION_EPSILON = 1e-5
# A yaw scale's prior sigma (a fraction of the angle turned): wheelbases and gyroscopes are off
# by a few percent at most; only a drive whose turns and time are collinear leans on it.
YAW_SCALE_PRIOR = 0.05
# The yaw scale is fitted only when it lowers the heading fit's Cauchy cost by more than this,
# twice (a likelihood-ratio test, chi-square with 1 degree of freedom at 99 %): on a drive whose
# turns keep pace with time it would only fit noise.
YAW_SCALE_EVIDENCE = 6.635
_TRANSLATION_MODELS = (DEPTH_PNP, ODOMETRY_PNP)
_IRLS_STEPS = 20


@dataclass(frozen=True)
class OdometryCalibration:
    """What the calibration found: the yaw-rate bias (rad/s while the odometry moves) and the
    yaw scale (per radian turned), both taken out of the odometry's heading, and the factor on
    its covariance; `metric_loop_edges` it had (with a translation), `off` when it was not
    asked for."""

    yaw_rate_bias: float = 0.0
    covariance_scale: float = 1.0
    metric_loop_edges: int = 0
    off: bool = False
    yaw_scale: float = 0.0

    @property
    def applied(self) -> bool:
        return not self.off and self.metric_loop_edges >= MIN_LOOP_EDGES

    def summary(self) -> str:
        if self.off:
            return "odometry as stated (calibration off)"
        if not self.applied:
            return (
                f"odometry as stated ({self.metric_loop_edges} metric loop edges with a "
                f"translation, {MIN_LOOP_EDGES} needed to calibrate it)"
            )
        return (
            f"odometry calibrated on {self.metric_loop_edges} metric loop edges: yaw-rate bias "
            f"{np.degrees(self.yaw_rate_bias):+.4f} deg/s, "
            + (f"yaw scale {100 * self.yaw_scale:+.2f} %" if self.yaw_scale else "no yaw scale")
            + f", covariance x {self.covariance_scale:.3g}"
        )

    def to_json(self) -> dict[str, object]:
        return {
            "applied": self.applied,
            "metric_loop_edges": self.metric_loop_edges,
            "yaw_rate_bias_deg_s": float(np.degrees(self.yaw_rate_bias)),
            "yaw_scale": self.yaw_scale,  # 0 when not fitted (YAW_SCALE_EVIDENCE)
            "covariance_scale": self.covariance_scale,
        }


# ---------------------------------------------------------------------------------------------
# SE(3) in ROS tangent order (x, y, z, rot x, rot y, rot z), right perturbations T * Exp(xi)


def _skew(v: F64) -> F64:
    matrix = np.zeros((*v.shape[:-1], 3, 3))
    matrix[..., 0, 1], matrix[..., 0, 2], matrix[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    matrix[..., 1, 0], matrix[..., 2, 0], matrix[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return matrix


def adjoint(rotation: F64, translation: F64) -> F64:
    """Ad(T) in ROS tangent order: Exp(Ad(T) xi) = T Exp(xi) T^-1; batched over leading axes."""
    matrix = np.zeros((*rotation.shape[:-2], 6, 6))
    matrix[..., :3, :3] = rotation
    matrix[..., :3, 3:] = _skew(translation) @ rotation
    matrix[..., 3:, 3:] = rotation
    return matrix


@dataclass(frozen=True)
class _Odometry:
    """The odometry edges as arrays."""

    turns: F64  # (N, 3, 3): each edge's rotation
    translations: F64  # (N, 3)
    covariances: F64  # (N, 6, 6), ROS order
    motion: F64  # (N,): each edge's duration while the odometry moved, else 0 (s)
    headings: F64  # (N,): each edge's turn about z (rad)

    @classmethod
    def of(cls, graph: PoseGraph) -> _Odometry:
        edges = graph.odometry_edges
        turns = Rotation.from_quat(np.array([e.quaternion_xyzw for e in edges]).reshape(-1, 4))
        translations = np.array([e.translation for e in edges], np.float64).reshape(-1, 3)
        information = np.array([e.information for e in edges], np.float64).reshape(-1, 6, 6)
        seconds = np.asarray(graph.poses.times_ns, np.float64) * 1e-9
        moved = (np.linalg.norm(translations, axis=1) > MOTION_EPSILON) | (
            turns.magnitude() > MOTION_EPSILON
        )
        motion = np.where(moved, np.diff(seconds), 0.0)
        covariances = np.asarray(np.linalg.inv(information), np.float64)
        headings = turns.as_rotvec()[:, 2]
        return cls(turns.as_matrix(), translations, covariances, motion, headings)

    def turned(self, heading: _Heading) -> F64:
        """The edges' rotations with the heading's drift taken out."""
        drift = heading.bias * self.motion + heading.scale * self.headings
        back = Rotation.from_rotvec(np.outer(-drift, [0.0, 0.0, 1.0]))
        return np.asarray(back.as_matrix() @ self.turns, np.float64)


@dataclass(frozen=True)
class _Heading:
    bias: float = 0.0  # rad/s while moving
    scale: float = 0.0  # per radian turned


@dataclass(frozen=True)
class _Chain:
    """The odometry integrated along the vertices and its covariance's prefix sums."""

    rotations: F64  # (N, 3, 3), vertex k in the first vertex's frame
    positions: F64  # (N, 3)
    world_covariance: F64  # (N, 6, 6): sum over edges before vertex k, moved to the first frame
    moving_time: F64  # (N,): seconds of motion before vertex k
    turned: F64  # (N,): the odometry's turns about z before vertex k, as it states them (rad)

    def between(self, a: int, c: int) -> tuple[F64, F64, F64, float, float]:
        """Vertex c in vertex a's frame (rotation, translation), its covariance at c, and
        the signed time of motion and angle turned from a to c."""
        rotation = self.rotations[a].T @ self.rotations[c]
        translation = self.rotations[a].T @ (self.positions[c] - self.positions[a])
        inverse_c = adjoint(self.rotations[c].T, -self.rotations[c].T @ self.positions[c])
        spanned = self.world_covariance[max(a, c)] - self.world_covariance[min(a, c)]
        covariance = inverse_c @ spanned @ inverse_c.T
        moving = float(self.moving_time[c] - self.moving_time[a])
        return rotation, translation, covariance, moving, float(self.turned[c] - self.turned[a])


def _integrate(odometry: _Odometry, heading: _Heading) -> _Chain:
    turns = odometry.turned(heading)
    rotations = np.empty((len(turns) + 1, 3, 3))
    rotations[0] = np.eye(3)
    for k, turn in enumerate(turns):  # sequential, but 3x3: cheap
        rotations[k + 1] = rotations[k] @ turn
    steps = np.einsum("nij,nj->ni", rotations[:-1], odometry.translations)
    positions = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
    moved = adjoint(rotations[1:], positions[1:])
    world = moved @ odometry.covariances @ np.swapaxes(moved, 1, 2)
    world = np.concatenate([np.zeros((1, 6, 6)), np.cumsum(world, axis=0)])
    moving = np.concatenate([[0.0], np.cumsum(odometry.motion)])
    turned = np.concatenate([[0.0], np.cumsum(odometry.headings)])
    return _Chain(rotations, positions, world, moving, turned)


@dataclass(frozen=True)
class _Discrepancies:
    """Each loop edge against the odometry chain between its two vertices."""

    residuals: F64  # (L, 6), ROS order: the measurement in the chain's end frame
    chain_covariances: F64  # (L, 6, 6), the odometry as stated (scale 1)
    edge_covariances: F64  # (L, 6, 6)
    moving_times: F64  # (L,), signed
    turned_angles: F64  # (L,), signed


def _discrepancies(
    graph: PoseGraph, loops: Sequence[Edge], odometry: _Odometry, heading: _Heading
) -> _Discrepancies:
    chain = _integrate(odometry, heading)
    index = {int(v): k for k, v in enumerate(graph.vertex_ids)}
    residuals, covariances, moving, turned = [], [], [], []
    for loop in loops:
        rotation, translation, covariance, time, angle = chain.between(
            index[loop.from_id], index[loop.to_id]
        )
        measured = Rotation.from_quat(loop.quaternion_xyzw).as_matrix()
        turn = Rotation.from_matrix(rotation.T @ measured).as_rotvec()
        residuals.append(np.concatenate([rotation.T @ (loop.translation - translation), turn]))
        covariances.append(covariance)
        moving.append(time)
        turned.append(angle)
    information = np.array([loop.information for loop in loops], np.float64)
    return _Discrepancies(
        np.asarray(residuals, np.float64).reshape(-1, 6),
        np.asarray(covariances, np.float64).reshape(-1, 6, 6),
        np.asarray(np.linalg.inv(information), np.float64),
        np.asarray(moving, np.float64),
        np.asarray(turned, np.float64),
    )


def _heading_step(
    found: _Discrepancies, scale: float, taken: _Heading, yaw_scale: bool
) -> tuple[_Heading, float]:
    """The heading residuals' robust fit against the time of motion (and with `yaw_scale`
    the angle turned), the drift `taken` out already: the step to take out too, and the
    fit's Cauchy cost (sum of log(1 + r^2), r whitened). The yaw scale's weak prior is on the
    whole, taken.scale - step."""
    heading = found.residuals[:, 5]
    regressors = np.column_stack([found.moving_times, found.turned_angles])[:, : 1 + yaw_scale]
    variances = scale * found.chain_covariances[:, 5, 5] + found.edge_covariances[:, 5, 5]
    prior = np.diag([0.0, 1.0 / YAW_SCALE_PRIOR**2])[: 1 + yaw_scale, : 1 + yaw_scale]
    pull = prior @ np.array([0.0, taken.scale])[: 1 + yaw_scale]
    slopes = np.zeros(1 + yaw_scale)
    for _ in range(_IRLS_STEPS):
        whitened = (heading - regressors @ slopes) / np.sqrt(variances)
        weights = 1.0 / (1.0 + whitened**2) / variances
        normal = regressors.T @ (weights[:, None] * regressors) + prior
        normal[0, 0] += 1e-12 * (1.0 + normal[0, 0])  # no motion at all: no bias
        slopes = np.linalg.solve(normal, regressors.T @ (weights * heading) + pull)
    whitened = (heading - regressors @ slopes) / np.sqrt(variances)
    step = _Heading(float(slopes[0]), float(slopes[1]) if yaw_scale else 0.0)
    return step, float(np.sum(np.log1p(whitened**2)))


def _rounds(
    graph: PoseGraph,
    loops: Sequence[Edge],
    odometry: _Odometry,
    start: tuple[_Heading, float],
    yaw_scale: bool,
) -> tuple[_Heading, float]:
    """`ROUNDS` of the heading's fit and the covariance scale's, from `start`."""
    heading, scale = start
    for _ in range(ROUNDS):
        step, _ = _heading_step(
            _discrepancies(graph, loops, odometry, heading), scale, heading, yaw_scale
        )
        heading = _Heading(heading.bias - step.bias, heading.scale - step.scale)
        scale = _scale_step(_discrepancies(graph, loops, odometry, heading))
    return heading, scale


def _median_excess(found: _Discrepancies, log_scale: float) -> float:
    covariances = np.exp(log_scale) * found.chain_covariances + found.edge_covariances
    solved = np.linalg.solve(covariances, found.residuals[..., None])[..., 0]
    return float(np.median(np.sum(found.residuals * solved, axis=1))) - CHI2_6_MEDIAN


def _scale_step(found: _Discrepancies) -> float:
    low, high = np.log(MIN_COVARIANCE_SCALE), np.log(MAX_COVARIANCE_SCALE)
    if _median_excess(found, low) <= 0:
        return MIN_COVARIANCE_SCALE
    if _median_excess(found, high) >= 0:
        return MAX_COVARIANCE_SCALE
    for _ in range(40):  # the excess falls as the scale grows
        middle = (low + high) / 2
        low, high = (middle, high) if _median_excess(found, middle) > 0 else (low, middle)
    return float(np.exp((low + high) / 2))


def calibrate_odometry(graph: PoseGraph) -> OdometryCalibration:
    """The yaw-rate bias, yaw scale (0 unless `YAW_SCALE_EVIDENCE` is met) and covariance
    scale of `graph`'s odometry (module docstring)."""
    loops = [e for e in graph.loop_edges if e.model in _TRANSLATION_MODELS]
    if len(loops) < MIN_LOOP_EDGES or not graph.odometry_edges:
        return OdometryCalibration(metric_loop_edges=len(loops))
    odometry = _Odometry.of(graph)
    heading, scale = _rounds(graph, loops, odometry, (_Heading(), 1.0), yaw_scale=False)
    found = _discrepancies(graph, loops, odometry, heading)
    costs = [_heading_step(found, scale, heading, with_scale)[1] for with_scale in (False, True)]
    if 2 * (costs[0] - costs[1]) > YAW_SCALE_EVIDENCE:  # the turns explain what time does not
        heading, scale = _rounds(graph, loops, odometry, (heading, scale), yaw_scale=True)
    return OdometryCalibration(heading.bias, scale, len(loops), yaw_scale=heading.scale)


def chain_covariances(graph: PoseGraph, loops: Sequence[Edge]) -> F64:
    """(L, 6, 6), ROS order: the covariance of the odometry chain between each loop edge's two
    vertices, at the loop edge's `to_id` end, with `graph`'s odometry edges as they are."""
    chain = _integrate(_Odometry.of(graph), _Heading())
    index = {int(v): k for k, v in enumerate(graph.vertex_ids)}
    found = [chain.between(index[e.from_id], index[e.to_id])[2] for e in loops]
    return np.asarray(found, np.float64).reshape(-1, 6, 6)


def calibrated_graph(graph: PoseGraph, calibration: OdometryCalibration) -> PoseGraph:
    """`graph` with its odometry edges turned by the bias and their covariance scaled, and
    the vertices integrated again from the first along the corrected edges."""
    if not calibration.applied:
        return graph
    odometry = _Odometry.of(graph)
    heading = _Heading(calibration.yaw_rate_bias, calibration.yaw_scale)
    quaternions = Rotation.from_matrix(odometry.turned(heading)).as_quat()
    quaternions *= np.where(quaternions[:, 3:] < 0, -1.0, 1.0)  # w >= 0, as relative_pose
    edges = [
        dataclasses.replace(
            edge,
            quaternion_xyzw=np.asarray(quaternion, np.float64),
            information=edge.information / calibration.covariance_scale,
        )
        for edge, quaternion in zip(graph.odometry_edges, quaternions, strict=True)
    ]
    chain = _integrate(odometry, heading)
    first = Rotation.from_quat(graph.poses.quaternions_xyzw[0]).as_matrix()
    positions = graph.poses.positions[0] + np.einsum("ij,nj->ni", first, chain.positions)
    rotations = np.einsum("ij,njk->nik", first, chain.rotations)
    vertex_quaternions = np.asarray(Rotation.from_matrix(rotations).as_quat(), np.float64)
    poses = dataclasses.replace(
        graph.poses, positions=positions, quaternions_xyzw=vertex_quaternions
    )
    return dataclasses.replace(graph, odometry_edges=edges, poses=poses)
