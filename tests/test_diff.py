"""`diff`: two annotated logs compared by time (doseqslam_logs.evaluation.diff, cli/diff.py)."""

from __future__ import annotations

import json
import re
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from doseqslam_logs.annotations.reader import AnnotatedLog, read_annotations
from doseqslam_logs.annotations.records import (
    NOT_RECORDED,
    FrameRef,
    FrameTimes,
    LoopClosureRecord,
    time_dict,
)
from doseqslam_logs.cli.main import main
from doseqslam_logs.detector.params import Parameters
from doseqslam_logs.evaluation.diff import (
    Pair,
    diff_logs,
    match_pairs,
    recorded_parameters,
    reported_pair,
)
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.verification import VerificationParameters

pytestmark = pytest.mark.slow  # the pipeline runs in its fixtures (pyproject: markers)

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
ROS2_LOG = SAMPLES / "drive_loops.ros2.mcap"
FOXGLOVE_LOG = SAMPLES / "drive_loops.foxglove.mcap"
MS = 1_000_000
VERIFY = VerificationParameters(refine_radius=2)


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The smallest sample annotated with several settings, once for the module."""
    out = tmp_path_factory.mktemp("diff")
    default = Parameters()
    paper = AnnotateOptions(sidecar=True, verification=None)  # the detector alone
    jobs: dict[str, tuple[Path, Parameters, AnnotateOptions]] = {
        "base": (ROS2_LOG, default, AnnotateOptions(verification=None)),
        "again": (ROS2_LOG, default, paper),
        "sidecar": (ROS2_LOG, default, paper),
        "threshold": (ROS2_LOG, default.replace(threshold=0.9), paper),
        "greedy": (ROS2_LOG, default.replace(association="greedy"), paper),
        "foxglove": (FOXGLOVE_LOG, default, paper),
        # Geometric verification with a small refinement radius (fast): same candidates.
        "verified": (ROS2_LOG, default, AnnotateOptions(sidecar=True, verification=VERIFY)),
    }
    paths = {}
    for name, (log, params, options) in jobs.items():
        paths[name] = out / f"{name}.mcap"
        annotate_log(log, paths[name], params, options)
    return paths


def run_cli(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = main(["diff", *[str(a) for a in args]])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def class_count(table: str, label: str) -> int:
    """The number in a row of the table's counts per class."""
    found = re.search(rf"^  {label} +(\d+)$", table, re.MULTILINE)
    assert found, f"no row {label!r} in:\n{table}"
    return int(found.group(1))


def index_pairs(path: Path) -> set[tuple[int, int]]:
    """(query, match) frame indices: the same source, so indices identify frames too."""
    return {(lc.query.index, lc.match.index) for lc in read_annotations(path).loop_closures}


# --- real logs ------------------------------------------------------------------------------


def test_same_parameters_twice_is_equal(runs, capsys) -> None:
    code, out, err = run_cli(capsys, runs["base"], runs["again"])
    assert (code, err) == (0, "")
    pairs = len(read_annotations(runs["base"]).loop_closures)
    assert pairs > 20
    assert class_count(out, "common") == pairs
    assert [class_count(out, c) for c in ("only in A", "only in B", "different match")] == [0] * 3
    assert "parameters: no difference" in out and "metadata: no difference" in out
    assert "warning" not in out
    assert out.rstrip().endswith("result: reported loop closures are the same (exit 0)")


def test_diff_logs_takes_paths_as_the_command_does(runs) -> None:
    by_path = diff_logs(runs["base"], runs["threshold"])
    read = diff_logs(read_annotations(runs["base"]), read_annotations(runs["threshold"]))
    assert by_path.to_json_dict() == read.to_json_dict() and not by_path.equal
    assert diff_logs(runs["base"], runs["again"]).equal


def test_sidecar_equals_the_full_copy_of_the_same_run(runs, capsys) -> None:
    code, out, _ = run_cli(capsys, runs["sidecar"], runs["base"], "--json")
    doc = json.loads(out)
    assert code == 0 and doc["equal"] is True and doc["same_source"] is True
    assert doc["warnings"] == [] and doc["metadata_differences"] == []
    assert doc["counts"]["common"] == doc["a"]["reported"] == doc["b"]["reported"] > 0


@pytest.mark.parametrize("order", ["ab", "ba"])
def test_a_higher_threshold_adds_pairs_only_in_that_log(runs, order) -> None:
    low, high = runs["base"], runs["threshold"]
    a, b = (low, high) if order == "ab" else (high, low)
    result = diff_logs(read_annotations(a), read_annotations(b))
    pairs_a, pairs_b = index_pairs(a), index_pairs(b)
    assert {(x.query_index, x.match_index) for x, _ in result.reported.common} == (
        pairs_a & pairs_b
    )
    assert {(p.query_index, p.match_index) for p in result.reported.only_a} == pairs_a - pairs_b
    assert {(p.query_index, p.match_index) for p in result.reported.only_b} == pairs_b - pairs_a
    assert result.reported.different_match == []
    assert len(pairs_b - pairs_a if order == "ab" else pairs_a - pairs_b) > 10
    assert not result.equal
    (difference,) = result.parameter_differences
    assert (difference.name, difference.a, difference.b) == (
        ("threshold", 0.75, 0.9) if order == "ab" else ("threshold", 0.9, 0.75)
    )
    assert result.metadata_differences[0].name == "parameters_hash"


def test_the_cli_shows_counts_parameters_and_first_pairs_and_exits_1(runs, capsys) -> None:
    code, out, _ = run_cli(capsys, runs["base"], runs["threshold"])
    assert code == 1
    log_b = read_annotations(runs["threshold"])
    extra = sorted(index_pairs(runs["threshold"]) - index_pairs(runs["base"]))
    assert class_count(out, "only in B") == len(extra)
    assert class_count(out, "only in A") == 0
    assert "  threshold  0.75  0.9" in out
    assert f"only in B (first 5 of {len(extra)}):" in out
    first = next(lc for lc in log_b.loop_closures if lc.query.index == extra[0][0])
    assert first.query.stamp_ns is not None
    query_s = first.query.stamp_ns / 1e9
    assert f"{query_s:.3f} (#{extra[0][0]})" in out
    assert out.rstrip().endswith("result: reported loop closures are different (exit 1)")


def test_another_association_changes_matches_of_the_same_queries(runs) -> None:
    result = diff_logs(read_annotations(runs["base"]), read_annotations(runs["greedy"]))
    different = result.reported.different_match
    assert different, "greedy association should move some matches on this log"
    for pair_a, pair_b in different:
        assert pair_a.query_index == pair_b.query_index
        assert pair_a.match_index != pair_b.match_index
    by_query_a = dict(index_pairs(runs["base"]))
    by_query_b = dict(index_pairs(runs["greedy"]))
    moved = {q for q in by_query_a.keys() & by_query_b.keys() if by_query_a[q] != by_query_b[q]}
    assert {a.query_index for a, _ in different} == moved
    assert [d.name for d in result.parameter_differences] == ["association"]


def test_different_sources_give_a_warning_not_an_error(runs, capsys) -> None:
    code, out, err = run_cli(capsys, runs["base"], runs["foxglove"])
    assert code == 0 and err == ""  # the same drive in another container: same loop closures
    warning = next(line for line in out.splitlines() if line.startswith("warning:"))
    assert "different sources" in warning
    assert "drive_loops.ros2.mcap" in warning and "drive_loops.foxglove.mcap" in warning
    code, out, _ = run_cli(capsys, runs["base"], runs["foxglove"], "--json")
    assert json.loads(out)["same_source"] is False


def test_json_lists_every_pair_with_times_and_indices(runs, capsys) -> None:
    code, out, _ = run_cli(capsys, runs["threshold"], runs["greedy"], "--json")
    doc = json.loads(out)
    assert code == 1 and doc["equal"] is False
    assert set(doc) == {
        "equal",
        "tolerance_ms",
        "a",
        "b",
        "same_source",
        "warnings",
        "counts",
        "common",
        "only_a",
        "only_b",
        "different_match",
        "verdict_changes",
        "parameter_differences",
        "metadata_differences",
    }
    for name in ("common", "only_a", "only_b", "different_match"):
        assert doc["counts"][name] == len(doc[name])
    assert doc["counts"]["only_a"] > 0 and doc["counts"]["different_match"] > 0
    assert (
        sum(doc["counts"][k] for k in ("common", "only_a", "different_match"))
        == (doc["a"]["reported"])
    )
    assert set(doc["only_a"][0]) == {
        "query_time_ns",
        "query_index",
        "match_time_ns",
        "match_index",
        "verification",
    }
    assert set(doc["different_match"][0]) == {"a", "b"}
    assert {d["name"] for d in doc["parameter_differences"]} == {"threshold", "association"}


def test_verification_rejects_pairs_refines_matches_and_changes_verdicts(runs) -> None:
    unchecked, verified = read_annotations(runs["base"]), read_annotations(runs["verified"])
    result = diff_logs(unchecked, verified)
    verdict = {lc.query.index: lc.verification for lc in verified.loop_closures}
    refined = {lc.query.index: lc.matched.index for lc in verified.loop_closures}
    proposed = dict(index_pairs(runs["base"]))
    assert proposed == dict(index_pairs(runs["verified"]))  # th alike: the same candidates
    rejected = {q for q, v in verdict.items() if v == "rejected"}
    moved = {q for q, v in verdict.items() if v == "accepted" and refined[q] != proposed[q]}
    assert rejected and moved  # this log exercises both
    assert {p.query_index for p in result.reported.only_a} == rejected
    assert result.reported.only_b == []
    assert {a.query_index for a, _ in result.reported.different_match} == moved
    for a, b in result.reported.different_match:
        assert (a.match_index, b.match_index) == (proposed[a.query_index], refined[a.query_index])
    assert len(result.reported.common) == len(verdict) - len(rejected) - len(moved)
    assert result.verdicts is not None and result.verdicts.compared == len(verdict)
    assert result.verdicts.by_change == {
        "off -> accepted": len(verdict) - len(rejected),
        "off -> rejected": len(rejected),
    }
    names = [d.name for d in result.parameter_differences]
    assert names and all(name.startswith("verification.") for name in names)
    assert "verification.refine_radius" in names
    verification_row = next(d for d in result.metadata_differences if d.name == "verification")
    assert (verification_row.a, verification_row.b) == ("off", "on")


# --- exit codes -----------------------------------------------------------------------------


def test_a_missing_file_is_a_usage_error(runs, capsys, tmp_path) -> None:
    missing = tmp_path / "nope.mcap"
    code, out, err = run_cli(capsys, runs["base"], missing)
    assert (code, out) == (2, "")
    assert err.startswith("doseqslam-logs: error: ") and str(missing) in err
    assert len(err.splitlines()) == 1


def test_a_log_that_is_not_annotated_is_a_usage_error(runs, capsys) -> None:
    code, _, err = run_cli(capsys, ROS2_LOG, runs["base"])
    assert code == 2
    assert "not annotated" in err and str(ROS2_LOG) in err


@pytest.mark.parametrize("value", ["-1", "nan", "inf"])
def test_a_bad_tolerance_is_a_usage_error(runs, capsys, value) -> None:
    code, out, err = run_cli(capsys, runs["base"], runs["again"], f"--tolerance-ms={value}")
    assert (code, out) == (2, "")
    assert "--tolerance-ms" in err


def test_a_tolerance_that_is_not_a_number_is_rejected_by_argparse(runs, capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["diff", str(runs["base"]), str(runs["again"]), "--tolerance-ms", "soon"])
    assert exit_info.value.code == 2


# --- tolerance, refined matches and verdicts on edited copies of a real log ----------------


def moved(frame: FrameRef, offset_ns: int) -> FrameRef:
    assert frame.stamp_ns is not None
    return replace(frame, stamp_ns=frame.stamp_ns + offset_ns)


def shifted(log: AnnotatedLog, offset_ns: int, prefixes: tuple[str, ...]) -> AnnotatedLog:
    """A copy whose frame stamps (of these prefixes) moved by `offset_ns`, e.g. another clock.
    The refined match moves with the match."""
    closures = []
    for lc in log.loop_closures:
        changes = {prefix: moved(getattr(lc, prefix), offset_ns) for prefix in prefixes}
        if "match" in prefixes:
            changes["refined_match"] = moved(lc.matched, offset_ns)
        closures.append(replace(lc, **changes))
    return replace(log, loop_closures=tuple(closures))


def test_tolerance_pairs_times_that_differ_by_less_than_it(runs) -> None:
    base = read_annotations(runs["base"])
    later = shifted(base, 20 * MS, ("query", "match"))  # frames are 500 ms apart
    count = len(base.loop_closures)
    exact = diff_logs(base, later).reported.counts
    assert exact == {"common": 0, "only_a": count, "only_b": count, "different_match": 0}
    assert diff_logs(base, later, 25 * MS).reported.counts["common"] == count
    assert diff_logs(base, later, 19 * MS).reported.counts["common"] == 0
    # Only the match moves: same query, different match unless the tolerance covers it.
    match_moved = shifted(base, -30 * MS, ("match",))
    assert diff_logs(base, match_moved).reported.counts["different_match"] == count
    assert not diff_logs(base, match_moved, 29 * MS).equal
    assert diff_logs(base, match_moved, 30 * MS).equal


def with_verification(log: AnnotatedLog, verdicts: dict[int, tuple[str, int]]) -> AnnotatedLog:
    """A copy with verification fields: query index -> (verdict, refined match index);
    every other pair "off"."""
    times = log.frame_times
    assert times is not None
    closures = []
    for lc in log.loop_closures:
        verdict, refined = verdicts.get(lc.query.index, ("off", lc.match.index))
        closures.append(
            replace(lc, verification=verdict, refined_match=FrameRef.of(refined, times))
        )
    return replace(log, loop_closures=tuple(closures))


def test_reported_pairs_use_the_refined_match_and_skip_rejected_ones(runs) -> None:
    base = read_annotations(runs["base"])
    first, second, third = (lc.query.index for lc in base.loop_closures[:3])
    match_of = {lc.query.index: lc.match.index for lc in base.loop_closures}
    verified = with_verification(
        base,
        {
            first: ("accepted", match_of[first]),
            second: ("accepted", match_of[second] + 2),  # refinement moved the match
            third: ("rejected", match_of[third]),
        },
    )
    result = diff_logs(with_verification(base, {}), verified)
    assert [p.query_index for p in result.reported.only_a] == [third]
    assert result.reported.only_b == []
    ((pair_a, pair_b),) = result.reported.different_match
    assert (pair_a.query_index, pair_a.match_index) == (second, match_of[second])
    assert (pair_b.query_index, pair_b.match_index) == (second, match_of[second] + 2)
    assert pair_b.match_time_ns - pair_a.match_time_ns == 1000 * MS  # 2 frames at 2 Hz
    verdicts = result.verdicts
    assert verdicts is not None and verdicts.compared == len(base.loop_closures)
    assert verdicts.by_change == {"off -> accepted": 2, "off -> rejected": 1}
    table = result.format_table()
    assert "3 changed of " in table and "off -> rejected: 1" in table


def test_verdicts_are_not_compared_when_a_log_predates_verification(runs) -> None:
    base = read_annotations(runs["base"])
    closures = tuple(replace(lc, verification=NOT_RECORDED) for lc in base.loop_closures)
    without = replace(base, loop_closures=closures)
    result = diff_logs(without, with_verification(base, {}))
    assert result.verdicts is None and result.equal
    assert "not compared" in result.format_table()
    assert result.to_json_dict()["verdict_changes"] is None


def test_a_refined_index_without_times_is_placed_by_the_frame_times() -> None:
    times = FrameTimes([10 * MS, 20 * MS, 30 * MS], [-1, 21 * MS, 31 * MS])
    lc = {
        "query_index": 2,
        "query_log_time": time_dict(30 * MS),
        "query_stamp": time_dict(31 * MS),
        "query_has_stamp": True,
        "match_index": 1,
        "match_log_time": time_dict(20 * MS),
        "match_stamp": time_dict(21 * MS),
        "match_has_stamp": True,
        "difference": 0.5,
        **dict.fromkeys(("sequence_id", "sequence_first_index", "sequence_last_index"), 0),
        **dict.fromkeys(("match_first_index", "match_last_index"), 1),
        **dict.fromkeys(("gamma", "gamma_previous", "gamma_next", "f", "threshold"), 0.5),
        "method": "doseqslam",
        "parameters_hash": "0" * 16,
    }

    def pair(message: dict[str, Any], frame_times: FrameTimes | None) -> Pair:
        return reported_pair(LoopClosureRecord.from_message(message, frame_times))

    assert pair(lc, times) == Pair(31 * MS, 21 * MS, 2, 1)
    assert pair({**lc, "refined_match_index": 0}, times) == Pair(31 * MS, 10 * MS, 2, 0)
    assert pair({**lc, "refined_match_index": 0}, None) == Pair(31 * MS, 21 * MS, 2, 1)


def test_recorded_parameters_flattens_every_parameter_set() -> None:
    metadata = {
        "parameters": json.dumps({"threshold": 0.75, "nested": {"k": 1}}),
        "verification_parameters": json.dumps({"min_inliers": 30}),
        "parameters_hash": "abc",
        "tool_version": "0.1.0",
    }
    assert recorded_parameters(metadata) == {
        "threshold": 0.75,
        "nested.k": 1,
        "verification.min_inliers": 30,
    }


# --- the matching function -------------------------------------------------------------------

times = st.integers(min_value=0, max_value=40)
pair_lists = st.lists(st.builds(lambda q, m: Pair(q * MS, m * MS, q, m), times, times), max_size=25)
tolerances = st.integers(min_value=0, max_value=5).map(lambda t: t * MS)


def keys(pairs: list[Pair]) -> Counter[tuple[int, int]]:
    return Counter((p.query_time_ns, p.match_time_ns) for p in pairs)


@settings(max_examples=300, deadline=None)
@given(pair_lists, pair_lists, tolerances)
def test_matching_partitions_both_logs_and_is_symmetric(
    a: list[Pair], b: list[Pair], tolerance: int
) -> None:
    forward, backward = match_pairs(a, b, tolerance), match_pairs(b, a, tolerance)
    paired = forward.common + forward.different_match
    assert keys([x for x, _ in paired] + forward.only_a) == keys(a)
    assert keys([y for _, y in paired] + forward.only_b) == keys(b)
    assert len(forward.common) + len(forward.different_match) + len(forward.only_a) == len(a)
    assert backward.counts == {
        "common": len(forward.common),
        "only_a": len(forward.only_b),
        "only_b": len(forward.only_a),
        "different_match": len(forward.different_match),
    }
    for x, y in forward.common:
        assert abs(x.query_time_ns - y.query_time_ns) <= tolerance
        assert abs(x.match_time_ns - y.match_time_ns) <= tolerance
    for x, y in forward.different_match:
        assert abs(x.query_time_ns - y.query_time_ns) <= tolerance
        assert abs(x.match_time_ns - y.match_time_ns) > tolerance
    assert match_pairs(a, a, tolerance).counts["common"] == len(a)


@settings(max_examples=300, deadline=None)
@given(pair_lists, pair_lists)
def test_exact_matching_pairs_every_equal_query(a: list[Pair], b: list[Pair]) -> None:
    result = match_pairs(a, b, 0)
    queries_a = Counter(p.query_time_ns for p in a)
    queries_b = Counter(p.query_time_ns for p in b)
    assert len(result.common) == sum((keys(a) & keys(b)).values())
    assert len(result.common) + len(result.different_match) == sum((queries_a & queries_b).values())


spaced_queries = st.lists(st.integers(0, 200), unique=True, max_size=20).map(
    lambda qs: [q * 20 * MS for q in sorted(qs)]  # queries 20 ms apart or more in each log
)


@settings(max_examples=300, deadline=None)
@given(spaced_queries, spaced_queries, st.integers(0, 9), st.integers(-9, 9))
def test_with_spaced_queries_every_query_within_tolerance_is_paired(
    queries_a: list[int], queries_b: list[int], tolerance_ms: int, shift_ms: int
) -> None:
    tolerance = tolerance_ms * MS  # below half the spacing: each query has one partner at most
    a = [Pair(q, q // 2, i, i) for i, q in enumerate(queries_a)]
    b = [Pair(q, q // 2, i, i) for i, q in enumerate(queries_b)]
    close = sum(1 for x in a for y in b if abs(x.query_time_ns - y.query_time_ns) <= tolerance)
    result = match_pairs(a, b, tolerance)
    assert len(result.common) + len(result.different_match) == close
    moved = [Pair(p.query_time_ns + shift_ms * MS, p.match_time_ns, 0, 0) for p in a]
    shifted_result = match_pairs(a, moved, tolerance)
    if abs(shift_ms) <= tolerance_ms:
        assert shifted_result.counts["common"] == len(a)
    else:
        assert shifted_result.counts["common"] == 0


def test_a_negative_tolerance_is_refused() -> None:
    with pytest.raises(ValueError, match="tolerance"):
        match_pairs([], [], -1)
