#!/usr/bin/env python3
"""The pose-graph table of docs/export.md: annotate, export g2o, optimize with GTSAM, ATE.

For the three generated drifting drives (seeds 29, 2, 20, made like the test's) and the three
committed sample drives: annotate with the command's defaults, export `--format g2o
--odometry-topic /odom`, then the round trip tests/test_pose_graph.py asserts on
(tools/reproduce/pose_graph_check.py: readG2o, a tight prior on the first pose,
Levenberg-Marquardt, ATE after rigid alignment against /ground_truth/pose: plain least
squares), and the `optimize` command's optimization of the same graph (robust loop edges,
outlier check; ATE and loop edges rejected). A second table injects `--wrong N` wrong loop
edges (random vertex pairs more than 15 m apart) into each graph and compares plain least
squares, each kernel alone, and each kernel with the outlier check. Needs the `gtsam` extra. A
few minutes.

`--metric` prints the table of issue #20 instead: for the same drives plus a drifting drive
with an aligned depth topic (`--depth`), each loop-edge model's error against the true
relative pose (the edge's measurement: the match's body pose in the query's frame) and the ATE
after the `optimize` command's optimization of the odometry alone, the placeholder model, the
metric model, and an oracle graph whose loop edges are the true relative poses (with the
metric model's information).

`--odometry-weights` prints how the ATE of the metric and the oracle graphs depends on the
odometry edges' information: each odometry edge's covariance (the /odom messages' pose
covariance per frame spanned) multiplied by each factor, on the calibration drives (seeds 5, 7,
13, 17), the table's drifting drives and the committed samples (docs/export.md, "How much the
odometry edges weigh"); the odometry as stated, not calibrated.

`--calibration` prints the odometry calibration's table (docs/export.md, "The odometry
calibrated from the loop edges"): on the calibration drives (seeds 5, 7, 13, 17, 3, 23, 31,
37), the table's drifting drives, drives of other seeds, routes and lengths, and the committed
samples, the ATE of the metric and the oracle graphs with the odometry as stated and
calibrated, the loop edges the outlier check rejected, and the bias and scale found.

    python -m reproduce.pose_graph_table [--wrong 5]
    python -m reproduce.pose_graph_table --metric
    python -m reproduce.pose_graph_table --odometry-weights
    python -m reproduce.pose_graph_table --calibration
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from doseqslam_logs.annotations.reader import AnnotatedLog, read_annotations
from doseqslam_logs.cli.main import main as cli_main
from doseqslam_logs.export.base import ExportOptions, OptimizeOptions
from doseqslam_logs.export.gtsam_graph import optimize_pose_graph
from doseqslam_logs.export.loops import frame_times_ns
from doseqslam_logs.export.pose_graph import Edge, PoseGraph, build_pose_graph, relative_pose
from doseqslam_logs.sources.poses import PoseTrack, read_poses
from loggen import make_sample_logs as gen
from reproduce import pose_graph_check as check

ROOT = Path(__file__).resolve().parents[2]

SAMPLES = ROOT / "sample_logs"
COMMITTED = [
    ("drive_loops (committed)", SAMPLES / "drive_loops.ros2.mcap"),
    ("drive_parked (committed)", SAMPLES / "drive_parked.ros2.mcap"),
    ("drive_varrate (committed)", SAMPLES / "drive_varrate.bag"),
]


# The second table's optimizations: least squares, each kernel alone, each with the check.
INJECTED = {
    "least squares": OptimizeOptions(loop_kernel="none", outlier_check=False),
    "check only": OptimizeOptions(loop_kernel="none"),
    "Huber": OptimizeOptions(loop_kernel="huber", outlier_check=False),
    "Cauchy": OptimizeOptions(loop_kernel="cauchy", outlier_check=False),
    "Huber + check": OptimizeOptions(loop_kernel="huber"),
    "Cauchy + check (default)": OptimizeOptions(),
}


def oracle_edges(graph: PoseGraph, truth: PoseTrack) -> list[Edge]:
    """The graph's loop edges with the true relative pose as their measurement."""
    index = {int(v): k for k, v in enumerate(graph.vertex_ids)}
    edges = []
    for edge in graph.loop_edges:
        i, j = index[edge.from_id], index[edge.to_id]
        t, q = relative_pose(
            truth.positions[i],
            truth.quaternions_xyzw[i],
            truth.positions[j],
            truth.quaternions_xyzw[j],
        )
        edges.append(dataclasses.replace(edge, translation=t, quaternion_xyzw=q))
    return edges


def edge_errors(edges: Sequence[Edge], oracle: Sequence[Edge]) -> tuple[list[float], list[float]]:
    """Translation (m; not for rotation-only edges) and rotation (deg) errors of each edge."""
    translation, rotation = [], []
    for edge, true in zip(edges, oracle, strict=True):
        turn = Rotation.from_quat(true.quaternion_xyzw).inv() * Rotation.from_quat(
            edge.quaternion_xyzw
        )
        rotation.append(float(np.degrees(turn.magnitude())))
        if edge.model != "rotation_only":
            translation.append(float(np.linalg.norm(edge.translation - true.translation)))
    return translation, rotation


def _stats(values: Sequence[float], digits: int) -> str:
    if not values:
        return "-"
    return f"{np.median(values):.{digits}f} / {np.percentile(values, 95):.{digits}f}"


def metric_graph_and_truth(annotated: Path) -> tuple[AnnotatedLog, PoseGraph, PoseTrack]:
    """The annotated drive, its pose graph with the metric model (/odom) and
    /ground_truth/pose at the graph's vertices."""
    log = read_annotations(annotated)
    graph = build_pose_graph(log, ExportOptions(odometry_topic="/odom", loop_model="metric"))
    truth = read_poses(annotated, "/ground_truth/pose")
    return log, graph, truth.interpolate(frame_times_ns(log)[graph.vertex_ids])


def annotated_drives(root: Path, drives: Sequence[tuple[str, Path]]) -> Iterator[tuple[str, Path]]:
    """Each (name, log) annotated with the command's defaults into `root`, as it is done."""
    for k, (name, log) in enumerate(drives):
        annotated = root / f"annotated{k}.mcap"
        if cli_main(["annotate", str(log), "-o", str(annotated)]) != 0:
            raise RuntimeError(f"annotate {log} failed")
        yield name, annotated


def metric_row(name: str, annotated: Path) -> str:
    """One drive's row of the --metric table."""
    log, metric, truth = metric_graph_and_truth(annotated)
    placeholder = ExportOptions(odometry_topic="/odom", loop_model="placeholder")
    graphs = {"placeholder": build_pose_graph(log, placeholder), "metric": metric}
    oracle = oracle_edges(metric, truth)
    cells = []
    for graph in graphs.values():
        t, r = edge_errors(graph.loop_edges, oracle)
        cells += [_stats(t, 3), _stats(r, 2)]
    ate = {"odometry": check.umeyama_rmse(metric.poses.positions, truth.positions)}
    for model, graph in [
        *graphs.items(),
        ("oracle", dataclasses.replace(metric, loop_edges=oracle)),
    ]:
        ate[model] = check.umeyama_rmse(optimize_pose_graph(graph).positions, truth.positions)
    models = ", ".join(f"{n} {m}" for m, n in metric.loop_models.items())
    return (
        f"| {name} | {models} | "
        + " | ".join(cells)
        + " | "
        + " | ".join(f"{ate[k]:.3f}" for k in ("odometry", "placeholder", "metric", "oracle"))
        + f" | {ate['metric'] / ate['oracle']:.2f} |"
    )


def metric_table() -> None:
    print(
        "| drive | loop edges (metric model) | placeholder t err, m | placeholder r err, deg "
        "| metric t err, m | metric r err, deg | ATE odometry | ATE placeholder | ATE metric "
        "| ATE oracle | metric / oracle |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as scratch:
        root = Path(scratch)
        drifting = [(f"seed {s}", check.generate_drifting_drive(root, s)) for s in (29, 2, 20)]
        depth = [("seed 29 with depth", check.generate_drifting_drive(root, 29, depth=True))]
        for name, annotated in annotated_drives(root, drifting + depth + COMMITTED):
            print(metric_row(name, annotated), flush=True)


# Factors on the odometry edges' covariance (translation, rotation) of --odometry-weights.
ODOMETRY_FACTORS = ((1.0, 1.0), (0.1, 0.1), (0.01, 0.01), (0.01, 0.001), (0.001, 0.001))


def scaled_odometry(graph: PoseGraph, translation: float, rotation: float) -> PoseGraph:
    """The graph with each odometry edge's covariance multiplied by `translation` on x, y, z
    and `rotation` on the three rotation axes."""
    root = np.sqrt(np.array([translation] * 3 + [rotation] * 3))
    edges = [
        dataclasses.replace(edge, information=edge.information / np.outer(root, root))
        for edge in graph.odometry_edges
    ]
    return dataclasses.replace(graph, odometry_edges=edges)


def odometry_weight_row(name: str, annotated: Path) -> str:
    """ATE of the metric and the oracle graph (and their ratio) at each ODOMETRY_FACTORS."""
    _, metric, truth = metric_graph_and_truth(annotated)
    oracle = dataclasses.replace(metric, loop_edges=oracle_edges(metric, truth))
    cells = [f"{check.umeyama_rmse(metric.poses.positions, truth.positions):.3f}"]
    stated = OptimizeOptions(calibrate_odometry=False)
    for translation, rotation in ODOMETRY_FACTORS:
        ate = [
            check.umeyama_rmse(
                optimize_pose_graph(scaled_odometry(g, translation, rotation), stated).positions,
                truth.positions,
            )
            for g in (metric, oracle)
        ]
        cells.append(f"{ate[0]:.3f} / {ate[1]:.3f} ({ate[0] / ate[1]:.2f})")
    return f"| {name} | " + " | ".join(cells) + " |"


def odometry_weight_table() -> None:
    factors = " | ".join(f"x {t:g} / {r:g}" for t, r in ODOMETRY_FACTORS)
    print(f"| drive | ATE odometry | {factors} |")
    print("|---|---:|" + "---:|" * len(ODOMETRY_FACTORS))
    with tempfile.TemporaryDirectory() as scratch:
        root = Path(scratch)
        seeds = [(f"seed {s} (calibration)", s) for s in (5, 7, 13, 17)]
        seeds += [(f"seed {s}", s) for s in (29, 2, 20)]
        drives = [(name, check.generate_drifting_drive(root, s)) for name, s in seeds]
        for name, annotated in annotated_drives(root, drives + COMMITTED):
            print(odometry_weight_row(name, annotated), flush=True)


# Drives of other seeds, routes and lengths than the calibration's (seed, route, options).
OTHER_DRIVES: tuple[tuple[int, gen.Route, dict[str, float | bool]], ...] = (
    (41, "loops", {}),
    (43, "loops", {}),
    (47, "loops", {}),
    (61, "outandback", {"variable_rate": True, "drop_frames": 4}),
    (67, "outandback", {"variable_rate": True}),
    (71, "loops", {"duration": 300.0}),
    (123, "outandback", {"variable_rate": True}),
    (125, "outandback", {"variable_rate": True}),
    (131, "figure8", {"duration": 240.0}),
    (133, "figure8", {"duration": 240.0}),
)


def calibration_row(name: str, annotated: Path) -> str:
    """ATE of the metric and oracle graphs, odometry as stated and calibrated."""
    _, metric, truth = metric_graph_and_truth(annotated)
    oracle = dataclasses.replace(metric, loop_edges=oracle_edges(metric, truth))
    cells = [", ".join(f"{n} {m}" for m, n in metric.loop_models.items()) or "none"]
    cells.append(f"{check.umeyama_rmse(metric.poses.positions, truth.positions):.3f}")
    for options in (OptimizeOptions(calibrate_odometry=False), OptimizeOptions()):
        found = optimize_pose_graph(metric, options)
        ate = check.umeyama_rmse(found.positions, truth.positions)
        best = check.umeyama_rmse(optimize_pose_graph(oracle, options).positions, truth.positions)
        cells.append(f"{ate:.3f} / {best:.3f} ({ate / best:.2f})")
    calibration = found.calibration
    cells.append(f"{len(found.rejected_loop_edges)}")
    if calibration.applied:
        cells.append(f"{np.degrees(calibration.yaw_rate_bias):+.3f}")
        cells.append(f"{100 * calibration.yaw_scale:+.2f}" if calibration.yaw_scale else "-")
        cells.append(f"{calibration.covariance_scale:.2g}")
    else:
        cells += ["-", "-", "-"]
    return f"| {name} | " + " | ".join(cells) + " |"


def calibration_table() -> None:
    print(
        "| drive | loop edges | ATE odometry | as stated: metric / oracle | calibrated: metric "
        "/ oracle | rejected | bias, deg/s | yaw scale, % | covariance x |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as scratch:
        root = Path(scratch)
        seeds = [(f"seed {s} (calibration)", s) for s in (5, 7, 13, 17, 3, 23, 31, 37)]
        seeds += [(f"seed {s}", s) for s in (29, 2, 20)]
        drives = [(name, check.generate_drifting_drive(root, s)) for name, s in seeds]
        for seed, route, options in OTHER_DRIVES:
            label = " ".join([f"seed {seed} {route}", *(f"{k}={v}" for k, v in options.items())])
            drives.append(
                (label, check.generate_drive(root, f"{route}{seed}", seed, route, **options))
            )
        for name, annotated in annotated_drives(root, drives + COMMITTED):
            print(calibration_row(name, annotated), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--wrong", type=int, default=5, help="wrong loop edges to inject")
    parser.add_argument("--metric", action="store_true", help="issue #20's table instead")
    parser.add_argument(
        "--odometry-weights", action="store_true", help="ATE against the odometry's weight"
    )
    parser.add_argument(
        "--calibration", action="store_true", help="ATE with the odometry as stated and calibrated"
    )
    args = parser.parse_args()
    if args.calibration:
        calibration_table()
        return
    if args.metric:
        metric_table()
        return
    if args.odometry_weights:
        odometry_weight_table()
        return
    graphs = []
    with tempfile.TemporaryDirectory() as scratch:
        root = Path(scratch)
        drifting = [(f"seed {s}", check.generate_drifting_drive(root, s)) for s in (29, 2, 20)]
        logs = drifting + COMMITTED
        print(
            "| drive | loop edges | ATE before | ATE after | factor "
            "| `optimize` ATE | factor | rejected |"
        )
        print("|---|---:|---:|---:|---:|---:|---:|---:|")
        for name, log in logs:
            folder = root / f"out{len(list(root.iterdir()))}"
            folder.mkdir()
            paths = check.annotate_and_export(log, folder)
            before, after, _ = check.trajectory_errors(paths)
            edges = len(read_annotations(paths["annotated"]).reported_loop_closures)
            graph, truth = check.pose_graph_and_truth(paths["annotated"])
            robust, rejected = check.robust_errors(graph, truth)
            graphs.append((name, graph, truth))
            row = (
                f"| {name} | {edges} | {before:.3f} m | {after:.3f} m | {before / after:.2f} "
                f"| {robust:.3f} m | {before / robust:.2f} | {rejected} |"
            )
            print(row, flush=True)
    print(f"\nWith {args.wrong} wrong loop edges injected: ATE (m), wrong edges rejected\n")
    print("| drive | " + " | ".join(INJECTED) + " |")
    print("|---|" + "---:|" * len(INJECTED))
    for name, graph, truth in graphs:
        wrong = check.with_wrong_loops(graph, truth, args.wrong)
        cells = []
        for options in INJECTED.values():
            ate, rejected = check.robust_errors(wrong, truth, options)
            cells.append(f"{ate:.3f}" + (f" ({rejected})" if options.outlier_check else ""))
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
