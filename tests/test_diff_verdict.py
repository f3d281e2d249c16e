"""`diff` with a verdict: ground truth labels the differing pairs, two batch folders compare
log by log, and --fail-on gates a release (evaluation/diff_truth, fleet_diff, diff_gate)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from doseqslam_logs.cli.main import main
from doseqslam_logs.errors import ExitCode, UsageError
from doseqslam_logs.evaluation.diff_gate import GateFigures, parse_gate
from doseqslam_logs.evaluation.groundtruth import load_ground_truth

pytestmark = pytest.mark.slow  # annotates two samples with a second parameter set

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
LOGS = ("drive_loops.ros2.mcap", "drive_parked.ros2.mcap")
# A looser version (no motion rule, no bracketing): more true pairs and, on the parked drive,
# false ones (the parked camera matched with itself), at the cost of one default annotation.
LOOSE = ("--vset", "motion_rule=false", "--vset", "bracket=false")
POSES = ("--gt-topic", "/ground_truth/pose", "--radius", "3")


@pytest.fixture(scope="module")
def versions(annotated_sample, tmp_path_factory) -> dict[str, Path]:
    """Two 'batch folders' (annotated logs, no manifest) of the same two samples."""
    root = tmp_path_factory.mktemp("versions")
    for name, options in (("a", ()), ("b", LOOSE)):
        (root / name).mkdir()
        for log in LOGS:
            shutil.copy(annotated_sample(log, *options), root / name / log.replace(".ros2", ""))
    return {"a": root / "a", "b": root / "b"}


def run(capsys, *args: object) -> tuple[int, str, str]:
    code = main(["diff", *[str(a) for a in args]])
    out, err = capsys.readouterr()
    return code, out, err


def evaluated(capsys, log: Path, *truth: str) -> dict:
    assert main(["evaluate", str(log), *truth, "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    return document["verified"] or document


def test_each_side_is_scored_as_evaluate_scores_it_and_pairs_are_labelled(versions, capsys):
    a, b = versions["a"] / "drive_parked.mcap", versions["b"] / "drive_parked.mcap"
    gt_file = SAMPLES / "drive_parked.gt.npz"
    code, out, _ = run(capsys, a, b, "--gt", gt_file, "--json")
    assert code == ExitCode.DIFFERENT
    document = json.loads(out)
    for side, log in (("a", a), ("b", b)):
        alone = evaluated(capsys, log, "--gt", str(gt_file))
        for key in ("tp", "fp", "precision", "recall"):
            assert document[side][key] == alone[key], (side, key)
        assert [c["covered"] for c in document[side]["coverage"]] == [
            c["covered"] for c in alone["coverage"]
        ]
    assert document["a"]["fp"] == 0 and document["b"]["fp"] > 0  # the parked camera
    gt = load_ground_truth(gt_file)
    labelled = document["only_b"] + [pair["b"] for pair in document["different_match"]]
    turned_false = sum(p["a"]["true"] and not p["b"]["true"] for p in document["different_match"])
    assert document["new_false"] == sum(not p["true"] for p in document["only_b"]) + turned_false
    assert document["lost_true"] == sum(p["true"] for p in document["only_a"]) + turned_false
    assert labelled and document["new_false"] > 0
    for pair in labelled + document["only_a"]:
        assert pair["true"] == gt.is_true(pair["query_index"], pair["match_index"])
    assert document["b"]["only_here"] == document["only_b"]


def test_the_table_labels_each_differing_pair(versions, capsys):
    a, b = versions["a"] / "drive_parked.mcap", versions["b"] / "drive_parked.mcap"
    code, out, _ = run(capsys, a, b, *POSES)
    assert code == ExitCode.DIFFERENT
    assert "ground truth: pose topic /ground_truth/pose (radius 3.0 m)" in out
    assert "ground truth" in out.split("only in B (first")[1].splitlines()[1]
    assert " false" in out and "B reports" in out


def test_two_folders_compare_log_by_log_with_a_total(versions, capsys):
    code, out, _ = run(capsys, versions["a"], versions["b"], *POSES, "--json")
    assert code == ExitCode.DIFFERENT
    document = json.loads(out)
    rows = {row["name"]: row for row in document["logs"]}
    assert sorted(rows) == sorted(LOGS)  # matched by source, named by the annotated log
    assert all(row["state"] == "compared" for row in rows.values())
    for key in ("common", "only_a", "only_b", "different_match"):
        assert document["totals"][key] == sum(row["counts"][key] for row in rows.values())
    for name, row in rows.items():  # each row is the file diff of that log
        code, out, _ = run(capsys, *(versions[s] / name.replace(".ros2", "") for s in "ab"),
                           *POSES, "--json")  # fmt: skip
        alone = json.loads(out)
        assert row["counts"] == alone["counts"]
        assert row["tp_fp"]["b"] == {"tp": alone["b"]["tp"], "fp": alone["b"]["fp"]}


def test_a_log_on_one_side_only_is_listed_and_counts_as_lost(versions, capsys, tmp_path):
    partial = tmp_path / "b"
    partial.mkdir()
    shutil.copy(versions["b"] / "drive_loops.mcap", partial)
    code, out, _ = run(capsys, versions["a"], partial, *POSES, "--json", "--fail-on", "lost-true")
    assert code == ExitCode.REGRESSION
    document = json.loads(out)
    assert document["only_a"] == ["drive_parked.ros2.mcap"]
    lost = next(row for row in document["logs"] if row["state"] == "only in A")
    assert document["gate"]["figures"]["lost-true"] >= lost["tp_fp"]["a"]["tp"] > 0


def test_the_gate_fails_on_new_false_pairs_and_passes_within_its_limit(versions, capsys):
    a, b = versions["a"], versions["b"]
    code, out, _ = run(capsys, a, b, *POSES, "--fail-on", "new-false")
    assert code == ExitCode.REGRESSION
    assert "gate new-false: FAILED: new-false:" in out
    code, out, _ = run(capsys, a, b, *POSES, "--json", "--fail-on", "new-false")
    new_false = json.loads(out)["gate"]["figures"]["new-false"]
    code, out, _ = run(capsys, a, b, *POSES, "--fail-on", f"new-false={new_false}")
    assert code == ExitCode.OK, out  # different, but no rule broken
    code, _, _ = run(capsys, a, a, *POSES, "--fail-on", "new-false,lost-true,coverage-drop")
    assert code == ExitCode.OK
    code, _, _ = run(capsys, b, a, *POSES, "--fail-on", "lost-pairs")
    assert code == ExitCode.REGRESSION  # A reports pairs that the other lost


def test_gate_rules_that_need_ground_truth_are_refused_without_it(versions, capsys):
    code, _, err = run(capsys, versions["a"], versions["b"], "--fail-on", "new-false")
    assert code == ExitCode.USAGE and "needs ground truth" in err
    code, _, err = run(capsys, versions["a"], versions["b"], "--fail-on", "new-pairs=1")
    assert code == ExitCode.REGRESSION  # drive_loops and drive_parked each gained pairs
    code, _, err = run(capsys, versions["a"], versions["b"], "--gt", SAMPLES / "drive_loops.gt.npz")
    assert code == ExitCode.USAGE and "--gt-topic" in err


def test_the_report_has_the_table_and_its_pictures(versions, capsys, tmp_path):
    report = tmp_path / "report.md"
    code, _, _ = run(capsys, versions["a"], versions["b"], *POSES, "--report", report)
    assert code == ExitCode.DIFFERENT
    text = report.read_text()
    assert "| drive_parked.ros2.mcap | compared |" in text
    pictures = sorted(p.name for p in tmp_path.glob("*.png"))
    assert pictures == ["report-changes.png", "report-trajectory-1.png", "report-trajectory-2.png"]
    for name in pictures:
        assert f"]({name})" in text
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_report_that_cannot_be_written_is_refused_before_the_work(versions, capsys, tmp_path):
    report = tmp_path / "no-such-folder" / "report.md"
    code, out, err = run(capsys, versions["a"], versions["b"], *POSES, "--report", report)
    assert code == ExitCode.OUTPUT_ERROR and out == ""
    assert err.strip().endswith(f"{report}: cannot create the output: no folder {report.parent}")


@pytest.mark.parametrize(
    ("rules", "limits"),
    [
        ("new-false", {"new-false": 0.0}),
        ("new-false,lost-true=2, coverage-drop=1.5", {"new-false": 0, "lost-true": 2,
                                                      "coverage-drop": 1.5}),
    ],
)  # fmt: skip
def test_gate_rules_parse(rules, limits):
    assert parse_gate(rules).limits == limits


@pytest.mark.parametrize(
    "rules", ["", "new-falses", "lost-true=-1", "coverage-drop=nan", "new-false=x"]
)
def test_bad_gate_rules_are_usage_errors(rules):
    with pytest.raises(UsageError, match="--fail-on"):
        parse_gate(rules)


def test_coverage_drop_is_the_worst_window_in_points():
    gate = parse_gate("coverage-drop=2")
    assert gate.failures(GateFigures(0, 0, 0, 0, {1.0: 2.5, 5.0: 0.0})) == [
        "coverage-drop: 2.5 > 2"
    ]
    assert gate.failures(GateFigures(0, 0, 0, 0, {1.0: 1.9, 5.0: -3.0})) == []
