"""Issue #21, item 5: signals are heard in every stage, and no process outlives its batch.

Each test runs the real command in a subprocess whose stderr is a terminal (a pty), so that it
draws its progress: the frame line of the replay, then a line as verification and writing
begin (the batch's status line names the stage of each running log). The test waits for the
stage's line, sends the signal, and checks the documented exit code, that nothing but the
inputs is left (no output, no temporary file) and that the inputs are unchanged. The logs are
built here from the sample log, long enough that each stage lasts many seconds after its line
appears: without a stop inside the stage, the command would run on for all of it.

Stop latencies are printed (pytest -s) and asserted only against a generous bound
(STOP_BOUND_S): the promise is 2 s (docs/robustness.md), the bound keeps a loaded CI machine
from failing a correct build, and a stage that does not hear the signal takes far longer.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import pty
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from doseqslam_logs.errors import ExitCode
from doseqslam_logs.sources import open_source
from doseqslam_logs.verification import DEFAULT_VERIFICATION, stage
from doseqslam_logs.verification.stage import Cancelled, Verifier, verify_in_threads

SAMPLE = Path(__file__).resolve().parents[1] / "sample_logs" / "drive_loops.ros2.mcap"
TOPIC = "/camera/image/compressed"
LAPS = 4  # the sample's 240 frames replayed 4 times: seconds of replay, tens of verification
METRIC_LAPS = 2  # twice: 15 s or more of metric fits after the stage's line
FILLER_MESSAGES = 300_000  # tiny messages of another topic: seconds of copying when writing
STOP_BOUND_S = 10.0  # generous: the promise is 2 s, a stage deaf to the signal takes > 20 s
START_BOUND_S = 900.0  # a safety net only: the wait ends when the line shows or the run ends
CODES = {signal.SIGTERM: ExitCode.TERMINATED, signal.SIGINT: ExitCode.INTERRUPTED}
WORDS = {signal.SIGTERM: "terminated", signal.SIGINT: "interrupted"}

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="needs Linux (/proc, prctl)")


# --- the inputs ---------------------------------------------------------------------------------


def repeated_log(
    path: Path, laps: int, filler: int = 0, topics: tuple[str, ...] = (TOPIC,)
) -> Path:
    """The sample's messages of `topics` (the camera's by default) `laps` times over, lap
    after lap in log time (use --time-source log: the header stamps repeat), then `filler`
    tiny JSON messages."""
    with SAMPLE.open("rb") as stream:
        items = list(make_reader(stream).iter_messages(topics=list(topics)))
    first = items[0][2]
    lap_ns = max(m.log_time for _, _, m in items) - first.log_time + 500_000_000
    with path.open("wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="ros2")
        channels: dict[int, int] = {}
        for schema, channel, _ in items:
            if channel.id not in channels and schema is not None:
                schema_id = writer.register_schema(schema.name, schema.encoding, schema.data)
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_id
                )
        for lap in range(laps):
            for _, channel, message in items:
                time_ns = message.log_time + lap * lap_ns
                writer.add_message(channels[channel.id], time_ns, message.data, time_ns)
        if filler:
            other = writer.register_channel("/filler", "json", 0)
            for i in range(filler):
                writer.add_message(other, first.log_time + i, b"{}", first.log_time + i)
        writer.finish()
    return path


def image_folder(folder: Path, laps: int) -> tuple[Path, Path]:
    """The sample's JPEGs `laps` times over as files, and an all-zero ground truth for them."""
    folder.mkdir()
    with open_source(SAMPLE) as source:
        jpegs = [message.data for message in source.image_messages(TOPIC)]
    for i in range(laps * len(jpegs)):
        (folder / f"{i:05d}.jpg").write_bytes(jpegs[i % len(jpegs)])
    gt = folder.parent / "gt.npy"
    np.save(gt, np.zeros((laps * len(jpegs),) * 2, dtype=np.uint8))
    return folder, gt


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("inputs")
    images, gt = image_folder(folder / "images", LAPS)
    return {
        "laps": repeated_log(folder / "laps.mcap", LAPS),
        "filler": repeated_log(folder / "filler.mcap", 1, FILLER_MESSAGES),
        # With the camera's CameraInfo: the accepted pairs get metric poses (rotation only);
        # METRIC_LAPS: the replay and the checks before the metric stage are most of the test.
        "calibrated": repeated_log(
            folder / "calibrated.mcap", METRIC_LAPS, topics=(TOPIC, "/camera/camera_info")
        ),
        "images": images,
        "gt": gt,
    }


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# --- a command on a terminal --------------------------------------------------------------------


def _default_sigint() -> None:
    # A shell starts background jobs with SIGINT ignored (CI may run us so), and Python then
    # installs no KeyboardInterrupt handler: the test is about our handling, so restore it.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class OnTerminal:
    """`doseqslam-logs ARGV` in a subprocess with its stderr on a pty, read on a thread."""

    def __init__(self, argv: list[str], cwd: Path) -> None:
        master, slave = pty.openpty()
        self.process = subprocess.Popen(
            [sys.executable, "-m", "doseqslam_logs.cli.main", *argv],
            cwd=cwd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=slave,
            preexec_fn=_default_sigint,
        )
        os.close(slave)
        self._master = master
        self._chunks: list[bytes] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        with contextlib.suppress(OSError):  # EIO once the child closed the terminal
            while chunk := os.read(self._master, 4096):
                self._chunks.append(chunk)

    @property
    def text(self) -> str:
        return b"".join(self._chunks).decode(errors="replace")

    def wait_for(self, pattern: str) -> None:
        deadline = time.monotonic() + START_BOUND_S
        while not re.search(pattern, self.text):
            assert self.process.poll() is None, f"ended before {pattern!r}: {self.text}"
            assert time.monotonic() < deadline, f"no {pattern!r} after {START_BOUND_S} s"
            time.sleep(0.02)

    def stop(self, sig: signal.Signals) -> tuple[int, float]:
        """Sends `sig`; the exit code and the seconds it took the command to end."""
        sent = time.monotonic()
        self.process.send_signal(sig)
        code = self.process.wait(timeout=60)
        return code, time.monotonic() - sent

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait()
        self._reader.join(5)
        os.close(self._master)


@contextlib.contextmanager
def on_terminal(argv: list[str], cwd: Path) -> Iterator[OnTerminal]:
    run = OnTerminal(argv, cwd)
    try:
        yield run
    finally:
        run.close()


def check_stopped(
    run: OnTerminal, sig: signal.Signals, what: str, code: int, latency: float
) -> None:
    print(f"\n{what}: {signal.Signals(sig).name} stopped it in {latency:.2f} s")
    assert code == CODES[sig], run.text
    assert run.text.rstrip().endswith(f"doseqslam-logs: {WORDS[sig]}"), run.text
    assert "Traceback" not in run.text
    assert latency < STOP_BOUND_S


def copy_inputs(inputs: dict[str, Path], names: list[str], folder: Path) -> dict[Path, str]:
    """The named inputs copied into `folder` (which the command may write into), with their
    sha256."""
    folder.mkdir(exist_ok=True)
    copies = {}
    for name in names:
        copy = folder / inputs[name].name
        shutil.copy(inputs[name], copy)
        copies[copy] = sha256(copy)
    return copies


def left_in(folder: Path) -> list[str]:
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*"))


# --- annotate and evaluate, each stage ----------------------------------------------------------

# The progress each stage shows as it begins (cli/progress.py).
REPLAY = r"\d+/\d+ frames"
VERIFY = "verifying the candidate pairs"
METRIC = "metric poses of the accepted pairs"
WRITE = "writing the output"


@pytest.mark.parametrize(
    ("stage", "sig", "log", "extra"),
    [
        ("replay", signal.SIGINT, "laps", ["--no-verify"]),
        ("verify", signal.SIGTERM, "laps", []),
        ("verify", signal.SIGINT, "laps", []),
        pytest.param("metric", signal.SIGTERM, "calibrated", [], marks=pytest.mark.slow),
        ("write", signal.SIGTERM, "filler", ["--no-verify"]),
    ],
)
def test_annotate_stops_in_every_stage(
    inputs: dict[str, Path],
    tmp_path: Path,
    stage: str,
    sig: signal.Signals,
    log: str,
    extra: list[str],
) -> None:
    copies = copy_inputs(inputs, [log], tmp_path)
    [copy] = copies
    argv = ["annotate", copy.name, "-o", "out.mcap", "--time-source", "log", *extra]
    with on_terminal(argv, tmp_path) as run:
        run.wait_for({"replay": REPLAY, "verify": VERIFY, "metric": METRIC, "write": WRITE}[stage])
        code, latency = run.stop(sig)
    check_stopped(run, sig, f"annotate, {stage}", code, latency)
    assert left_in(tmp_path) == [copy.name]  # no output, no temporary file
    assert sha256(copy) == copies[copy]


@pytest.mark.parametrize(("stage", "sig"), [("replay", signal.SIGTERM), ("verify", signal.SIGINT)])
def test_evaluate_images_stops_in_every_stage(
    inputs: dict[str, Path], tmp_path: Path, stage: str, sig: signal.Signals
) -> None:
    argv = ["evaluate", "--images", str(inputs["images"]), "--fps", "2", "--gt", str(inputs["gt"])]
    with on_terminal(argv, tmp_path) as run:
        run.wait_for({"replay": REPLAY, "verify": VERIFY}[stage])
        code, latency = run.stop(sig)
    check_stopped(run, sig, f"evaluate --images, {stage}", code, latency)
    assert left_in(tmp_path) == []


# --- batch --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("stage", "sig", "log", "jobs", "extra"),
    [
        ("replay", signal.SIGINT, "laps", "2", ["--no-verify"]),
        ("verify", signal.SIGTERM, "laps", "1", []),  # one log: two verification threads
        ("write", signal.SIGTERM, "filler", "1", ["--no-verify"]),
    ],
)
def test_batch_stops_in_every_stage(
    inputs: dict[str, Path],
    tmp_path: Path,
    stage: str,
    sig: signal.Signals,
    log: str,
    jobs: str,
    extra: list[str],
) -> None:
    copies = copy_inputs(inputs, [log], tmp_path / "logs")
    argv = ["batch", "logs", "-o", "out", "-j", jobs, "--time-source", "log", *extra]
    # The status line: `name done/total` per running log, then the stage after the replay.
    shown = {"replay": rf"{log}\.mcap [1-9]\d*/\d+", "verify": " verify", "write": " write"}
    with on_terminal(argv, tmp_path) as run:
        run.wait_for(shown[stage])
        code, latency = run.stop(sig)
    check_stopped(run, sig, f"batch, {stage}", code, latency)
    assert left_in(tmp_path / "out") == []  # nothing finished: not even a manifest line
    assert all(sha256(copy) == digest for copy, digest in copies.items())


def _children(pid: int) -> list[int]:
    children = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, IndexError, ValueError):
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if int(fields[1]) == pid:
                children.append(int(stat.parent.name))
    return children


def _running(pid: int) -> bool:
    """Alive and not a zombie (an orphan's reaper may not have collected it yet)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def test_no_process_outlives_a_killed_batch(inputs: dict[str, Path], tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    for name in ("a", "b"):
        shutil.copy(inputs["laps"], logs / f"{name}.mcap")
    (logs / "c.mcap").write_bytes(b"")  # fails at once: its worker is idle when the batch dies
    argv = ["batch", "logs", "-o", "out", "-j", "3", "--time-source", "log"]
    with on_terminal(argv, tmp_path) as run:
        run.wait_for(r"c\.mcap: FAILED")
        run.wait_for(r"\.mcap [1-9]\d*/\d+.*\.mcap [1-9]\d*/\d+")  # two workers replaying
        ours = _children(run.process.pid)  # 3 workers and multiprocessing's resource tracker
        assert len(ours) >= 4, ours
        run.process.kill()
        run.process.wait()
        killed = time.monotonic()
        while any(map(_running, ours)) and time.monotonic() < killed + STOP_BOUND_S:
            time.sleep(0.01)
        gone_after = time.monotonic() - killed
        survivors = [pid for pid in ours if _running(pid)]
        for pid in survivors:  # do not leave them to the next test
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
    print(f"\nbatch killed: its {len(ours)} processes gone {gone_after:.2f} s later")
    assert survivors == []
    # The workers heard of it in time to remove their temporary files: no output at all.
    assert [p for p in left_in(tmp_path / "out") if p != "manifest.jsonl"] == []
    assert sha256(logs / "a.mcap") == sha256(inputs["laps"])


# --- the stop inside the verification stage -----------------------------------------------------


def test_an_error_in_one_verification_thread_is_raised_not_the_others_stop(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The stop that an error sets makes the other threads leave their decision at the next
    frame pair; the error is what the stage raises, not their being stopped."""
    stopped = []

    def verify(self: Verifier, decision: object, hint: object = None) -> object:
        if decision == "bad":
            time.sleep(0.2)  # the other thread is inside its long decision by now
            raise LookupError("the frame loader did not return frames [7]")
        for _ in range(1000):  # a long decision: checks between frame pairs
            self._check_cancelled()
            time.sleep(0.01)
        stopped.append(False)  # not stopped: it ran to its end
        return decision

    monkeypatch.setattr(Verifier, "verify", verify)
    monkeypatch.setattr(stage, "CHAIN_DECISIONS", 1)  # one decision a thread, as they say
    with pytest.raises(LookupError, match="did not return"):
        verify_in_threads(
            ["long", "bad"],  # type: ignore[list-item]  # only verify() sees them
            lambda: contextlib.nullcontext(lambda indices: iter(())),
            DEFAULT_VERIFICATION,
            workers=2,
        )
    assert stopped == []


def test_an_interrupt_while_the_verification_threads_start_stops_those_started(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Ctrl-C landing in the pool's submit() (the stage has just begun) must stop the threads
    already started: the pool's shutdown does not join a thread whose start was interrupted,
    and the interpreter's exit would wait for it to finish the stage."""
    ended = []

    def verify(self: Verifier, decision: object, hint: object = None) -> object:
        try:
            for _ in range(1000):  # a long decision: checks between frame pairs
                self._check_cancelled()
                time.sleep(0.01)
        except Cancelled:
            ended.append("stopped")
            raise
        ended.append("ran to its end")
        return decision

    class InterruptedPool(stage.ThreadPoolExecutor):
        def submit(self, *args: Any, **kwargs: Any) -> Any:
            if getattr(self, "_threads", None):  # the second thread: Ctrl-C arrives
                time.sleep(0.1)  # the first is inside its decision
                raise KeyboardInterrupt
            return super().submit(*args, **kwargs)

    monkeypatch.setattr(Verifier, "verify", verify)
    monkeypatch.setattr(stage, "CHAIN_DECISIONS", 1)  # one decision a thread, as they say
    monkeypatch.setattr(stage, "ThreadPoolExecutor", InterruptedPool)
    with pytest.raises(KeyboardInterrupt):
        verify_in_threads(
            ["long", "long"],  # type: ignore[list-item]  # only verify() sees them
            lambda: contextlib.nullcontext(lambda indices: iter(())),
            DEFAULT_VERIFICATION,
            workers=2,
        )
    assert ended == ["stopped"]
