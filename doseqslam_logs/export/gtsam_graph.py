"""A `PoseGraph` in GTSAM form, and its robust optimization (the `optimize` command's core).

`to_gtsam(graph)` gives a `gtsam.NonlinearFactorGraph` and initial `gtsam.Values`, keyed by
frame index:

* a `PriorFactorPose3` holding the first vertex where the odometry put it (tight sigmas), so
  that the optimized trajectory stays in the odometry's frame;
* a `BetweenFactorPose3` per odometry edge with its information as a Gaussian noise model;
* a `BetweenFactorPose3` per loop edge with the same Gaussian wrapped in a robust kernel
  (`noiseModel.Robust`, Cauchy by default): a loop edge that disagrees with the rest pulls
  with a bounded force instead of one growing with its error.

Our information matrices are in ROS order (x, y, z, rot x, rot y, rot z); GTSAM's Pose3 tangent
puts the rotation first (rot x, rot y, rot z, x, y, z), so the blocks are swapped
(`gtsam_information`), as `gtsam.readG2o` does for a g2o file.

`optimize_pose_graph(graph)` first calibrates the odometry from the metric loop edges
(`odometry_calibration`: heading drift and a covariance factor), then runs Levenberg-Marquardt,
then the outlier check: a loop edge whose squared Mahalanobis error (with its Gaussian
information, no kernel; plus the calibrated odometry's between its two vertices) at the
optimum exceeds a chi-square bound (6 degrees of freedom, 99 %) is dropped and the graph
optimized again from the odometry, until every remaining loop edge passes. A kernel alone
only weakens a wrong loop; the check removes it.

GTSAM is the optional extra `gtsam` and is imported only when a function here needs it.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from ..errors import UsageError
from .base import OptimizeOptions
from .odometry_calibration import (
    OdometryCalibration,
    calibrate_odometry,
    calibrated_graph,
    chain_covariances,
)
from .pose_graph import Edge, PoseGraph

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

GTSAM_EXTRA = "pip install 'doseqslam-logs[gtsam]'"
# The first vertex stays where the odometry put it (sigmas in rad and m).
PRIOR_SIGMAS = (1e-6,) * 6
MAX_OUTLIER_ROUNDS = 10

# ROS order (x, y, z, rot x, rot y, rot z) -> GTSAM Pose3 tangent order (rot, then translation).
_GTSAM_ORDER = np.array([3, 4, 5, 0, 1, 2])


def gtsam_information(information: F64) -> F64:
    """A 6x6 information matrix in ROS order (x, y, z, rot x, rot y, rot z) reordered for
    GTSAM's Pose3 tangent (rot x, rot y, rot z, x, y, z): the translation and rotation blocks
    swap places, and so do the two off-diagonal blocks."""
    matrix = np.asarray(information, np.float64)
    if matrix.shape != (6, 6):
        raise ValueError(f"an information matrix must be 6x6, got {matrix.shape}")
    return np.asarray(matrix[np.ix_(_GTSAM_ORDER, _GTSAM_ORDER)], np.float64)


def import_gtsam() -> ModuleType:
    """The gtsam module; UsageError (exit 2) naming the extra when it is not installed."""
    try:
        return importlib.import_module("gtsam")
    except ImportError as exc:
        raise UsageError(f"pose-graph optimization needs GTSAM ({exc}): {GTSAM_EXTRA}") from exc


@dataclass(frozen=True)
class GtsamGraph:
    """A pose graph in GTSAM form: factors, initial values (the odometry), and where each
    loop edge's factor is."""

    graph: Any  # gtsam.NonlinearFactorGraph
    initial: Any  # gtsam.Values, Pose3 by frame index
    keys: list[int]  # the vertices' frame indices, ascending
    loop_factors: list[int]  # index in `graph` of each loop edge's factor, in edge order


def gtsam_pose(translation: F64, quaternion_xyzw: F64) -> Any:
    """A gtsam.Pose3 from a translation and a unit quaternion (x, y, z, w)."""
    gtsam = import_gtsam()
    x, y, z, w = (float(v) for v in quaternion_xyzw)
    rotation = gtsam.Rot3.Quaternion(w, x, y, z)
    return gtsam.Pose3(rotation, np.asarray(translation, np.float64))


def _loop_noise(gtsam: ModuleType, information: F64, options: OptimizeOptions) -> Any:
    gaussian = gtsam.noiseModel.Gaussian.Information(gtsam_information(information))
    if options.loop_kernel == "none":
        return gaussian
    estimators = gtsam.noiseModel.mEstimator
    kernel = (estimators.Cauchy if options.loop_kernel == "cauchy" else estimators.Huber).Create(
        options.kernel_width
    )
    return gtsam.noiseModel.Robust.Create(kernel, gaussian)


def _between(gtsam: ModuleType, edge: Edge, noise: Any) -> Any:
    measured = gtsam_pose(edge.translation, edge.quaternion_xyzw)
    return gtsam.BetweenFactorPose3(edge.from_id, edge.to_id, measured, noise)


def to_gtsam(
    graph: PoseGraph,
    options: OptimizeOptions | None = None,
    loop_edges: Sequence[Edge] | None = None,
) -> GtsamGraph:
    """`graph` as a GTSAM factor graph (module docstring) with `loop_edges` (default: all of
    `graph.loop_edges`) under `options`' kernel. Raises UsageError without GTSAM."""
    gtsam = import_gtsam()
    options = options or OptimizeOptions()
    loops = graph.loop_edges if loop_edges is None else list(loop_edges)
    keys = [int(k) for k in graph.vertex_ids]
    initial = gtsam.Values()
    for k, key in enumerate(keys):
        initial.insert(key, gtsam_pose(graph.poses.positions[k], graph.poses.quaternions_xyzw[k]))
    factors = gtsam.NonlinearFactorGraph()
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(PRIOR_SIGMAS, np.float64))
    factors.add(gtsam.PriorFactorPose3(keys[0], initial.atPose3(keys[0]), prior))
    for edge in graph.odometry_edges:
        noise = gtsam.noiseModel.Gaussian.Information(gtsam_information(edge.information))
        factors.add(_between(gtsam, edge, noise))
    loop_factors = []
    for edge in loops:
        loop_factors.append(int(factors.size()))
        factors.add(_between(gtsam, edge, _loop_noise(gtsam, edge.information, options)))
    return GtsamGraph(factors, initial, keys, loop_factors)


# ---------------------------------------------------------------------------------------------
# Optimization


@dataclass(frozen=True)
class OptimizedGraph:
    """The optimized vertex poses and what the optimization did."""

    vertex_ids: I64  # frame indices, as in the PoseGraph
    positions: F64  # (N, 3), odometry frame
    quaternions_xyzw: F64  # (N, 4)
    iterations: int  # Levenberg-Marquardt iterations, summed over the rounds
    rounds: int  # optimizations run (1 + those after dropping loop edges)
    error_before: float  # the final graph's error at the odometry (GTSAM's 0.5 * sum of squares)
    error_after: float  # the same graph's error at the optimum
    loop_edges_kept: int
    rejected_loop_edges: list[int] = field(default_factory=list)  # indices into loop_edges
    calibration: OdometryCalibration = field(default_factory=OdometryCalibration)

    def summary(self, graph: PoseGraph) -> str:
        """E.g. '240 vertices, 239 odometry edges, 65 loop edges; 12 iterations, error
        1520.3 -> 20.1; loop edges: 64 kept, 1 rejected by the outlier check'."""
        models = ", ".join(f"{n} {model}" for model, n in graph.loop_models.items())
        return (
            f"{len(self.vertex_ids)} vertices, {len(graph.odometry_edges)} odometry edges, "
            f"{len(graph.loop_edges)} loop edges{f' ({models})' if models else ''}; "
            f"{self.iterations} iterations, "
            f"error {self.error_before:.6g} -> {self.error_after:.6g}; loop edges: "
            f"{self.loop_edges_kept} kept, {len(self.rejected_loop_edges)} rejected by the "
            f"outlier check; {self.calibration.summary()}"
        )


@dataclass(frozen=True)
class _Round:
    result: Any  # gtsam.Values
    iterations: int
    error_before: float
    error_after: float


def _optimize_once(gtsam_graph: GtsamGraph, options: OptimizeOptions) -> _Round:
    gtsam = import_gtsam()
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(options.max_iterations)
    optimizer = gtsam.LevenbergMarquardtOptimizer(gtsam_graph.graph, gtsam_graph.initial, params)
    result = optimizer.optimize()
    return _Round(
        result,
        int(optimizer.iterations()),
        float(gtsam_graph.graph.error(gtsam_graph.initial)),
        float(gtsam_graph.graph.error(result)),
    )


def squared_loop_errors(
    gtsam_graph: GtsamGraph,
    values: Any,
    loops: Sequence[Edge],
    odometry_covariances: F64 | None = None,
) -> F64:
    """Each loop edge's squared Mahalanobis error e^T C^-1 e at `values`, C its Gaussian
    covariance (the kernel left out): chi-square with 6 degrees of freedom for a right edge
    whose information is right. With `odometry_covariances` ((L, 6, 6), ROS order), C is the
    loop edge's covariance plus that of the odometry between its two vertices: a calibrated,
    stiff odometry leaves a right loop edge a residual that its own covariance alone does not
    explain."""
    errors = []
    for k, (factor_index, edge) in enumerate(zip(gtsam_graph.loop_factors, loops, strict=True)):
        residual = np.asarray(gtsam_graph.graph.at(factor_index).unwhitenedError(values))
        if odometry_covariances is None:
            errors.append(float(residual @ gtsam_information(edge.information) @ residual))
            continue
        # A rotation-only edge measures no translation: only the axes it measures are tested.
        axes = np.flatnonzero(np.diagonal(edge.information) > 0)
        covariance = np.linalg.inv(edge.information[np.ix_(axes, axes)])
        covariance += odometry_covariances[k][np.ix_(axes, axes)]
        ros = residual[_GTSAM_ORDER][axes]  # the same permutation both ways
        errors.append(float(ros @ np.linalg.solve(covariance, ros)))
    return np.asarray(errors, np.float64)


def optimize_pose_graph(graph: PoseGraph, options: OptimizeOptions | None = None) -> OptimizedGraph:
    """Levenberg-Marquardt on `graph` with the robust loop edges and the outlier check of
    `options` (module docstring). Raises UsageError without GTSAM."""
    options = options or OptimizeOptions()
    calibration = (
        calibrate_odometry(graph) if options.calibrate_odometry else OdometryCalibration(off=True)
    )
    graph = calibrated_graph(graph, calibration)
    chains = chain_covariances(graph, graph.loop_edges) if calibration.applied else None
    kept = list(range(len(graph.loop_edges)))
    iterations = rounds = 0
    while True:
        loops = [graph.loop_edges[i] for i in kept]
        gtsam_graph = to_gtsam(graph, options, loops)
        done = _optimize_once(gtsam_graph, options)
        iterations, rounds = iterations + done.iterations, rounds + 1
        if not options.outlier_check or rounds >= MAX_OUTLIER_ROUNDS:
            break
        squared = squared_loop_errors(
            gtsam_graph, done.result, loops, None if chains is None else chains[kept]
        )
        outliers = squared > options.outlier_bound
        if not outliers.any():
            break
        kept = [i for i, outlier in zip(kept, outliers, strict=True) if not outlier]
    positions, quaternions = _poses(done.result, gtsam_graph.keys)
    return OptimizedGraph(
        vertex_ids=graph.vertex_ids,
        positions=positions,
        quaternions_xyzw=quaternions,
        iterations=iterations,
        rounds=rounds,
        error_before=done.error_before,
        error_after=done.error_after,
        loop_edges_kept=len(kept),
        rejected_loop_edges=sorted(set(range(len(graph.loop_edges))) - set(kept)),
        calibration=calibration,
    )


def _poses(values: Any, keys: list[int]) -> tuple[F64, F64]:
    poses = [values.atPose3(key) for key in keys]
    positions = np.array([pose.translation() for pose in poses], np.float64).reshape(-1, 3)
    matrices = np.array([pose.rotation().matrix() for pose in poses], np.float64)
    quaternions = Rotation.from_matrix(matrices.reshape(-1, 3, 3)).as_quat()
    return positions, np.asarray(quaternions, np.float64)
