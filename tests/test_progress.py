"""Every stage shown: the run reports how far verification, the metric fits and the write are
(`StageObserver.advanced`), and the command line's Progress draws a bar with the time left on a
terminal and, off one, a line per stage once a run is past QUIET_S (short runs stay silent)."""

from __future__ import annotations

import io
import json
import re
from collections import defaultdict
from pathlib import Path

import pytest

from doseqslam_logs.cli import progress as progress_module
from doseqslam_logs.cli.main import main
from doseqslam_logs.cli.progress import Progress, remaining
from doseqslam_logs.pipeline.annotate import annotate_log
from doseqslam_logs.pipeline.stages import StageObserver

SAMPLE = Path(__file__).resolve().parents[1] / "sample_logs" / "drive_loops.ros2.mcap"


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


class Counts(StageObserver):
    def __init__(self) -> None:
        self.advanced_by: dict[str, list[tuple[int, int | None]]] = defaultdict(list)
        self.order: list[str] = []

    def started(self, stage: str) -> None:
        self.order.append(stage)

    def advanced(self, stage: str, done: int, total: int | None) -> None:
        self.advanced_by[stage].append((done, total))


class Watched(StageObserver):
    """One run heard by every observer the tests look at: the stage counts, and the command's
    Progress on a terminal, off one in a run shorter than QUIET_S (quiet), and off one in a
    run past it (lines). The replay's frames go to the terminal's, as `annotate` passes them."""

    def __init__(self) -> None:
        self.counts = Counts()
        self.streams = {"terminal": Terminal(), "quiet": io.StringIO(), "lines": io.StringIO()}
        self.shown = {name: Progress(None, "annotate", s) for name, s in self.streams.items()}
        # As if the run were shorter than QUIET_S, or longer, whatever the machine's load.
        self.shown["quiet"]._past_quiet = lambda: False  # type: ignore[method-assign]
        self.shown["lines"]._past_quiet = lambda: True  # type: ignore[method-assign]
        self._observers: list[StageObserver] = [self.counts, *self.shown.values()]

    def __call__(self, done: int) -> None:
        self.shown["terminal"](done)

    def started(self, stage: str) -> None:
        for observer in self._observers:
            observer.started(stage)

    def advanced(self, stage: str, done: int, total: int | None) -> None:
        for observer in self._observers:
            observer.advanced(stage, done, total)

    def text(self, name: str) -> str:
        self.shown[name].close()
        return self.streams[name].getvalue()


@pytest.fixture(scope="module")
def watched(tmp_path_factory: pytest.TempPathFactory) -> Watched:
    run = Watched()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(progress_module, "LINE_EVERY_S", 0.0)  # off a terminal: every count a line
        out = tmp_path_factory.mktemp("run") / "out.mcap"
        annotate_log(SAMPLE, out, progress=run, observer=run)
    return run


@pytest.mark.slow
def test_every_stage_after_the_replay_reports_its_count_up_to_its_total(watched: Watched) -> None:
    counts = watched.counts
    assert counts.order == ["replay", "verify", "metric", "write"]
    verify = counts.advanced_by["verify"]
    assert [done for done, _ in verify] == list(range(1, 33))  # the sample's 32 sequences
    assert {total for _, total in verify} == {32}
    metric = counts.advanced_by["metric"]
    assert metric and metric[-1][0] == metric[-1][1] > 0
    write = counts.advanced_by["write"]
    totals = {total for _, total in write}
    assert len(totals) == 1 and write[-1][0] <= totals.pop()  # in steps, up to the total
    assert [done for done, _ in write] == sorted(done for done, _ in write)


@pytest.mark.slow
def test_on_a_terminal_each_stage_has_its_bar_and_time_left(watched: Watched) -> None:
    text = watched.text("terminal")
    for stage, unit in (("verify", "sequences"), ("metric", "fits"), ("write", "messages")):
        assert re.search(rf"annotate {stage} \[[#-]{{30}}\] \d+/\d+ {unit}", text), stage
    assert "verifying the candidate pairs geometrically" in text and "writing the output" in text


@pytest.mark.slow
def test_off_a_terminal_a_short_run_prints_nothing_and_a_long_one_a_line_per_stage(
    watched: Watched,
) -> None:
    assert watched.text("quiet") == ""
    text = watched.text("lines")
    assert "\r" not in text
    for line in ("annotate: verifying the candidate pairs geometrically", "annotate: writing"):
        assert line in text
    assert re.search(r"^annotate verify \[#{30}\] 32/32 sequences", text, re.MULTILINE)


def test_the_time_left_is_the_rate_so_far() -> None:
    assert remaining(25, 100, 10.0) == ", 0:30 left"
    assert remaining(1, 10_000, 1.0) == ", 2:46:39 left"
    assert remaining(0, 100, 5.0) == remaining(100, 100, 5.0) == remaining(5, None, 1.0) == ""


@pytest.mark.slow
def test_annotate_json_has_every_figure_of_the_summary_line(tmp_path: Path, capsys) -> None:
    assert main(["annotate", str(SAMPLE), "-o", str(tmp_path / "out.mcap"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["loop_closures"] == doc["verification"]["accepted"] == 83
    verification = doc["verification"]
    assert verification["model"] == "essential" and verification["wall_time_s"] > 0
    assert verification["frame_pairs"] > 0 and verification["ms_per_pair"] > 0
    metric = doc["metric"]
    assert metric["pairs"] == 83 and sum(metric["methods"].values()) == 83
    assert metric["odometry_topic"] == "/odom" and metric["methods"]["odometry_pnp"] > 0
    assert doc["log_time_fallbacks"] == 0 and doc["frames_per_second"] > 0


def test_evaluate_of_an_annotated_log_says_each_stage_off_a_terminal(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    """Scoring an 8-hour log takes minutes (reading 290,000 records, its pose topic): past
    QUIET_S, a line as each part begins, the report on stdout unchanged."""
    from doseqslam_logs.detector import Parameters
    from doseqslam_logs.evaluation.log_run import LogEvaluationOptions, evaluate_log
    from doseqslam_logs.pipeline.annotate import AnnotateOptions

    out = tmp_path / "drive_loops.annotated.mcap"
    annotate_log(SAMPLE, out, Parameters(), AnnotateOptions(verification=None))
    seen: list[str] = []
    options = LogEvaluationOptions(gt_topic="/ground_truth/pose", radius=2.0)
    evaluate_log(out, options, stage=seen.append)
    assert seen == ["read", "truth", "score"]
    args = ["evaluate", str(out), "--gt-topic", "/ground_truth/pose", "--radius", "2"]
    monkeypatch.setattr(progress_module, "QUIET_S", 0.0)
    assert main(args) == 0
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [
        "evaluate: reading the annotations",
        "evaluate: reading the ground truth",
        "evaluate: scoring the run",
    ]
    assert "ground truth     : /ground_truth/pose (within 2 m" in captured.out
    monkeypatch.setattr(progress_module, "QUIET_S", 3600.0)
    assert main(args) == 0
    assert capsys.readouterr().err == ""
