"""`doseqslam-logs batch`: discovery, parallel runs, failures, the manifest and resuming.

Logs are copies of the committed samples, annotated over their first seconds only (-E) so that
each batch run takes a few seconds.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
from dataclasses import replace
from pathlib import Path

import pytest

from doseqslam_logs.batch import local
from doseqslam_logs.batch.discovery import discover_logs, output_name
from doseqslam_logs.batch.job import Job, Outcome, options_hash
from doseqslam_logs.batch.manifest import Entry, read_entries
from doseqslam_logs.batch.report import ConsoleDisplay
from doseqslam_logs.batch.runner import BatchPlan, plan_batch
from doseqslam_logs.cli.annotate import annotate_options_from_args
from doseqslam_logs.cli.main import build_parser, main
from doseqslam_logs.cli.params_args import run_parameters
from doseqslam_logs.detector import Parameters
from doseqslam_logs.errors import UsageError
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.sources.digest import source_sha256

pytestmark = pytest.mark.slow  # the pipeline runs in its fixtures (pyproject: markers)

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "sample_logs"
T0_NS = 1_700_000_000 * 10**9  # first frame of every sample
END_NS = T0_NS + 15 * 10**9  # 30 frames at 2 Hz: enough to run every stage, fast
END = str(END_NS)


def annotate_settings(*argv: str) -> tuple[Parameters, AnnotateOptions]:
    """The parameters and options `annotate` builds from these options (its defaults)."""
    args = build_parser().parse_args(["annotate", "log.mcap", "-o", "out.mcap", *argv])
    return run_parameters(args), annotate_options_from_args(args, args.workers)


def run_batch_cli(*argv: str) -> tuple[int, str, str]:
    """main() in this process, with stdout and stderr captured (usable in module fixtures)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["batch", *argv])
    return code, out.getvalue(), err.getvalue()


def truncated_copy(source: Path, target: Path, size: int = 300_000) -> Path:
    target.write_bytes(source.read_bytes()[:size])
    return target


def build_tree(root: Path) -> Path:
    """logs/a/drive_loops.ros2.mcap, logs/b/ the same name plus a rosbag2 folder, a broken
    MCAP cut short, and a file that is not a log."""
    logs = root / "logs"
    (logs / "a").mkdir(parents=True)
    (logs / "b").mkdir()
    shutil.copy(SAMPLES / "drive_loops.ros2.mcap", logs / "a")
    shutil.copy(SAMPLES / "drive_loops.ros2.mcap", logs / "b")
    shutil.copytree(SAMPLES / "drive_loops.rosbag2", logs / "b" / "drive_loops.rosbag2")
    truncated_copy(SAMPLES / "drive_parked.ros2.mcap", logs / "broken.mcap")
    (logs / "notes.txt").write_text("not a log\n")
    return logs


@pytest.fixture(scope="module")
def first_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, int, str, str]:
    root = tmp_path_factory.mktemp("batch")
    logs = build_tree(root)
    out = root / "out"
    code, stdout, stderr = run_batch_cli(str(logs), "-o", str(out), "-j", "2", "-E", END)
    return logs, out, code, stdout, stderr


def manifest(out: Path) -> list[Entry]:
    return list(read_entries(out / "manifest.jsonl"))


def test_every_log_is_annotated_under_its_mirrored_path_and_the_broken_one_fails(
    first_run,
) -> None:
    _, out, code, _, stderr = first_run
    assert code == 1  # one log failed
    outputs = sorted(p.relative_to(out).as_posix() for p in out.rglob("*.mcap"))
    assert outputs == [
        "a/drive_loops.ros2.annotated.mcap",
        "b/drive_loops.ros2.annotated.mcap",
        "b/drive_loops.rosbag2.annotated.mcap",  # the folder is one log, its .db3 is not another
    ]
    failed = [line for line in stderr.splitlines() if "FAILED" in line]
    assert len(failed) == 1
    assert failed[0].startswith("[") and "broken.mcap: FAILED (3 unreadable input)" in failed[0]
    assert "truncated MCAP" in failed[0]
    assert "doseqslam-logs: error: 1 of 4 logs failed" in stderr
    assert not list(out.rglob("*.tmp")) and not list(out.rglob(".*"))


def test_plain_progress_lines_and_summary_table(first_run) -> None:
    _, _, _, stdout, stderr = first_run
    finished = [line for line in (stdout + stderr).splitlines() if line.startswith("[")]
    assert sorted(line.split(" logs,")[0] for line in finished) == ["[1/4", "[2/4", "[3/4", "[4/4"]
    assert all(" failed, " in line for line in finished)
    assert "\r" not in stdout + stderr  # not a terminal: nothing is redrawn
    table = stdout[stdout.index("status  frames") :].splitlines()
    assert table[1].split()[:5] == ["ok", "30", *table[1].split()[2:4], "0"]
    assert [row.split()[-1] for row in table[1:4]] == [
        "a/drive_loops.ros2.mcap",
        "b/drive_loops.ros2.mcap",
        "b/drive_loops.rosbag2",
    ]
    assert table[4].split()[:2] == ["FAILED", "-"] and "(3 unreadable input)" in table[4]
    assert table[5].startswith("4 logs: 3 annotated, 0 up to date, 1 failed; 90 frames")


def test_manifest_has_one_complete_entry_per_attempt(first_run) -> None:
    logs, out, _, _, _ = first_run
    entries = {Path(e.input).relative_to(logs).as_posix(): e for e in manifest(out)}
    assert sorted(entries) == [
        "a/drive_loops.ros2.mcap",
        "b/drive_loops.ros2.mcap",
        "b/drive_loops.rosbag2",
        "broken.mcap",
    ]
    params, options = annotate_settings("-E", END)
    for name, entry in entries.items():
        assert entry.sha256 == source_sha256(logs / name)
        assert entry.parameters_hash == params.hash
        assert entry.options_hash == options_hash(options)
        assert entry.tool_version and entry.engine == "local"
        assert entry.stamp is not None and entry.stamp.size > 0
    ok = entries["a/drive_loops.ros2.mcap"]
    assert ok.status == "ok" and ok.exit_code == 0 and ok.error == ""
    assert ok.output == str(out.resolve() / "a" / "drive_loops.ros2.annotated.mcap")
    assert ok.counts.frames == 30 and ok.counts.sequences > 0 and ok.counts.skipped == 0
    assert ok.timings["total_s"] >= ok.timings["replay_s"] > 0
    bad = entries["broken.mcap"]
    assert (bad.status, bad.exit_code, bad.counts.frames) == ("failed", 3, 0)
    assert bad.error.startswith(str(logs / "broken.mcap")) and "truncated" in bad.error
    # Every line is one JSON object ending in a newline (appended whole).
    raw = (out / "manifest.jsonl").read_text()
    assert raw.endswith("\n") and all(json.loads(line) for line in raw.splitlines())


def test_outputs_are_byte_identical_to_annotate_log(first_run, tmp_path) -> None:
    logs, out, _, _, _ = first_run
    for name, output in [
        ("a/drive_loops.ros2.mcap", "a/drive_loops.ros2.annotated.mcap"),
        ("b/drive_loops.rosbag2", "b/drive_loops.rosbag2.annotated.mcap"),
    ]:
        direct = tmp_path / "direct.mcap"
        annotate_log(logs / name, direct, *annotate_settings("-E", END))
        assert direct.read_bytes() == (out / output).read_bytes(), name


def test_rerun_skips_what_is_done_and_redoes_what_changed_or_failed(tmp_path) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    shutil.copy(SAMPLES / "drive_loops.ros2.mcap", logs / "one.mcap")
    shutil.copy(SAMPLES / "drive_loops.ros2.mcap", logs / "two.mcap")
    truncated_copy(SAMPLES / "drive_loops.ros2.mcap", logs / "bad.mcap")
    out = tmp_path / "out"
    args = (str(logs), "-o", str(out), "-j", "2", "-E", END)

    def attempts() -> list[str]:
        return [Path(e.input).name for e in manifest(out)]

    def mtimes() -> dict[str, int]:
        return {p.name: p.stat().st_mtime_ns for p in out.glob("*.annotated.mcap")}

    assert run_batch_cli(*args)[0] == 1
    assert sorted(attempts()) == ["bad.mcap", "one.mcap", "two.mcap"]
    before = mtimes()

    code, stdout, _ = run_batch_cli(*args)  # the failed one is retried, the others skipped
    assert code == 1 and attempts()[3:] == ["bad.mcap"] and mtimes() == before
    assert "2 of 3 logs up to date" in stdout

    # Repaired and modified logs are redone; a touched one (same bytes) is not.
    shutil.copy(SAMPLES / "drive_loops.ros2.mcap", logs / "bad.mcap")
    shutil.copy(SAMPLES / "drive_parked.ros2.mcap", logs / "two.mcap")
    os.utime(logs / "one.mcap", ns=(1, 1))
    assert run_batch_cli(*args)[0] == 0
    assert sorted(attempts()[4:]) == ["bad.mcap", "two.mcap"]
    assert mtimes()["one.annotated.mcap"] == before["one.annotated.mcap"]
    assert manifest(out)[-1].status == "ok"

    code, stdout, _ = run_batch_cli(*args)  # all done: nothing runs
    assert code == 0 and len(attempts()) == 6
    assert "3 of 3 logs up to date" in stdout and "0 annotated, 3 up to date" in stdout

    # What a run would redo (plan only): other parameters or options redo every log, a
    # deleted output its log.
    found = discover_logs([str(logs)], out)
    params, options = annotate_settings("-E", END)

    def planned(params: Parameters, options: AnnotateOptions) -> list[str]:
        return sorted(job.input.name for job in plan_batch(found, out, params, options).to_run)

    assert planned(params, options) == []
    assert planned(params.replace(kappa_s=20.0), options) == ["bad.mcap", "one.mcap", "two.mcap"]
    assert planned(params, replace(options, verification=None)) == [
        "bad.mcap",
        "one.mcap",
        "two.mcap",
    ]
    (out / "one.annotated.mcap").unlink()
    assert planned(params, options) == ["one.mcap"]

    assert run_batch_cli(*args, "--force")[0] == 0  # --force: every log again
    assert sorted(attempts()[6:]) == ["bad.mcap", "one.mcap", "two.mcap"]
    assert (out / "one.annotated.mcap").is_file()


def test_directories_globs_and_files_mirror_their_common_folder(tmp_path) -> None:
    root = tmp_path / "fleet"
    for path in [
        "day1/cam.mcap",
        "day1/cam.bag",  # same stem, other suffix: cam.bag.annotated.mcap
        "day2/cam.mcap",  # same name, other folder
        "day2/old.annotated.mcap",  # an output of ours: left out of the search
        "day2/readme.md",
        "day3/bag/metadata.yaml",  # rosbag2 folder: one log
        "day3/bag/bag_0.db3",
        "day3/bag/bag_1.mcap",
        "day3/lone.db3",  # a .db3 outside a rosbag2 folder is a log
        "out/x.mcap",  # inside OUTDIR: left out
    ]:
        (root / path).parent.mkdir(parents=True, exist_ok=True)
        (root / path).write_bytes(b"")
    found = discover_logs([str(root)], root / "out")
    assert [(log.path.relative_to(root).as_posix(), str(log.relative_output)) for log in found] == [
        ("day1/cam.bag", "day1/cam.bag.annotated.mcap"),
        ("day1/cam.mcap", "day1/cam.annotated.mcap"),
        ("day2/cam.mcap", "day2/cam.annotated.mcap"),
        ("day3/bag", "day3/bag.annotated.mcap"),
        ("day3/lone.db3", "day3/lone.db3.annotated.mcap"),
    ]
    by_glob = discover_logs([str(root / "day*" / "cam.mcap")], tmp_path / "o")
    assert [str(log.relative_output) for log in by_glob] == [
        "day1/cam.annotated.mcap",
        "day2/cam.annotated.mcap",
    ]
    # Two folders and a file: named relative to their common folder; duplicates count once.
    mixed = discover_logs(
        [str(root / "day3"), str(root / "day1" / "cam.mcap"), str(root / "day1/cam.mcap")],
        tmp_path / "o",
    )
    assert [str(log.relative_output) for log in mixed] == [
        "day3/bag.annotated.mcap",
        "day3/lone.db3.annotated.mcap",
        "day1/cam.annotated.mcap",
    ]
    # The rosbag2 folder named directly is one log; a file named directly is always taken.
    assert [str(x.relative_output) for x in discover_logs([str(root / "day3/bag")], root)] == [
        "bag.annotated.mcap"
    ]
    assert discover_logs([str(root / "day2/readme.md")], root)[0].path.name == "readme.md"


@pytest.mark.parametrize(
    ("inputs", "message"),
    [
        (["missing.mcap"], "no such file or directory"),
        (["nothing*.mcap"], "no file matches this pattern"),
        (["empty"], "no logs"),
        (["clash"], "would both be written to"),
    ],
)
def test_discovery_refuses_what_cannot_be_run(tmp_path, monkeypatch, inputs, message) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "empty").mkdir()
    (tmp_path / "clash" / "x").mkdir(parents=True)  # a folder x and a file x.mcap
    (tmp_path / "clash" / "x.mcap").write_bytes(b"")
    (tmp_path / "clash" / "x" / "metadata.yaml").write_text("")
    assert output_name(tmp_path / "clash" / "x") == output_name(tmp_path / "clash" / "x.mcap")
    with pytest.raises(UsageError, match=message):
        discover_logs(inputs, tmp_path / "out")


def test_usage_errors_exit_2_before_anything_runs(tmp_path, capsys, monkeypatch) -> None:
    out = tmp_path / "out"
    log = str(SAMPLES / "drive_loops.ros2.mcap")
    assert main(["batch", str(tmp_path / "missing"), "-o", str(out)]) == 2
    assert "no such file or directory" in capsys.readouterr().err
    assert main(["batch", log, "-o", str(out), "--address", "ray://x:1"]) == 2
    assert "--engine ray" in capsys.readouterr().err
    assert main(["batch", log, "-o", str(out), "--set", "kappa_s=fast"]) == 2
    assert "kappa_s must be float" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "ray", None)  # as if the extra were not installed
    assert main(["batch", log, "-o", str(out), "--engine", "ray"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "needs Ray: pip install 'doseqslam-logs[ray]'" in err
    assert not out.exists()


class Collected:
    """Events that keep what an engine reports."""

    def __init__(self) -> None:
        self.outcomes: list[Outcome] = []
        self.frames_done: dict[str, int] = {}
        self.frames_expected: dict[str, int | None] = {}

    def expected(self, key: str, total: int | None) -> None:
        self.frames_expected[key] = total

    def progress(self, key: str, done: int) -> None:
        self.frames_done[key] = done

    def stage(self, key: str, name: str) -> None:
        pass

    def finished(self, outcome: Outcome) -> None:
        self.outcomes.append(outcome)

    def tick(self) -> None:
        pass


def crash_on_crash_logs(job: Job) -> Outcome:
    """A worker that dies outright (as if killed by the OOM killer) on logs named crash*."""
    if job.input.name.startswith("crash"):
        os.kill(os.getpid(), signal.SIGKILL)
    return local._work(job)


def test_a_crashed_worker_fails_only_its_log(tmp_path) -> None:
    names = ["crash.mcap", "a.mcap"]  # run side by side: the pool breaks under both
    jobs = []
    for name in names:
        shutil.copy(SAMPLES / "drive_loops.ros2.mcap", tmp_path / name)
        jobs.append(
            Job(
                str(tmp_path / name),
                tmp_path / name,
                tmp_path / "out" / f"{name}.annotated.mcap",
                Parameters(),
                AnnotateOptions(end_ns=END_NS, verification=None),
                name=name,
            )
        )
    events = Collected()
    local.LocalEngine(2, work=crash_on_crash_logs).run(jobs, events)
    by_name = {Path(o.key).name: o for o in events.outcomes}
    assert sorted(by_name) == sorted(names)  # each reported exactly once
    assert len(events.outcomes) == 2 and by_name["a.mcap"].ok
    crashed = by_name["crash.mcap"]
    assert (crashed.status, crashed.exit_code, crashed.error_kind) == (
        "failed",
        70,
        "worker crashed",
    )
    assert crashed.error == f"{tmp_path / 'crash.mcap'}: worker crashed: the worker process died"
    assert crashed.sha256 == source_sha256(tmp_path / "crash.mcap")
    assert events.frames_expected[str(tmp_path / "a.mcap")] == 240  # progress came from the workers
    assert (tmp_path / "out" / "a.mcap.annotated.mcap").is_file()
    assert not (tmp_path / "out" / "crash.mcap.annotated.mcap").exists()


def _marked_processes(marker: str) -> list[int]:
    """Processes whose environment holds `marker` (the batch and every worker it spawned)."""
    pids = []
    for environ in Path("/proc").glob("[0-9]*/environ"):
        with contextlib.suppress(OSError):
            if marker.encode() in environ.read_bytes():
                pids.append(int(environ.parent.name))
    return pids


def _reading(marker: str, folder: Path) -> list[int]:
    """The marked processes that have a file of `folder` open."""
    busy = []
    for pid in _marked_processes(marker):
        with contextlib.suppress(OSError):
            targets = [os.readlink(fd) for fd in Path(f"/proc/{pid}/fd").iterdir()]
            if any(target.startswith(str(folder)) for target in targets):
                busy.append(pid)
    return busy


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="needs /proc")
def test_sigterm_stops_every_worker_and_leaves_no_partial_output(tmp_path) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    for name in ("one.mcap", "two.mcap"):
        shutil.copy(SAMPLES / "drive_parked.ros2.mcap", logs / name)
    out = tmp_path / "out"
    marker = f"DOSEQSLAM_BATCH_TEST={uuid.uuid4().hex}"
    env = {**os.environ, marker.split("=")[0]: marker.split("=")[1]}
    command = [sys.executable, "-m", "doseqslam_logs.cli.main", "batch", str(logs)]
    proc = subprocess.Popen(
        [*command, "-o", str(out), "-j", "2"], env=env, stderr=subprocess.PIPE, text=True
    )
    deadline = time.monotonic() + 60
    # Asserted on the poll that saw it: a second look can miss a worker between its
    # reads of the log, or while /proc momentarily refuses its environ.
    while (busy := len(_reading(marker, logs))) < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert busy == 2  # both workers are annotating a log
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 143, stderr
    assert stderr.strip().splitlines()[-1] == "doseqslam-logs: terminated"
    leftovers = [p.name for p in out.rglob("*")] if out.exists() else []
    assert all(name == "manifest.jsonl" for name in leftovers), leftovers
    deadline = time.monotonic() + 10
    while _marked_processes(marker) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _marked_processes(marker) == []


class FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_terminal_status_line_shows_logs_frames_and_eta() -> None:
    now = [100.0]
    out, err = FakeTerminal(), FakeTerminal()
    display = ConsoleDisplay(out, err, clock=lambda: now[0])
    jobs = [
        Job(
            f"/l/{n}",
            Path(f"/l/{n}"),
            Path(f"/o/{n}"),
            Parameters(),
            AnnotateOptions(verification=None),
            n,
            100,
        )
        for n in ("a.mcap", "b.mcap")
    ]
    display.start(BatchPlan(jobs, []))
    display.expected(jobs[0], 40)
    display.progress(jobs[0], 10)
    now[0] = 110.0
    display.tick()
    status = err.getvalue().rsplit("\r\x1b[K", 1)[-1]
    # 10 of 40 frames of one of two equal logs: 1/8 of the bytes in 10 s, 70 s to go.
    assert status == "batch: 0/2 logs, 0 failed, 10 s, ETA 1:10 min | a.mcap 10/40"
    display.finished(jobs[0], Outcome(jobs[0].key, "failed", error="a.mcap: bad", error_kind="3 x"))
    assert err.getvalue().count("a.mcap: FAILED (3 x): a.mcap: bad\n") == 1
    assert err.getvalue().endswith("batch: 1/2 logs, 1 failed, 10 s, ETA 10 s")
    display.close()
    assert err.getvalue().endswith("\r\x1b[K") and out.getvalue() == ""


def test_options_hash_follows_what_changes_the_output() -> None:
    _, options = annotate_settings("-E", END)
    same = options_hash(options)
    assert options_hash(replace(options, workers=7)) == same
    assert options_hash(replace(options, end_ns=END_NS + 1)) != same
    assert options_hash(replace(options, verification=None)) != same  # --no-verify
    assert options_hash(annotate_settings("-E", END, "--vset", "min_inliers=40")[1]) != same
