"""`evaluate --images` verifies the candidate pairs geometrically by default (as annotate does)
and reports raw and verified figures side by side; `--no-verify` is the paper's report."""

from __future__ import annotations

import contextlib
import io
import json
import re
from pathlib import Path
from typing import Any

import pytest
from golden import RTABMAP_LOOP_EVENTS, RTABMAP_PAPER_TP

from doseqslam_logs.cli.main import main
from doseqslam_logs.errors import ExitCode
from doseqslam_logs.evaluation.folder_run import FolderEvaluation, evaluate_folder
from doseqslam_logs.verification import (
    VERIFIED_THRESHOLD,
    VerificationParameters,
    verified_detector_parameters,
)

# What `evaluate --images` printed on the RTAB-Map samples before verification existed (the
# paper's decision); only the speed varies.


def _run(*argv: object) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        code = main([str(a) for a in argv])
    return code, out.getvalue()


def _args(shared_data: Path) -> list[object]:
    folder = shared_data / "rtabmap_samples_loop"
    return [
        "evaluate",
        "--images",
        folder / "images",
        "--fps",
        "1",
        "--gt",
        folder / "samples_GT.bmp",
        "--set",
        "kappa_s=10",
    ]


@pytest.fixture(scope="module")
def verified_run(shared_data: Path) -> FolderEvaluation:
    """What `evaluate --images ... --set kappa_s=10` runs (verification on, its defaults)."""
    folder = shared_data / "rtabmap_samples_loop"
    params = verified_detector_parameters(kappa_s=10.0)
    return evaluate_folder(folder / "images", 1.0, folder / "samples_GT.bmp", params)


@pytest.fixture(scope="module")
def verified_runs(verified_run: FolderEvaluation) -> tuple[str, dict[str, Any]]:
    """The default (verified) report as text and as --json, of one run."""
    return verified_run.format_report(), json.loads(json.dumps(verified_run.to_json_dict()))


def test_the_command_prints_the_librarys_report(shared_data, verified_runs) -> None:
    code, text = _run(*_args(shared_data))
    timing = re.compile(r"\d+ frames/s|\d+\.\d ms each, \d+\.\d s")
    assert code == 0
    assert timing.sub("<t>", text) == timing.sub("<t>", verified_runs[0] + "\n")
    code, out = _run(*_args(shared_data), "--json")
    document = json.loads(out)
    for doc in (document, verified_runs[1]):
        doc.pop("wall_time_s")
        doc["verification_cost"].pop("ms_per_pair")
        doc["verification_cost"].pop("wall_time_s")
    assert code == 0 and document == verified_runs[1]


@pytest.fixture(scope="module")
def verified_json(verified_runs: tuple[str, dict[str, Any]]) -> dict[str, Any]:
    return verified_runs[1]


@pytest.fixture(scope="module")
def verified_text(verified_runs: tuple[str, dict[str, Any]]) -> str:
    return verified_runs[0]


def test_verified_figures_on_the_rtabmap_samples(verified_json) -> None:
    doc = verified_json
    verified = doc["verified"]
    assert verified is not None
    # th defaults to the verified one, as annotate's; raw and verified are scored at it.
    assert doc["parameters"]["threshold"] == VERIFIED_THRESHOLD
    assert doc["threshold"] == verified["threshold"] == VERIFIED_THRESHOLD
    assert verified["r_p100"] >= 0.60
    assert verified["fp"] == 0 and verified["tp"] > 0  # at the recorded th
    assert verified["r_p100"] > doc["r_p100"]
    # Every raw figure has its verified counterpart.
    raw = {k for k in doc if k in verified}
    assert raw == set(verified)
    cost = doc["verification_cost"]
    assert doc["verification"] == "on"
    assert doc["verification_hash"] == VerificationParameters().hash
    assert cost["candidate_pairs"] == doc["tp"] + doc["fp"]
    assert cost["accepted_pairs"] == verified["tp"] + verified["fp"]
    assert cost["frame_pairs_checked"] >= cost["candidate_pairs"] > 0
    # RTAB-Map with the ORB segmentation of verified runs, its features shared with
    # verification: 2 of the 40 accepted pairs are on a next-best trajectory (0 with its own
    # extraction, 1 with SIFT's sequences); they pass the second guess's doubled bar.
    assert cost["accepted_on_alternatives"] <= 2


def test_verified_report_puts_raw_and_verified_side_by_side(verified_text, verified_json) -> None:
    lines = verified_text.splitlines()
    cost = verified_json["verification_cost"]
    on_alternatives = cost["accepted_on_alternatives"]
    alternatives = f", {on_alternatives} of them on a next-best trajectory" * bool(on_alternatives)
    assert re.search(
        rf"; verification {VerificationParameters().hash}: {cost['candidate_pairs']} candidate "
        rf"pairs verified, {cost['accepted_pairs']} accepted{alternatives} "
        rf"\({cost['frame_pairs_checked']} "
        r"frame pairs checked, \d+\.\d ms each, \d+\.\d s; fundamental matrix, no intrinsics\)$",
        lines[0],
    )
    assert lines[4].startswith("threshold th     : 0.99 (default with verification;")
    assert lines[5].split() == ["raw", "(all", "candidates)", "verified", "(accepted", "pairs)"]
    v = verified_json["verified"]
    reported = lines[6]
    assert reported.startswith("reported pairs   : ")
    assert reported.endswith(f"{v['tp'] + v['fp']} (TP {v['tp']}, FP {v['fp']})")


def test_no_verify_prints_the_papers_one_column_report(shared_data: Path) -> None:
    """The whole report is docs/cli.md's --no-verify block (tests/test_readme.py checks it
    line by line); here: one column, the paper's th, no verification header."""
    code, out = _run(*_args(shared_data), "--no-verify")
    assert code == 0 and "verification" not in out and "raw (all candidates)" not in out
    assert "threshold th     : 0.75 (tolerance +-0 frames)" in out
    assert f"reported pairs   : {RTABMAP_PAPER_TP} (TP {RTABMAP_PAPER_TP}, FP 0)" in out


def test_no_verify_json_has_no_verified_figures(shared_data: Path) -> None:
    code, out = _run(*_args(shared_data), "--no-verify", "--json")
    doc = json.loads(out)
    assert code == 0 and doc["verified"] is None and doc["verification"] == "off"
    assert (doc["tp"], doc["fp"], doc["threshold"]) == (9, 0, 0.75)
    assert doc["r_p100"] == pytest.approx(RTABMAP_PAPER_TP / RTABMAP_LOOP_EVENTS)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--vset", "min_inlier=3"], "unknown verification parameter"),
        (["--intrinsics", "1,2"], "--intrinsics expects four numbers"),
    ],
)
def test_bad_verification_options_fail_before_the_run(shared_data, capsys, extra, message) -> None:
    code = main([str(a) for a in [*_args(shared_data), *extra]])
    assert code == ExitCode.USAGE and message in capsys.readouterr().err


def test_verification_options_are_refused_with_an_annotated_log(capsys) -> None:
    log = Path(__file__).resolve().parents[1] / "sample_logs" / "drive_loops.ros2.mcap"
    code = main(["evaluate", str(log), "--gt", "x.npz", "--no-verify"])
    err = capsys.readouterr().err
    assert code == ExitCode.USAGE and "--no-verify" in err and "--images only" in err
