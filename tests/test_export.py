"""`doseqslam-logs export`: every format parsed back, rejected pairs, atomic output, exit codes."""

from __future__ import annotations

import csv
import io
import itertools
import json
import math
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from doseqslam_logs.annotations.reader import AnnotatedLog, read_annotations
from doseqslam_logs.annotations.records import LoopClosureRecord, RunMetadata
from doseqslam_logs.cli.main import main
from doseqslam_logs.errors import UsageError
from doseqslam_logs.export import export_log
from doseqslam_logs.export.loops import COLUMNS, frame_times_ns, loop_closure_row
from doseqslam_logs.export.pose_graph import verified_body_rotation
from doseqslam_logs.sources.poses import read_poses

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
BAG = SAMPLES / "drive_loops.bag"  # annotated into an MCAP with the ROS 1 profile


@pytest.fixture(scope="module")
def annotated(annotated_sample: Callable[..., Path]) -> Path:
    return annotated_sample(BAG.name)  # `annotate` with its defaults: verification on


@pytest.fixture(scope="module")
def log(annotated: Path) -> AnnotatedLog:
    return read_annotations(annotated)


def export(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(["export", *args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_the_sample_has_accepted_and_rejected_pairs(log: AnnotatedLog) -> None:
    verdicts = {lc.verification for lc in log.loop_closures}
    assert verdicts == {"accepted", "rejected"}  # the rest of this file relies on both


def test_csv_has_one_row_per_reported_loop_closure(
    annotated: Path, log: AnnotatedLog, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = export(capsys, str(annotated), "--format", "csv")
    assert code == 0
    rows = list(csv.DictReader(io.StringIO(out)))
    reported = log.reported_loop_closures
    assert len(rows) == len(reported) > 20
    assert tuple(rows[0]) == COLUMNS
    assert {row["verification"] for row in rows} == {"accepted"}
    times = frame_times_ns(log)
    for row, lc in zip(rows, reported, strict=True):
        assert int(row["query_index"]) == lc.query.index
        assert int(row["query_time_ns"]) == times[lc.query.index]
        assert int(row["match_time_ns"]) == times[lc.match.index]
        assert int(row["refined_match_index"]) == lc.matched.index
        assert int(row["refined_match_time_ns"]) == times[lc.matched.index]
        assert int(row["inliers"]) > 0
        assert float(row["f"]) < float(row["threshold"])
        quaternion = [float(row[f"rotation_q{axis}"]) for axis in "xyzw"]
        assert math.isclose(float(np.linalg.norm(quaternion)), 1.0, rel_tol=1e-6)
    assert f"{len(rows)} loop closures" in err and "rejected by verification left out" in err


def test_include_rejected_adds_them_with_their_verdict(
    annotated: Path, log: AnnotatedLog, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, _ = export(capsys, str(annotated), "--format", "csv", "--include-rejected")
    assert code == 0
    rows = list(csv.DictReader(io.StringIO(out)))
    assert len(rows) == len(log.loop_closures)
    rejected = [row for row in rows if row["verification"] == "rejected"]
    assert len(rejected) == len(log.loop_closures) - len(log.reported_loop_closures) > 0
    assert all(row["rotation_qw"] == "" for row in rejected)  # no pose for a rejected pair


def test_jsonl_matches_the_csv(annotated: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _, csv_text, _ = export(capsys, str(annotated), "--format", "csv")
    code, out, _ = export(capsys, str(annotated), "--format", "jsonl")
    assert code == 0
    objects = [json.loads(line) for line in out.splitlines()]
    rows = list(csv.DictReader(io.StringIO(csv_text)))
    assert len(objects) == len(rows)
    for obj, row in zip(objects, rows, strict=True):
        assert tuple(obj) == COLUMNS
        assert obj["query_time_ns"] == int(row["query_time_ns"])
        assert obj["difference"] == float(row["difference"])
        assert obj["verification"] == "accepted"


def test_rows_of_logs_without_verification_have_empty_verification_fields() -> None:
    time = {"sec": 1, "nsec": 5}
    old = {
        **{f"{p}_index": i for p, i in (("query", 9), ("match", 2))},
        **{f"{p}_log_time": time for p in ("query", "match")},
        **{f"{p}_stamp": {"sec": 0, "nsec": 0} for p in ("query", "match")},
        **{f"{p}_has_stamp": False for p in ("query", "match")},
        "difference": 1.5,
        **dict.fromkeys(("sequence_first_index", "sequence_last_index"), 9),
        **dict.fromkeys(("match_first_index", "match_last_index"), 2),
        **dict.fromkeys(("gamma", "gamma_previous", "gamma_next"), 0.5),
        "f": 0.5,
        "threshold": 0.75,
        "sequence_id": 3,
        "method": "doseqslam",
        "parameters_hash": "0" * 16,
    }
    metadata = RunMetadata.from_entries({"tool_version": "0.1.0"})
    record = LoopClosureRecord.from_message(old)
    row = loop_closure_row(AnnotatedLog(Path("old.mcap"), metadata, (record,)), record)
    assert row["query_time_ns"] == 1_000_000_005  # no header stamp: the log time
    assert row["verification"] is None and row["refined_match_index"] is None
    assert row["rotation_qw"] is None and row["translation_dz"] is None


def test_tum_is_the_odometry_at_every_camera_frame(
    annotated: Path, log: AnnotatedLog, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = export(capsys, str(annotated), "--format", "tum", "--odometry-topic", "/odom")
    assert code == 0
    lines = out.splitlines()
    assert lines[0].startswith("#")
    table = np.array([[float(v) for v in line.split()] for line in lines[1:]])
    assert table.shape == (240, 8)
    times = frame_times_ns(log)
    np.testing.assert_allclose(table[:, 0], times / 1e9, rtol=0, atol=1e-6)
    assert [line.split()[0] for line in lines[1:3]] == [
        "1700000000.000000000",
        "1700000000.500000000",
    ]
    odometry = read_poses(BAG, "/odom").interpolate(times)
    np.testing.assert_allclose(table[:, 1:4], odometry.positions, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(table[:, 4:], axis=1), 1.0, atol=1e-9)
    assert "240 poses of /odom" in err


def _g2o(text: str) -> dict[str, list[list[str]]]:
    """Lines by tag; "#" holds the leading comment lines (none may come later)."""
    parsed: dict[str, list[list[str]]] = {
        "#": [], "VERTEX_SE3:QUAT": [], "EDGE_SE3:QUAT": [], "FIX": []
    }  # fmt: skip
    lines = text.splitlines()
    header = list(itertools.takewhile(lambda line: line.startswith("#"), lines))
    parsed["#"] = [[line] for line in header]
    for line in lines[len(header) :]:
        tag, *values = line.split()
        parsed[tag].append(values)  # KeyError: an unexpected line (a late comment too)
    return parsed


def _information(values: list[str]) -> np.ndarray:
    upper = [float(v) for v in values[9:]]
    assert len(upper) == 21
    matrix = np.zeros((6, 6))
    matrix[np.triu_indices(6)] = upper
    return matrix + np.triu(matrix, 1).T


def test_g2o_vertices_and_edges_are_consistent(
    annotated: Path, log: AnnotatedLog, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = export(
        capsys, str(annotated), "--format", "g2o", "--odometry-topic", "/odom",
        "--loop-model", "placeholder",
    )  # fmt: skip
    assert code == 0
    graph = _g2o(out)
    ids = [int(v[0]) for v in graph["VERTEX_SE3:QUAT"]]
    assert ids == list(range(240))
    assert graph["FIX"] == [["0"]]
    edges = graph["EDGE_SE3:QUAT"]
    reported = log.reported_loop_closures
    assert len(edges) == 239 + len(reported)
    odometry, loops = edges[:239], edges[239:]
    assert [(int(e[0]), int(e[1])) for e in odometry] == [(k, k + 1) for k in range(239)]
    assert [(int(e[0]), int(e[1])) for e in loops] == [
        (lc.query.index, lc.matched.index) for lc in reported
    ]
    for edge in edges:
        information = _information(edge)
        assert np.linalg.eigvalsh(information).min() > 0
        assert math.isclose(float(np.linalg.norm([float(v) for v in edge[5:9]])), 1.0)
    # Odometry: 1/0.05 on x and y from the message covariance; the unmeasured z, roll and pitch
    # (variance 1e6) get the default sigmas 0.1 m and 0.02 rad; yaw 1/0.01.
    np.testing.assert_allclose(
        np.diag(_information(odometry[0])), [20, 20, 100, 2500, 2500, 100], rtol=1e-9
    )
    # Loops: zero translation, weak (sigma 3 m); rotation sigma 10 deg.
    for edge in loops:
        assert [float(v) for v in edge[2:5]] == [0.0, 0.0, 0.0]
        expected = [1 / 9] * 3 + [1 / math.radians(10) ** 2] * 3
        np.testing.assert_allclose(np.diag(_information(edge)), expected, rtol=1e-9)
    assert f"240 vertices, 239 odometry edges, {len(reported)} loop edges" in err


def test_g2o_identity_loop_rotation_and_sigmas(
    annotated: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = [str(annotated), "--format", "g2o", "--odometry-topic", "/odom"]
    args += ["--loop-model", "placeholder"]
    code, out, _ = export(
        capsys, *args, "--identity-loop-rotation", "--loop-translation-sigma", "2",
        "--loop-rotation-sigma", "5",
    )  # fmt: skip
    assert code == 0
    loops = _g2o(out)["EDGE_SE3:QUAT"][239:]
    assert loops and all([float(v) for v in e[2:9]] == [0, 0, 0, 0, 0, 0, 1] for e in loops)
    expected = [1 / 4] * 3 + [1 / math.radians(5) ** 2] * 3
    np.testing.assert_allclose(np.diag(_information(loops[0])), expected, rtol=1e-9)


def test_g2o_header_states_the_loop_edge_model_and_gtsam_still_reads_the_file(
    annotated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = [str(annotated), "--format", "g2o", "--odometry-topic", "/odom"]
    args += ["--loop-model", "placeholder"]
    _, out, _ = export(capsys, *args)
    header = "\n".join(line for [line] in _g2o(out)["#"])
    assert out.startswith("# ") and "placeholder measurement model" in header
    assert "translation: zero, low information (sigma 3 m on x, y, z)" in header
    assert "rotation: from geometric verification when recorded, else identity" in header
    assert "(sigma 10 deg on each axis)" in header
    _, identity, _ = export(
        capsys, *args, "--identity-loop-rotation", "--loop-translation-sigma", "2.5",
        "--loop-rotation-sigma", "4",
    )  # fmt: skip
    header = "\n".join(line for [line] in _g2o(identity)["#"])
    assert "(sigma 2.5 m on x, y, z)" in header
    assert "rotation: identity (--identity-loop-rotation) (sigma 4 deg on each axis)" in header

    gtsam = pytest.importorskip("gtsam")
    with_header, without = tmp_path / "with.g2o", tmp_path / "without.g2o"
    with_header.write_text(out)
    without.write_text("".join(line for line in out.splitlines(True) if not line.startswith("#")))
    graph, initial = gtsam.readG2o(str(with_header), True)
    assert initial.size() == 240 and graph.size() == len(_g2o(out)["EDGE_SE3:QUAT"]) > 239
    bare_graph, bare_initial = gtsam.readG2o(str(without), True)
    assert graph.equals(bare_graph, 0.0) and initial.equals(bare_initial, 0.0)


def test_g2o_stride_keeps_every_kth_frame_and_the_loop_frames(
    annotated: Path, log: AnnotatedLog, capsys: pytest.CaptureFixture[str]
) -> None:
    args = [str(annotated), "--format", "g2o", "--odometry-topic", "/odom", "--stride", "10"]
    code, out, _ = export(capsys, *args)
    assert code == 0
    graph = _g2o(out)
    ids = [int(v[0]) for v in graph["VERTEX_SE3:QUAT"]]
    loop_frames = {lc.query.index for lc in log.reported_loop_closures}
    loop_frames |= {lc.matched.index for lc in log.reported_loop_closures}
    assert ids == sorted(set(range(0, 240, 10)) | {239} | loop_frames)
    odometry = [(int(e[0]), int(e[1])) for e in graph["EDGE_SE3:QUAT"][: len(ids) - 1]]
    assert odometry == list(itertools.pairwise(ids))
    assert len(graph["EDGE_SE3:QUAT"]) == len(ids) - 1 + len(log.reported_loop_closures)
    # An edge spanning k frames gets 1/k of the per-frame information.
    spans = {b - a: e for (a, b), e in zip(odometry, graph["EDGE_SE3:QUAT"], strict=False)}
    longest = max(spans)
    assert longest > 1
    assert _information(spans[longest])[0, 0] == pytest.approx(20 / longest)


def test_poses_from_another_log_are_refused_unless_asked_for(
    annotated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The same drive in another container: other bytes, so not the log that was annotated.
    args = [str(annotated), "--format", "g2o", "--odometry-topic", "/odom"]
    other = ["--poses-from", str(SAMPLES / "drive_loops.rosbag2")]
    _, own, _ = export(capsys, *args)
    code, out, err = export(capsys, *args, *other)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1
    assert "not the log" in err and "--no-source-check" in err
    code, out, _ = export(capsys, *args, *other, "--no-source-check")
    assert code == 0 and out == own
    code, out, _ = export(capsys, *args, "--poses-from", str(SAMPLES / BAG.name))
    assert code == 0 and out == own  # the log that was annotated
    copy = tmp_path / "copy.mcap"
    copy.write_bytes(annotated.read_bytes())
    code, out, _ = export(capsys, *args, "--poses-from", str(copy))
    assert code == 0 and out == own  # a full annotated copy of it: its record names the log


def test_output_file_is_written_atomically(
    annotated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / "graph.g2o"
    code, out, err = export(
        capsys, str(annotated), "--format", "g2o", "--odometry-topic", "/odom", "-o", str(target)
    )
    assert code == 0 and out == ""
    assert "\nVERTEX_SE3:QUAT 0 " in target.read_text()
    assert f"{target}: 240 vertices" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["graph.g2o"]  # no temporary left
    before = target.read_bytes()
    code, _, err = export(
        capsys, str(annotated), "--format", "g2o", "--odometry-topic", "/nope", "-o", str(target)
    )
    assert code == 3 and "'/nope' is not in the log" in err
    assert target.read_bytes() == before  # a failed export leaves the old file untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["graph.g2o"]


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["--format", "csv"], 3, "not annotated by doseqslam-logs"),
        (["--format", "g2o", "--odometry-topic", "/nope"], 3, "topic '/nope' is not in the log"),
        (
            ["--format", "g2o", "--odometry-topic", "/camera/camera_info"],
            3,
            "not a supported pose type",
        ),
    ],
)
def test_exit_codes(
    annotated: Path,
    capsys: pytest.CaptureFixture[str],
    args: list[str],
    code: int,
    message: str,
) -> None:
    not_annotated = message.startswith("not annotated")
    log = SAMPLES / "drive_loops.ros2.mcap" if not_annotated else annotated
    status, out, err = export(capsys, str(log), *args)
    assert status == code
    assert err.startswith("doseqslam-logs: error: ") and message in err
    assert len(err.strip().splitlines()) == 1 and out == ""


def test_an_output_that_would_replace_the_input_is_refused(
    annotated: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    status, _, err = export(capsys, str(annotated), "--format", "csv", "-o", str(annotated))
    assert status == 6 and "would replace the input" in err


def test_an_output_over_the_sidecars_log_is_refused(
    annotated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # --poses-from names the log a sidecar annotates: writing over it would destroy the input.
    log = tmp_path / "drive.mcap"
    log.write_bytes((SAMPLES / "drive_loops.ros2.mcap").read_bytes())
    before = log.read_bytes()
    args = ["--format", "tum", "--odometry-topic", "/odom", "--poses-from", str(log)]
    status, _, err = export(capsys, str(annotated), *args, "-o", str(log))
    assert status == 6 and f"would replace the input {log}" in err
    assert log.read_bytes() == before


def _optical_rotation_for_body_yaw(degrees: float) -> list[float]:
    """verification's R (X_match = R X_query + t, optical axes) when the match camera is
    turned `degrees` to the left (about body z = optical -y) of the query camera."""
    match_in_query = Rotation.from_rotvec([0.0, -math.radians(degrees), 0.0])
    return [float(v) for v in match_in_query.inv().as_quat()]


@pytest.mark.parametrize("degrees", [-30.0, -5.0, 0.0, 12.0, 90.0])
def test_verified_rotation_becomes_a_body_yaw(degrees: float, log: AnnotatedLog) -> None:
    rotation = tuple(_optical_rotation_for_body_yaw(degrees))
    lc = replace(log.loop_closures[0], has_relative_pose=True, rotation_xyzw=rotation)
    body = verified_body_rotation(lc)
    assert body is not None
    yaw, pitch, roll = Rotation.from_quat(body).as_euler("zyx", degrees=True)
    assert yaw == pytest.approx(degrees, abs=1e-9)
    assert pitch == pytest.approx(0.0, abs=1e-9) and roll == pytest.approx(0.0, abs=1e-9)
    assert verified_body_rotation(replace(lc, has_relative_pose=False)) is None
    assert verified_body_rotation(replace(lc, rotation_xyzw=(math.nan,) * 4)) is None


def test_export_log_gives_the_commands_text(annotated: Path, tmp_path, capsys) -> None:
    code, out, _ = export(capsys, str(annotated), "--format", "csv")
    result = export_log(annotated, "csv")
    assert code == 0 and "".join(result.chunks) == out and out.count("\n") > 20
    written = export_log(annotated, "csv", output=tmp_path / "loops.csv")
    assert (tmp_path / "loops.csv").read_text() == out and list(written.chunks) == []
    assert written.summary == result.summary
    with pytest.raises(UsageError, match="unknown export format"):
        export_log(annotated, "kml")


@pytest.mark.parametrize("kind", ["tum", "g2o"])
def test_the_pose_topic_defaults_to_the_one_annotate_picks(
    annotated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str
) -> None:
    # drive_loops.bag: /odom (nav_msgs/Odometry) before /ground_truth/pose (PoseStamped), as
    # annotate's rule takes it (sources.poses.default_pose_topic); the same file as asked for.
    given, default = tmp_path / f"given.{kind}", tmp_path / f"default.{kind}"
    args = [str(annotated), "--format", kind]
    assert export(capsys, *args, "--odometry-topic", "/odom", "-o", str(given))[0] == 0
    code, _, err = export(capsys, *args, "-o", str(default))
    assert code == 0 and default.read_bytes() == given.read_bytes()
    assert kind == "g2o" or "240 poses of /odom at camera times" in err


@pytest.mark.parametrize(
    ("asked", "recorded"),
    [([], "/odom"), (["--odometry-topic", "/ground_truth/pose"], "/ground_truth/pose")],
)
def test_annotate_records_its_odometry_and_export_defaults_to_it(
    annotated_sample: Callable[..., Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    asked: list[str],
    recorded: str,
) -> None:
    """The odometry annotate used (the one asked for, else the log's rule) is recorded, and
    export takes it where no --odometry-topic is given: here the ground truth, which the rule
    would not pick (/odom is the log's nav_msgs/Odometry)."""
    out = annotated_sample("drive_loops.ros2.mcap", "--no-verify", *asked)
    assert read_annotations(out).metadata.odometry_topic == recorded
    code, text, err = export(capsys, str(out), "--format", "tum")
    assert code == 0 and f"240 poses of {recorded} at camera times" in err
    expected = read_poses(out, recorded).interpolate(frame_times_ns(read_annotations(out)))
    rows = np.array([line.split()[1:4] for line in text.splitlines()[1:]], float)
    np.testing.assert_allclose(rows, expected.positions, atol=1e-9)
    # The trajectory annotate drew is that topic's too: in its frame (odom, map).
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with out.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        [(_, _, _, markers)] = reader.iter_decoded_messages(topics=["/doseqslam/markers"])
    assert {m.header.frame_id for m in markers.markers} == {read_poses(out, recorded).frame_id}


def test_none_records_no_odometry_and_export_takes_the_logs_rule(
    annotated_sample: Callable[..., Path], capsys: pytest.CaptureFixture[str]
) -> None:
    out = annotated_sample("drive_loops.ros2.mcap", "--no-verify", "--odometry-topic", "none")
    assert read_annotations(out).metadata.odometry_topic == ""
    code, _, err = export(capsys, str(out), "--format", "tum")
    assert code == 0 and "240 poses of /odom at camera times" in err


def test_a_sidecar_has_no_pose_topic_to_default_to(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sidecar = tmp_path / "sidecar.mcap"
    args = [str(BAG), "-o", str(sidecar), "--no-verify", "--sidecar"]
    assert main(["annotate", *args]) == 0
    code, _, err = export(capsys, str(sidecar), "--format", "tum", "-o", str(tmp_path / "t.tum"))
    assert code == 2 and "no pose topic (nav_msgs/Odometry, " in err and "--poses-from" in err
    assert not (tmp_path / "t.tum").exists()
