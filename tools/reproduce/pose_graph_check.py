"""The pose-graph round trip that tests/test_pose_graph.py asserts on and
tools/reproduce/pose_graph_table.py tabulates: annotate, export g2o, optimize with GTSAM, ATE.

The error is the ATE: RMSE of the vertex positions against the true poses at the same times,
after the best rigid alignment (rotation and translation, no scale; Umeyama), as `evo_ape`
computes it. Needs the `gtsam` extra.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.cli.main import main
from doseqslam_logs.export.base import ExportOptions, OptimizeOptions
from doseqslam_logs.export.gtsam_graph import optimize_pose_graph
from doseqslam_logs.export.loops import frame_times_ns
from doseqslam_logs.export.pose_graph import Edge, PoseGraph, build_pose_graph
from doseqslam_logs.sources.poses import read_poses
from loggen import make_sample_logs as gen

F64 = npt.NDArray[np.float64]


def generate_drifting_drive(folder: Path, seed: int = 29, depth: bool = False) -> Path:
    """A drive like drive_loops but another seed (29: odometry 4.4 m off at the end); with
    `depth`, an aligned depth topic too (make_sample_logs --depth), named drift{seed}depth."""
    name = f"drift{seed}depth" if depth else f"drift{seed}"
    return generate_drive(folder, name, seed, depth=depth)


def generate_drive(
    folder: Path, name: str, seed: int, route: gen.Route = "loops", **options: Any
) -> Path:
    """A drive of `route` at the samples' image settings (256x192 at 2 Hz, JPEG quality 70),
    120 s unless `options` (make_sample_logs.Config fields) say otherwise; its ROS 2 MCAP."""
    settings: dict[str, Any] = {"duration": 120.0, "rate": 2.0, **options}
    config = gen.Config(
        name=name, seed=seed, route=route, width=256, height=192, formats=("ros2mcap",),
        quality=70, noise_sigma=1.5, **settings,
    )  # fmt: skip
    gen.generate(config, folder, progress=False)
    return folder / f"{name}.ros2.mcap"


def annotate_and_export(log: Path, folder: Path) -> dict[str, Path]:
    """`annotate` with the command's defaults, then `export --format g2o --odometry-topic
    /odom`; the paths of both outputs."""
    annotated, g2o = folder / "annotated.mcap", folder / "graph.g2o"
    if main(["annotate", str(log), "-o", str(annotated)]) != 0:
        raise RuntimeError(f"annotate {log} failed")
    export = ["export", str(annotated), "--format", "g2o", "--odometry-topic", "/odom"]
    if main([*export, "-o", str(g2o)]) != 0:
        raise RuntimeError(f"export {annotated} failed")
    return {"annotated": annotated, "g2o": g2o}


def umeyama_rmse(estimate: F64, truth: F64) -> float:
    """RMSE of `estimate` against `truth` (both (N, 3)) after the best rigid alignment."""
    mean_e, mean_t = estimate.mean(axis=0), truth.mean(axis=0)
    u, _, vt = np.linalg.svd((estimate - mean_e).T @ (truth - mean_t))
    d = np.eye(3)
    d[2, 2] = np.sign(np.linalg.det(vt.T @ u.T))
    rotation = vt.T @ d @ u.T
    aligned = (estimate - mean_e) @ rotation.T + mean_t
    return float(np.sqrt(np.mean(np.sum((aligned - truth) ** 2, axis=1))))


@dataclass(frozen=True)
class Optimized:
    """A g2o graph before and after Levenberg-Marquardt, by vertex key."""

    keys: list[int]
    before: F64  # (N, 3) vertex positions
    after: F64
    graph: Any  # gtsam.NonlinearFactorGraph, with the prior


def optimize(g2o: Path) -> Optimized:
    """readG2o (3-D) + a tight prior on the first pose + Levenberg-Marquardt."""
    import gtsam

    graph, initial = gtsam.readG2o(str(g2o), True)
    keys = sorted(initial.keys())
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.full(6, 1e-6))
    graph.add(gtsam.PriorFactorPose3(keys[0], initial.atPose3(keys[0]), prior))
    result = gtsam.LevenbergMarquardtOptimizer(
        graph, initial, gtsam.LevenbergMarquardtParams()
    ).optimize()
    before = np.array([initial.atPose3(k).translation() for k in keys])
    after = np.array([result.atPose3(k).translation() for k in keys])
    return Optimized(keys, before, after, graph)


def trajectory_errors(paths: dict[str, Path]) -> tuple[float, float, Optimized]:
    """ATE before and after optimization against /ground_truth/pose, and the optimization."""
    optimized = optimize(paths["g2o"])
    log = read_annotations(paths["annotated"])
    truth = read_poses(paths["annotated"], "/ground_truth/pose")
    true_positions = truth.interpolate(frame_times_ns(log)[optimized.keys]).positions
    before = umeyama_rmse(optimized.before, true_positions)
    return before, umeyama_rmse(optimized.after, true_positions), optimized


def pose_graph_and_truth(annotated: Path) -> tuple[PoseGraph, F64]:
    """The export's pose graph of `annotated` (odometry /odom, default loop-edge model) and the
    true positions of its vertices (/ground_truth/pose)."""
    log = read_annotations(annotated)
    graph = build_pose_graph(log, ExportOptions(odometry_topic="/odom"))
    truth = read_poses(annotated, "/ground_truth/pose")
    return graph, truth.interpolate(frame_times_ns(log)[graph.vertex_ids]).positions


def robust_errors(
    graph: PoseGraph, truth: F64, options: OptimizeOptions | None = None
) -> tuple[float, int]:
    """ATE after `optimize_pose_graph` (the `optimize` command's optimization) and the loop
    edges its outlier check rejected."""
    optimized = optimize_pose_graph(graph, options)
    return umeyama_rmse(optimized.positions, truth), len(optimized.rejected_loop_edges)


def with_wrong_loops(graph: PoseGraph, truth: F64, count: int, seed: int = 0) -> PoseGraph:
    """`graph` plus `count` wrong loop edges: between random vertices more than 15 m apart in
    truth, with the loop-edge model of the first loop edge (zero translation, identity)."""
    rng = np.random.default_rng(seed)
    template = graph.loop_edges[0]
    wrong: list[Edge] = []
    while len(wrong) < count:
        a, b = sorted(rng.choice(len(graph.vertex_ids), 2, replace=False))
        if np.linalg.norm(truth[a] - truth[b]) > 15.0:
            query, match = int(graph.vertex_ids[b]), int(graph.vertex_ids[a])
            identity = np.array([0.0, 0.0, 0.0, 1.0])
            wrong.append(
                dataclasses.replace(template, from_id=query, to_id=match, quaternion_xyzw=identity)
            )
    return dataclasses.replace(graph, loop_edges=[*graph.loop_edges, *wrong])
