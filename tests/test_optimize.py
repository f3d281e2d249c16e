"""`doseqslam-logs optimize`: the GTSAM form of the pose graph, the robust optimization with its
outlier check, and the optimized trajectory written back into the log (docs/export.md,
"Optimizing the pose graph").

The drifting drive is tests/test_pose_graph.py's (seed 29, odometry 4.4 m off at the end);
the ATE is tools/reproduce/pose_graph_check.py's (rigid alignment, as evo_ape --align).
"""

from __future__ import annotations

import dataclasses
import json
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.cli.main import main
from doseqslam_logs.export.base import (
    ODOMETRY_PATH_TOPIC,
    OPTIMIZED_PATH_TOPIC,
    OPTIMIZED_POSE_TOPIC,
    ExportOptions,
    OptimizeOptions,
)
from doseqslam_logs.export.gtsam_graph import gtsam_information, optimize_pose_graph, to_gtsam
from doseqslam_logs.export.loops import frame_times_ns
from doseqslam_logs.export.pose_graph import Edge, PoseGraph, build_pose_graph
from doseqslam_logs.sources import open_source
from doseqslam_logs.sources.poses import PoseTrack, read_poses
from reproduce import pose_graph_check as check

gtsam = pytest.importorskip("gtsam")

REPO = Path(__file__).resolve().parents[1]

SAMPLES = REPO / "sample_logs"
IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])
PLAIN_LEAST_SQUARES = OptimizeOptions(loop_kernel="none", outlier_check=False)


# -- the information order ------------------------------------------------------------------


@given(arrays(np.float64, (6, 6), elements=st.floats(-1e3, 1e3)))
def test_gtsam_information_swaps_the_translation_and_rotation_blocks(matrix: Any) -> None:
    reordered = gtsam_information(matrix)
    np.testing.assert_array_equal(reordered[:3, :3], matrix[3:, 3:])  # rotation, rotation
    np.testing.assert_array_equal(reordered[3:, 3:], matrix[:3, :3])  # translation, translation
    np.testing.assert_array_equal(reordered[:3, 3:], matrix[3:, :3])  # rotation, translation
    np.testing.assert_array_equal(gtsam_information(reordered), matrix)


def _track(positions: list[list[float]]) -> PoseTrack:
    count = len(positions)
    return PoseTrack(
        "/odom",
        np.arange(count, dtype=np.int64),
        np.asarray(positions, np.float64),
        np.tile(IDENTITY, (count, 1)),
        None,
    )


def _edge(kind: Any, a: int, b: int, translation: list[float], information: Any) -> Edge:
    return Edge(kind, a, b, np.asarray(translation, np.float64), IDENTITY, information)


# Odometry that is sure of x and of the heading, unsure of y and of roll and pitch (ROS order:
# x, y, z, rot x, rot y, rot z); one loop edge that disagrees with it in x and y.
ODOMETRY_SIGMAS_ROS = np.array([0.01, 0.5, 0.05, 0.3, 0.3, 0.002])
LOOP_SIGMAS_ROS = np.array([0.2, 0.2, 0.2, 0.05, 0.05, 0.05])


def _anisotropic_graph() -> PoseGraph:
    information = np.diag(1.0 / ODOMETRY_SIGMAS_ROS**2)
    odometry = [_edge("odometry", k, k + 1, [1.0, 0.0, 0.0], information) for k in range(3)]
    loop = _edge("loop", 0, 3, [2.5, 0.8, 0.0], np.diag(1.0 / LOOP_SIGMAS_ROS**2))
    poses = _track([[float(k), 0.0, 0.0] for k in range(4)])
    return PoseGraph(np.arange(4, dtype=np.int64), poses, odometry, [loop], 0, 0, 0)


def _hand_built(graph: PoseGraph, odometry_sigmas: Any, loop_sigmas: Any) -> Any:
    """The same graph written straight in GTSAM, its sigmas given in the order passed."""
    factors, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k in range(4):
        initial.insert(k, gtsam.Pose3(gtsam.Rot3(), np.array([float(k), 0.0, 0.0])))
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.full(6, 1e-6))
    factors.add(gtsam.PriorFactorPose3(0, initial.atPose3(0), prior))
    for edge in graph.odometry_edges + graph.loop_edges:
        sigmas = odometry_sigmas if edge.kind == "odometry" else loop_sigmas
        measured = gtsam.Pose3(gtsam.Rot3(), edge.translation)
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, np.float64))
        factors.add(gtsam.BetweenFactorPose3(edge.from_id, edge.to_id, measured, noise))
    result = gtsam.LevenbergMarquardtOptimizer(factors, initial).optimize()
    return np.array([result.atPose3(k).translation() for k in range(4)])


def test_anisotropic_information_gives_the_hand_built_gtsam_answer() -> None:
    graph = _anisotropic_graph()
    ours = optimize_pose_graph(graph, PLAIN_LEAST_SQUARES).positions
    # GTSAM's tangent: rotation first, then translation.
    gtsam_order = _hand_built(
        graph,
        [*ODOMETRY_SIGMAS_ROS[3:], *ODOMETRY_SIGMAS_ROS[:3]],
        [*LOOP_SIGMAS_ROS[3:], *LOOP_SIGMAS_ROS[:3]],
    )
    np.testing.assert_allclose(ours, gtsam_order, atol=1e-6)
    # The graph is sensitive to the order: the ROS order passed unchanged is another answer.
    unconverted = _hand_built(graph, ODOMETRY_SIGMAS_ROS, LOOP_SIGMAS_ROS)
    assert np.abs(unconverted - gtsam_order).max() > 0.05
    # x is sure and y is not: the loop's pull goes into y.
    assert abs(ours[3, 0] - 3.0) < 0.05 and ours[3, 1] > 0.3


def test_the_gtsam_form_holds_a_prior_every_edge_and_robust_loop_edges() -> None:
    graph = _anisotropic_graph()
    form = to_gtsam(graph)
    assert form.keys == [0, 1, 2, 3]
    assert form.graph.size() == 1 + 3 + 1  # prior, odometry, loop
    assert form.loop_factors == [4]
    loop_noise = form.graph.at(4).noiseModel()
    assert isinstance(loop_noise, gtsam.noiseModel.Robust)
    assert not isinstance(form.graph.at(1).noiseModel(), gtsam.noiseModel.Robust)


def test_without_gtsam_the_command_names_the_extra(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    monkeypatch.setitem(sys.modules, "gtsam", None)  # import gtsam raises ImportError
    log = SAMPLES / "drive_loops.ros2.mcap"
    code = main(["optimize", str(log), "--odometry-topic", "/odom", "-o", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1
    assert "pip install 'doseqslam-logs[gtsam]'" in err
    assert not (tmp_path / "o").exists()


# -- a drifting drive -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def drifting(annotated_drifting_drive: Path) -> Path:
    return annotated_drifting_drive  # the run's shared annotation (conftest)


def _truth_at_vertices(annotated: Path, graph: PoseGraph) -> Any:
    times = frame_times_ns(read_annotations(annotated))[graph.vertex_ids]
    return read_poses(annotated, "/ground_truth/pose").interpolate(times).positions


@pytest.mark.slow
def test_optimize_brings_the_drifting_drive_closer_to_the_truth(
    drifting: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "optimized.mcap"
    capsys.readouterr()
    assert main(["optimize", str(drifting), "--odometry-topic", "/odom", "-o", str(out)]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"{out}: 240 vertices, 239 odometry edges, ")
    assert "rejected by the outlier check" in line
    with open_source(out) as source:
        types = {c.topic: c.message_type for c in source.channels()}
        messages = list(source.messages(OPTIMIZED_POSE_TOPIC))
        odometry_frame = next(iter(source.messages("/odom"))).message.header.frame_id
    assert types[OPTIMIZED_POSE_TOPIC] == "geometry_msgs/msg/PoseStamped"
    assert len(messages) == 240
    assert {m.message.header.frame_id for m in messages} == {odometry_frame}
    optimized = np.array([[getattr(m.message.pose.position, a) for a in "xyz"] for m in messages])
    stamps = [m.message.header.stamp.sec * 10**9 + m.message.header.stamp.nanosec for m in messages]
    log = read_annotations(drifting)
    np.testing.assert_array_equal(stamps, frame_times_ns(log))  # at the vertices' times
    truth = read_poses(drifting, "/ground_truth/pose").interpolate(stamps).positions
    odometry = read_poses(drifting, "/odom").interpolate(stamps).positions
    before = check.umeyama_rmse(odometry, truth)
    after = check.umeyama_rmse(optimized, truth)
    print(f"seed-29 drive, optimize: ATE {before:.3f} m -> {after:.3f} m")
    assert before > 0.8
    assert after < before / 2.5
    # Every input record is still there, and the annotations read back the same.
    with open_source(drifting) as source:
        counts = {c.topic: c.message_count for c in source.channels()}
    with open_source(out) as source:
        out_counts = {c.topic: c.message_count for c in source.channels()}
    paths = dict.fromkeys([OPTIMIZED_PATH_TOPIC, ODOMETRY_PATH_TOPIC], 1)
    assert out_counts == {**counts, OPTIMIZED_POSE_TOPIC: 240, **paths}
    assert repr(read_annotations(out).loop_closures) == repr(log.loop_closures)  # NaN != NaN


def _far_apart_edge(graph: PoseGraph, truth: Any, template: Edge | None = None) -> Edge:
    """A loop edge between two frames at least 20 m apart: a wrong loop closure (with the
    information of `template`, default the first loop edge)."""
    distances = np.linalg.norm(truth[:, None, :] - truth[None, :, :], axis=2)
    far = np.argwhere(distances > 20.0)
    a, b = far[len(far) // 2]
    template = template or graph.loop_edges[0]
    query, match = int(graph.vertex_ids[max(a, b)]), int(graph.vertex_ids[min(a, b)])
    return dataclasses.replace(template, from_id=query, to_id=match, quaternion_xyzw=IDENTITY)


@pytest.mark.slow
def test_one_wrong_loop_edge_is_rejected_and_does_not_bend_the_trajectory(
    drifting: Path,
) -> None:
    # The placeholder model, with which the kernel and the check were chosen (with the metric
    # model the check also drops 3 of the 65 right edges whose stated covariance is too small
    # for their error: docs/export.md; see the test below).
    options = ExportOptions(odometry_topic="/odom", loop_model="placeholder")
    graph = build_pose_graph(read_annotations(drifting), options)
    truth = _truth_at_vertices(drifting, graph)
    wrong = dataclasses.replace(
        graph, loop_edges=[*graph.loop_edges, _far_apart_edge(graph, truth)]
    )

    def ate(pose_graph: PoseGraph, options: OptimizeOptions) -> tuple[float, list[int]]:
        optimized = optimize_pose_graph(pose_graph, options)
        return check.umeyama_rmse(optimized.positions, truth), optimized.rejected_loop_edges

    clean, rejected_clean = ate(graph, OptimizeOptions())
    robust, rejected = ate(wrong, OptimizeOptions())
    plain_clean, _ = ate(graph, PLAIN_LEAST_SQUARES)
    plain, _ = ate(wrong, PLAIN_LEAST_SQUARES)
    print(f"one wrong loop edge: ATE {clean:.3f} -> {robust:.3f} m")
    print(f"plain least squares: ATE {plain_clean:.3f} -> {plain:.3f} m")
    assert rejected_clean == []  # no right loop edge is rejected
    assert rejected == [len(graph.loop_edges)]  # the wrong one, and only it
    assert robust <= 1.2 * clean
    assert plain > 3 * plain_clean  # least squares bends to it
    summary = optimize_pose_graph(wrong).summary(wrong)
    assert f"{len(graph.loop_edges)} kept, 1 rejected by the outlier check;" in summary


# -- the odometry calibrated from the metric loop edges ---------------------------------------


@pytest.mark.slow
def test_the_calibrated_odometry_brings_the_metric_graph_near_the_oracle(
    drifting: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue #20's target on the seed-29 drive: the ATE with the metric loop edges within 1.5x
    of the oracle graph's (the same graph, its loop edges the true relative poses). Measured:
    0.094 against 0.092 m calibrated; 0.146 against 0.077 m (1.91) with the /odom covariance
    as stated and no bias (docs/export.md). Since the best-split bracketing (c597829) the
    metric edges leave less to calibrate: 0.096 / 0.095 m calibrated, 0.101 to 0.117 m as
    stated depending on the machine (GTSAM's floating-point kernels): calibration takes 5 to
    18 % off, and never adds."""
    from reproduce.pose_graph_table import metric_graph_and_truth, oracle_edges

    _, graph, truth = metric_graph_and_truth(drifting)
    oracle = dataclasses.replace(graph, loop_edges=oracle_edges(graph, truth))
    stated = OptimizeOptions(calibrate_odometry=False)

    def ate(pose_graph: PoseGraph, options: OptimizeOptions | None = None) -> float:
        return check.umeyama_rmse(
            optimize_pose_graph(pose_graph, options).positions, truth.positions
        )

    calibrated, uncalibrated = ate(graph), ate(graph, stated)
    print(f"seed 29: metric {calibrated:.3f} / oracle {ate(oracle):.3f} m calibrated; "
          f"{uncalibrated:.3f} / {ate(oracle, stated):.3f} m as stated")  # fmt: skip
    assert calibrated <= 1.5 * ate(oracle)
    assert calibrated < uncalibrated
    result = optimize_pose_graph(graph)
    assert result.calibration.applied
    assert np.degrees(abs(result.calibration.yaw_rate_bias)) > 0.05  # the drive's drift
    # The command: the calibration in its summary and --json, and the switch that turns it off.
    out = tmp_path / "o.mcap"
    args = ["optimize", str(drifting), "--odometry-topic", "/odom", "-o", str(out), "--json"]
    capsys.readouterr()
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out)["odometry_calibration"]
    assert (
        summary["applied"] and summary["metric_loop_edges"] == result.calibration.metric_loop_edges
    )
    assert summary["yaw_rate_bias_deg_s"] == pytest.approx(
        np.degrees(result.calibration.yaw_rate_bias)
    )
    assert main([*args[:-1], "--no-odometry-calibration"]) == 0
    assert capsys.readouterr().out.strip().endswith("; odometry as stated (calibration off)")


@pytest.mark.slow
def test_the_g2o_export_carries_the_calibrated_odometry_on_request(
    drifting: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """export --format g2o --calibrate-odometry: the graph optimize builds, for another
    optimizer; plain least squares on it (gtsam.readG2o) beats the odometry as stated
    (measured 0.087 against 0.102 m, 15 % off: the edges since c597829 are better as stated)."""
    ate = {}
    for name, extra in (("stated", []), ("calibrated", ["--calibrate-odometry"])):
        g2o = tmp_path / f"{name}.g2o"
        args = ["export", str(drifting), "--format", "g2o", "--odometry-topic", "/odom"]
        assert main([*args, *extra, "-o", str(g2o)]) == 0
        summary = capsys.readouterr().err
        comments = [line for line in g2o.read_text().splitlines() if line.startswith("#")]
        calibrated = [line for line in comments if line.startswith("# odometry edges: ")]
        optimized = check.optimize(g2o)
        times = frame_times_ns(read_annotations(drifting))[optimized.keys]
        truth = read_poses(drifting, "/ground_truth/pose").interpolate(times).positions
        ate[name] = check.umeyama_rmse(optimized.after, truth)
        if name == "stated":
            assert not calibrated and "odometry calibrated" not in summary
        else:
            assert calibrated[0].startswith("# odometry edges: odometry calibrated on ")
            assert re.search(r"; odometry calibrated on \d+ metric loop edges: yaw-rate", summary)
    print(f"seed 29, g2o round trip: ATE {ate['stated']:.3f} m as stated, "
          f"{ate['calibrated']:.3f} m calibrated")  # fmt: skip
    assert ate["calibrated"] < 0.9 * ate["stated"]


# -- other profiles and the errors ----------------------------------------------------------


@pytest.mark.slow
def test_a_wrong_metric_loop_edge_is_rejected_too(drifting: Path) -> None:
    """With the metric model (the default), a wrong edge carrying a metric edge's information
    is rejected and leaves the trajectory as it was."""
    graph = build_pose_graph(read_annotations(drifting), ExportOptions(odometry_topic="/odom"))
    truth = _truth_at_vertices(drifting, graph)
    template = next(e for e in graph.loop_edges if e.model == "odometry_pnp")
    wrong_edge = _far_apart_edge(graph, truth, template)
    wrong = dataclasses.replace(graph, loop_edges=[*graph.loop_edges, wrong_edge])
    clean = optimize_pose_graph(graph)
    robust = optimize_pose_graph(wrong)
    assert len(graph.loop_edges) in robust.rejected_loop_edges
    before = check.umeyama_rmse(clean.positions, truth)
    after = check.umeyama_rmse(robust.positions, truth)
    assert after <= 1.2 * before


@pytest.fixture(scope="module")
def unverified(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """drive_loops annotated without verification (fast), as Foxglove protobuf, ROS 1 and
    ROS 2, and a ROS 2 sidecar."""
    folder = tmp_path_factory.mktemp("profiles")
    logs = {
        "foxglove": "drive_loops.foxglove.mcap",
        "ros1": "drive_loops.bag",
        "ros2": "drive_loops.ros2.mcap",
    }
    annotated = {}
    for name, log in logs.items():
        annotated[name] = folder / f"{name}.annotated.mcap"
        args = [str(SAMPLES / log), "-o", str(annotated[name]), "--no-verify"]
        assert main(["annotate", *args]) == 0
    annotated["sidecar"] = folder / "sidecar.mcap"
    args = [str(SAMPLES / "drive_loops.ros2.mcap"), "-o", str(annotated["sidecar"])]
    assert main(["annotate", *args, "--no-verify", "--sidecar"]) == 0
    return annotated


@pytest.mark.slow
@pytest.mark.parametrize(
    ("profile", "message_type"),
    [("foxglove", "foxglove.PoseInFrame"), ("ros1", "geometry_msgs/PoseStamped")],
)
def test_the_poses_take_the_type_of_the_logs_profile(
    unverified: dict[str, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    profile: str,
    message_type: str,
) -> None:
    out = tmp_path / "optimized.mcap"
    args = [str(unverified[profile]), "--odometry-topic", "/odom", "-o", str(out), "--json"]
    capsys.readouterr()
    assert main(["optimize", *args]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["vertices"] == 240 and summary["topic"] == OPTIMIZED_POSE_TOPIC
    with open_source(out) as source:
        channel = next(c for c in source.channels() if c.topic == OPTIMIZED_POSE_TOPIC)
        odometry = next(c for c in source.channels() if c.topic == "/odom")
    assert channel.message_type == message_type
    assert channel.message_encoding == odometry.message_encoding  # protobuf, ros1
    poses = read_poses(out, OPTIMIZED_POSE_TOPIC)
    assert len(poses) == 240
    assert summary["frame_id"] == "odom"


def _path_messages(path: Path) -> dict[str, Any]:
    """Each path topic's one message: its log time, schema, channel and decoded message (the
    mcap ROS 2 decoder, rosbags for ROS 1, the protobuf decoder); and the file's first log
    time."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoders
    from mcap_ros2.decoder import DecoderFactory as Ros2Decoders
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    found: dict[str, Any] = {}
    with path.open("rb") as stream:
        reader = make_reader(stream)
        first = min(m.log_time for _, _, m in reader.iter_messages())
        for schema, channel, message in reader.iter_messages(topics=PATH_TOPICS):
            assert channel.topic not in found  # one message a path
            if channel.message_encoding == "ros1":
                store = get_typestore(Stores.EMPTY)
                store.register(get_types_from_msg(schema.data.decode(), "nav_msgs/msg/Path"))
                decoded = store.deserialize_ros1(message.data, "nav_msgs/msg/Path")
            else:
                ros2 = channel.message_encoding == "cdr"
                factory = Ros2Decoders() if ros2 else ProtobufDecoders()
                decoder = factory.decoder_for(channel.message_encoding, schema)
                assert decoder is not None
                decoded = decoder(message.data)
            found[channel.topic] = (message.log_time, schema, channel, decoded)
    return {"first_log_time": first, "paths": found}


PATH_TOPICS = [OPTIMIZED_PATH_TOPIC, ODOMETRY_PATH_TOPIC]


def _path_arrays(message: Any) -> tuple[Any, Any, Any]:
    """Stamps (ns; None for PosesInFrame, whose poses have none), positions, quaternions."""
    poses = [getattr(p, "pose", p) for p in message.poses]
    positions = np.array([[p.position.x, p.position.y, p.position.z] for p in poses])
    quaternions = np.array([[getattr(p.orientation, a) for a in "xyzw"] for p in poses])
    stamps = None
    if message.poses and hasattr(message.poses[0], "header"):
        stamps = np.array([p.header.stamp.sec * 10**9 + p.header.stamp.nanosec
                           for p in message.poses])  # fmt: skip
    return stamps, positions, quaternions


@pytest.mark.slow
@pytest.mark.parametrize(
    ("profile", "path_type", "schema_encoding"),
    [
        ("ros2", "nav_msgs/msg/Path", "ros2msg"),
        ("ros1", "nav_msgs/Path", "ros1msg"),
        ("foxglove", "foxglove.PosesInFrame", "protobuf"),
    ],
)
def test_the_optimized_and_odometry_paths_are_one_message_each_at_the_start(
    unverified: dict[str, Path], tmp_path: Path, profile: str, path_type: str, schema_encoding: str
) -> None:
    out = tmp_path / "optimized.mcap"
    assert main(["optimize", str(unverified[profile]), "-o", str(out)]) == 0
    found = _path_messages(out)
    assert sorted(found["paths"]) == sorted(PATH_TOPICS)
    optimized = read_poses(out, OPTIMIZED_POSE_TOPIC)
    odometry = read_poses(out, "/odom").interpolate(optimized.times_ns)
    expected = {OPTIMIZED_PATH_TOPIC: optimized, ODOMETRY_PATH_TOPIC: odometry}
    for topic, (log_time, schema, channel, message) in found["paths"].items():
        # At the log's first message: a viewer seeking anywhere has the whole trajectory.
        assert log_time == found["first_log_time"]
        assert (schema.name, schema.encoding) == (path_type, schema_encoding)
        if profile == "ros1":
            assert channel.metadata["md5sum"] == "6227e2b7e9cce15051f669a5e197bbf7"
        stamps, positions, quaternions = _path_arrays(message)
        frame_id = message.header.frame_id if hasattr(message, "header") else message.frame_id
        assert frame_id == "odom"
        assert len(positions) == 240
        if stamps is not None:
            np.testing.assert_array_equal(stamps, optimized.times_ns)
        np.testing.assert_allclose(positions, expected[topic].positions, atol=1e-9)
        np.testing.assert_allclose(quaternions, expected[topic].quaternions_xyzw, atol=1e-9)
    # The two are different trajectories: the loop edges moved the optimized one.
    assert not np.allclose(optimized.positions, odometry.positions, atol=1e-3)


@pytest.mark.slow
def test_optimize_defaults_to_the_odometry_annotate_recorded(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Annotated with --odometry-topic /ground_truth/pose, optimized with no topic given: the
    graph is built on the ground truth (frame map), not on the log's rule's /odom."""
    annotated, out = tmp_path / "annotated.mcap", tmp_path / "optimized.mcap"
    asked = ["--no-verify", "--odometry-topic", "/ground_truth/pose"]
    assert (
        main(["annotate", str(SAMPLES / "drive_loops.ros2.mcap"), "-o", str(annotated), *asked])
        == 0
    )
    capsys.readouterr()
    assert main(["optimize", str(annotated), "-o", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["frame_id"] == "map"
    found = _path_messages(out)["paths"]
    _, positions, _ = _path_arrays(found[ODOMETRY_PATH_TOPIC][3])
    optimized = read_poses(out, OPTIMIZED_POSE_TOPIC)
    truth = read_poses(out, "/ground_truth/pose").interpolate(optimized.times_ns)
    np.testing.assert_allclose(positions, truth.positions, atol=1e-9)


@pytest.mark.slow
def test_a_sidecar_takes_its_poses_from_the_original_log(
    unverified: dict[str, Path], tmp_path: Path
) -> None:
    sidecar, out = unverified["sidecar"], tmp_path / "optimized.mcap"
    args = [str(sidecar), "--odometry-topic", "/odom", "-o", str(out)]
    assert main(["optimize", *args]) == 3  # a sidecar holds no odometry
    poses_from = ["--poses-from", str(SAMPLES / "drive_loops.ros2.mcap")]
    assert main(["optimize", *args, *poses_from]) == 0
    with open_source(out) as source:
        types = {c.topic: c.message_type for c in source.channels()}
    assert types == {
        "/doseqslam/loop_closures": "doseqslam_msgs/msg/LoopClosure",
        "/doseqslam/candidates": "doseqslam_msgs/msg/LoopClosure",
        "/doseqslam/sequences": "doseqslam_msgs/msg/Sequence",
        OPTIMIZED_POSE_TOPIC: "geometry_msgs/msg/PoseStamped",
        OPTIMIZED_PATH_TOPIC: "nav_msgs/msg/Path",
        ODOMETRY_PATH_TOPIC: "nav_msgs/msg/Path",
    }
    assert len(read_poses(out, OPTIMIZED_POSE_TOPIC)) == 240
    original = tmp_path / "original.mcap"  # a copy: the refusal is what is tested
    original.write_bytes((SAMPLES / "drive_loops.ros2.mcap").read_bytes())
    over_the_poses = [str(sidecar), "--odometry-topic", "/odom", "--poses-from", str(original)]
    assert main(["optimize", *over_the_poses, "-o", str(original)]) == 6
    assert original.read_bytes() == (SAMPLES / "drive_loops.ros2.mcap").read_bytes()


@pytest.mark.slow
@pytest.mark.parametrize(
    ("case", "code", "message"),
    [
        ("missing topic", 3, "topic '/nope' is not in the log"),
        ("not annotated", 3, "not annotated by doseqslam-logs"),
        ("output over the input", 6, "the output would replace the input"),
        ("no pose topic", 2, "no pose topic (nav_msgs/Odometry, "),
        ("poses from another log", 2, "not the log"),
        ("output a device", 6, "refusing to replace it"),
    ],
)
def test_errors_exit_with_their_documented_codes(
    unverified: dict[str, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    case: str,
    code: int,
    message: str,
) -> None:
    log, out = unverified["ros1"], tmp_path / "out.mcap"
    args = {
        "missing topic": [str(log), "--odometry-topic", "/nope", "-o", str(out)],
        "not annotated": [
            str(SAMPLES / "drive_loops.ros2.mcap"),
            "--odometry-topic",
            "/odom",
            "-o",
            str(out),
        ],
        "output over the input": [str(log), "--odometry-topic", "/odom", "-o", str(log)],
        # A sidecar holds our channels only: without --poses-from no pose topic to default to.
        "no pose topic": [str(unverified["sidecar"]), "-o", str(out)],
        "output a device": [str(log), "--odometry-topic", "/odom", "-o", "/dev/null"],
        "poses from another log": [
            str(unverified["sidecar"]),
            "--poses-from",
            str(SAMPLES / "drive_parked.ros2.mcap"),
            "-o",
            str(out),
        ],
    }[case]
    before = log.read_bytes()
    capsys.readouterr()
    assert main(["optimize", *args]) == code
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err
    assert not out.exists()
    assert log.read_bytes() == before


# -- the pose topic in a JSON profile, and the copy ------------------------------------------


def _small_json_log(path: Path) -> None:
    """An MCAP of the Foxglove JSON kind: one JSON channel, an attachment, a metadata record."""
    from mcap.writer import Writer

    with path.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="", library="test")
        schema = writer.register_schema("Note", "jsonschema", b'{"type":"object"}')
        channel = writer.register_channel("/notes", "json", schema)
        for k in range(4):
            data = json.dumps({"n": k}).encode()
            writer.add_message(channel, 10 + 10 * k, data, 10 + 10 * k, k)
        writer.add_attachment(1, 2, "calibration.txt", "text/plain", b"fx 100")
        writer.add_metadata("site", {"robot": "r1"})
        writer.finish()


def _records(path: Path) -> dict[str, Any]:
    from mcap.reader import make_reader

    with path.open("rb") as stream:
        reader = make_reader(stream)
        messages = [(c.topic, m.log_time, m.data) for _, c, m in reader.iter_messages()]
        attachments = [(a.name, a.data) for a in reader.iter_attachments()]
        metadata = [(m.name, m.metadata) for m in reader.iter_metadata()]
        profile = reader.get_header().profile
    return {"messages": messages, "attachments": attachments, "metadata": metadata, "p": profile}


def _schemas(path: Path) -> dict[str, tuple[str, str, str]]:
    """Each channel's schema: name, encoding, text."""
    from mcap.reader import make_reader

    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    schemas = summary.schemas
    return {
        c.topic: (schemas[c.schema_id].name, schemas[c.schema_id].encoding,
                  schemas[c.schema_id].data.decode())
        for c in summary.channels.values()
    }  # fmt: skip


def test_a_json_profile_gets_pose_in_frame_as_json_and_every_record_is_copied(
    tmp_path: Path,
) -> None:
    from doseqslam_logs.sinks.pose_topic import PathMessage, PoseStream, write_with_poses

    log, out, again = tmp_path / "log.mcap", tmp_path / "out.mcap", tmp_path / "again.mcap"
    _small_json_log(log)
    positions = np.array([[1.0, 2.0, 0.0], [2.0, 2.5, 0.0], [3.0, 3.0, 0.1]])
    quaternions = np.array([IDENTITY, [0.0, 0.0, 0.6, 0.8], IDENTITY])
    stream = PoseStream(
        topic=OPTIMIZED_POSE_TOPIC,
        frame_id="odom",
        log_times_ns=np.array([15, 25, 45], np.int64),
        stamps_ns=np.array([5_000_000_001, 5_000_000_002, 5_000_000_003], np.int64),
        positions=positions,
        quaternions_xyzw=quaternions,
        foxglove_encoding="json",
    )
    path = PathMessage(OPTIMIZED_PATH_TOPIC, "odom", stream.stamps_ns, positions, quaternions)
    summary = write_with_poses(log, out, stream, paths=[path])
    assert (summary.copied_messages, summary.pose_messages, summary.path_messages) == (4, 3, 1)
    with open_source(out) as source:
        channel = next(c for c in source.channels() if c.topic == OPTIMIZED_POSE_TOPIC)
        first = next(iter(source.messages(OPTIMIZED_POSE_TOPIC))).message
    assert (channel.message_type, channel.message_encoding) == ("foxglove.PoseInFrame", "json")
    assert first.frame_id == "odom"
    poses = read_poses(out, OPTIMIZED_POSE_TOPIC)
    np.testing.assert_array_equal(poses.times_ns, stream.stamps_ns)
    np.testing.assert_array_equal(poses.positions, positions)
    np.testing.assert_allclose(poses.quaternions_xyzw, quaternions)
    before, after = _records(log), _records(out)
    ours = [m for m in after["messages"] if m[0] == OPTIMIZED_POSE_TOPIC]
    copied = [m for m in after["messages"] if m[0] not in (OPTIMIZED_POSE_TOPIC, path.topic)]
    assert copied == before["messages"]
    # The path first, at the log's first message time; the poses interleaved.
    assert [m[1] for m in after["messages"]] == [10, 10, 15, 20, 25, 30, 40, 45]
    assert after["messages"][0][0] == OPTIMIZED_PATH_TOPIC
    assert len(ours) == 3
    path_message = json.loads(after["messages"][0][2])
    assert path_message == {
        "timestamp": {"sec": 5, "nsec": 3},  # its last pose's
        "frame_id": "odom",
        "poses": [
            {
                "position": dict(zip("xyz", p, strict=True)),
                "orientation": dict(zip("xyzw", q, strict=True)),
            }
            for p, q in zip(positions.tolist(), quaternions.tolist(), strict=True)
        ],
    }
    schemas = _schemas(out)
    assert schemas[OPTIMIZED_PATH_TOPIC][:2] == ("foxglove.PosesInFrame", "jsonschema")
    # The JSON schema is the one Foxglove's parser takes: no $ref, no type arrays.
    assert "$ref" not in schemas[OPTIMIZED_PATH_TOPIC][2]
    assert '"type": [' not in schemas[OPTIMIZED_PATH_TOPIC][2]
    assert (after["attachments"], after["metadata"], after["p"]) == (
        before["attachments"],
        before["metadata"],
        before["p"],
    )
    # Written again over its own output's topic: replaced, not doubled.
    replaced = write_with_poses(out, again, stream, paths=[path])
    assert replaced.replaced_topic
    assert _records(again)["messages"] == after["messages"]
