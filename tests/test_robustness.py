"""Issue #8: every case of the bad-input corpus behaves as docs/robustness.md says.

The corpus is built once per session by tests/make_bad_inputs.py from real RTAB-Map frames and
the real bags in shared/data. Each case runs through the command line in-process (and a few as
real subprocesses), and every run checks the promises: the documented exit code, one error line
naming the file and the problem, no traceback, the input unchanged (sha256), no output and no
temporary file after a failure, and after a success every skipped frame counted by reason in
the summary line and in the output's `doseqslam` metadata.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import make_bad_inputs
import numpy as np
import pytest
from mcap.reader import make_reader

from doseqslam_logs.cli.main import main
from doseqslam_logs.errors import ExitCode, ImageDecodeError, SourceError
from doseqslam_logs.pipeline.decode import (
    CLOCK_JUMP_NS,
    SKIP_BACKWARDS,
    FrameCounts,
    decoded_frames,
)
from doseqslam_logs.sinks.atomic import atomic_output, remove_stale_temps, scratch_file
from doseqslam_logs.sources.base import ImageMessage
from doseqslam_logs.sources.images import decode_gray

pytestmark = pytest.mark.slow  # the pipeline runs in its fixtures (pyproject: markers)

REPO = Path(__file__).resolve().parents[1]
FAIL = ("--on-error", "fail")
RECOVER = ("--recover",)


@pytest.fixture(scope="session")
def corpus(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return make_bad_inputs.make_corpus(tmp_path_factory.mktemp("corpus"), shared_data)


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def doseqslam_metadata(path: Path) -> dict[str, str]:
    with path.open("rb") as stream:
        records = [m for m in make_reader(stream).iter_metadata() if m.name == "doseqslam"]
    assert len(records) == 1
    return dict(records[0].metadata)


# --- the documented behaviour, case by case ---------------------------------------------------


@dataclass(frozen=True)
class Expect:
    """What one run must do: an error (code != 0, `message` in its one line) or a success
    with `frames` used, `skipped` by reason and `notes` in the summary line."""

    code: int
    message: str = ""
    frames: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    notes: tuple[str, ...] = ()


UNREADABLE, NO_CAMERA, BAD = ExitCode.UNREADABLE_INPUT, ExitCode.NO_CAMERA, ExitCode.BAD_IMAGE
DECODE = "undecodable image: "
NO_TOPIC = "no image topic among"
REINDEX = "`rosbag reindex` it"

BEHAVIOUR: list[tuple[str, tuple[str, ...], Expect]] = [
    ("good", (), Expect(0, frames=12)),
    ("truncated_footer", (), Expect(UNREADABLE, "truncated MCAP file: it ends after {size} ")),
    ("truncated_footer", RECOVER, Expect(0, frames=12, notes=("recovered: read {footer} of",))),
    ("truncated_chunk", (), Expect(UNREADABLE, "annotate --recover uses every complete message")),
    (
        "truncated_chunk",
        RECOVER,
        Expect(0, frames=6, notes=("recovered: read {chunk3} of {size}",)),
    ),
    ("rerun_truncated", ("--topic", "/image"), Expect(UNREADABLE, "truncated MCAP file")),
    ("rerun_truncated", (*RECOVER, "--topic", "/compressed_image"), Expect(0, frames=1)),
    ("rerun_truncated", RECOVER, Expect(NO_CAMERA, "2 image topics, choose one")),
    ("bad_crc", (), Expect(UNREADABLE, "a chunk fails its CRC check: the file is corrupt")),
    (
        "bad_crc",
        RECOVER,
        Expect(0, frames=9, skipped={"lost in a corrupt chunk": 3}, notes=("1 corrupt chunk",)),
    ),
    ("unindexed", (), Expect(0, frames=12)),
    ("empty", (), Expect(UNREADABLE, "not a log file: it is empty (0 bytes)")),
    ("empty", RECOVER, Expect(UNREADABLE, "not a log file: it is empty (0 bytes)")),
    ("not_mcap", (), Expect(UNREADABLE, "not a log file")),
    ("no_camera_mcap", (), Expect(NO_CAMERA, f"{NO_TOPIC} 3 topics")),
    ("no_camera_bag_bz2", (), Expect(NO_CAMERA, f"{NO_TOPIC} 9 topics")),
    ("no_camera_bag_lz4", (), Expect(NO_CAMERA, f"{NO_TOPIC} 9 topics")),
    ("zero_length", (), Expect(0, frames=10, skipped={DECODE + "empty image": 2})),
    ("zero_length", FAIL, Expect(BAD, "compressed image (format 'jpeg') has no data")),
    ("corrupt_jpeg", (), Expect(0, frames=10, skipped={DECODE + "corrupt compressed image": 2})),
    ("corrupt_jpeg", FAIL, Expect(BAD, "could not be decoded (Corrupt JPEG data: ")),
    ("bad_step", (), Expect(0, frames=10, skipped={DECODE + "raw size mismatch": 2})),
    ("bad_step", FAIL, Expect(BAD, "12288 data bytes, expected height 96 x step 130")),
    ("unknown_encoding", (), Expect(BAD, "none of the 12 image messages of /camera/image_raw")),
    ("unknown_encoding", FAIL, Expect(BAD, "unknown raw image encoding 'yuv420_888'")),
    ("resolution_change", (), Expect(0, frames=12)),
    ("log_out_of_order", (), Expect(0, frames=12)),
    ("stamps_out_of_order", (), Expect(0, frames=10, skipped={SKIP_BACKWARDS: 2})),
    ("stamps_out_of_order", FAIL, Expect(BAD, "timestamp earlier than the previous frame")),
    ("stamps_out_of_order", ("--time-source", "log"), Expect(0, frames=12)),
    ("duplicate_messages", (), Expect(0, frames=12, skipped={"duplicate message": 2})),
    ("duplicate_messages", FAIL, Expect(0, frames=12, skipped={"duplicate message": 2})),
    ("duplicate_stamps", (), Expect(0, frames=12)),
    ("clock_jump_back", (), Expect(0, frames=12, notes=("1 camera clock jumps bridged",))),
    ("clock_jump_forward", (), Expect(0, frames=12, notes=("1 camera clock jumps bridged",))),
    ("clock_jump_back_both", (), Expect(0, frames=12)),
    ("zero_stamps", (), Expect(0, frames=12, notes=("12 frames without header stamp used",))),
    ("bag_bz2", (), Expect(0, frames=12)),
    ("bag_lz4", (), Expect(0, frames=12)),
    ("bag_unindexed", (), Expect(UNREADABLE, "Bag is not indexed, reindex before reading.")),
    ("bag_truncated", (), Expect(UNREADABLE, REINDEX)),
]


def test_every_corpus_case_has_a_documented_behaviour() -> None:
    assert {case for case, _, _ in BEHAVIOUR} == set(make_bad_inputs.CASES)
    table = (REPO / "docs" / "robustness.md").read_text()
    for case in make_bad_inputs.CASES:
        assert f"`{case}`" in table, f"{case} is missing from docs/robustness.md"


def offsets(corpus: dict[str, Path], log: Path) -> dict[str, int]:
    """What messages may name, by placeholder: the file size, where the good MCAP's third
    chunk starts (where truncated_chunk becomes unreadable) and its footer."""
    good = corpus["good"]
    return {
        "size": log.stat().st_size,
        "chunk3": make_bad_inputs.chunk_spans(good)[2][0],
        "footer": good.stat().st_size - 8 - 29,  # the magic and the footer record
    }


def check_run(
    log: Path,
    out_dir: Path,
    argv: list[str],
    code: int,
    out: str,
    err: str,
    expect: Expect,
    values: dict[str, int],
) -> None:
    """The promises of issue #8 for one finished run of `annotate`."""
    output = out_dir / "out.mcap"
    assert "Traceback" not in err and "Traceback" not in out
    assert code == expect.code, err
    if code != 0:
        assert out == ""
        assert err.count("\n") == 1 and err.startswith("doseqslam-logs: error: "), err
        assert str(log) in err and expect.message.format(**values) in err, err
        assert list(out_dir.iterdir()) == [], "a failed run left a file"
        return
    assert sorted(p.name for p in out_dir.iterdir()) == ["out.mcap"], "temporary file left"
    assert all(line.startswith("doseqslam-logs: warning: ") for line in err.splitlines()), err
    [line] = out.splitlines()
    assert line.startswith(f"{output}: {expect.frames} frames of ")
    total = sum(expect.skipped.values())
    reasons = ", ".join(f"{n} {why}" for why, n in sorted(expect.skipped.items()))
    assert f" {total} skipped frames{f' ({reasons})' if reasons else ''}, " in line
    for note in expect.notes:
        assert note.format(**values) in line
    meta = doseqslam_metadata(output)
    assert meta["frames_used"] == str(expect.frames)
    assert meta["frames_skipped"] == str(total)
    assert json.loads(meta["frames_skipped_by_reason"]) == expect.skipped
    assert json.loads(meta["first_skipped_by_reason"]).keys() == {
        why.split(": ")[0] for why in expect.skipped
    }
    assert meta["source_file"] == log.name and meta["source_sha256"] == sha256(log)
    assert (meta["recovered"] != "") == ("--recover" in argv)
    assert int(meta["image_messages"]) == expect.frames + total


@pytest.mark.parametrize(
    ("case", "extra", "expect"),
    BEHAVIOUR,
    ids=[f"{case}{''.join(extra)}" for case, extra, _ in BEHAVIOUR],
)
def test_annotate_behaviour(
    corpus: dict[str, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    case: str,
    extra: tuple[str, ...],
    expect: Expect,
) -> None:
    log = corpus[case]
    before = sha256(log)
    argv = ["annotate", str(log), "-o", str(tmp_path / "out.mcap"), *extra]
    code = main(argv)
    out, err = capsys.readouterr()
    assert sha256(log) == before, "the input was modified"
    check_run(log, tmp_path, argv, code, out, err, expect, offsets(corpus, log))


INFO_FAILS = {"truncated_footer", "truncated_chunk", "rerun_truncated", "empty", "not_mcap"}
INFO_FAILS |= {"bag_unindexed", "bag_truncated"}


@pytest.mark.parametrize("case", sorted(make_bad_inputs.CASES))
def test_info_behaviour(
    corpus: dict[str, Path], capsys: pytest.CaptureFixture[str], case: str
) -> None:
    log = corpus[case]
    before = sha256(log)
    code = main(["info", str(log)])
    out, err = capsys.readouterr()
    assert sha256(log) == before and "Traceback" not in err
    if case in INFO_FAILS:
        assert code == ExitCode.UNREADABLE_INPUT
        assert err.count("\n") == 1 and err.startswith("doseqslam-logs: error: ")
        assert str(log) in err
    else:
        assert code == 0 and err == "" and out.startswith(f"{log}: ")
        assert ("no camera channel" in out) == case.startswith("no_camera")


def test_recovered_output_holds_every_complete_record(
    corpus: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--recover on a file cut mid-chunk: the output has the 2 complete chunks' messages and
    the metadata says where the file was cut; a whole file recovers to the same frames."""
    output = tmp_path / "out.mcap"
    assert main(["annotate", str(corpus["truncated_chunk"]), "-o", str(output), "--recover"]) == 0
    with output.open("rb") as stream:
        reader = make_reader(stream)
        topics = [channel.topic for _, channel, _ in reader.iter_messages()]
    assert topics.count("/camera/image/compressed") == 6
    recovered = json.loads(doseqslam_metadata(output)["recovered"])
    values = offsets(corpus, corpus["truncated_chunk"])
    assert recovered["complete"] is False and recovered["bytes_used"] == values["chunk3"]
    assert recovered["file_size"] == values["size"] and "truncated" in recovered["stop_reason"]
    whole = tmp_path / "whole.mcap"
    assert main(["annotate", str(corpus["good"]), "-o", str(whole), "--recover"]) == 0
    assert json.loads(doseqslam_metadata(whole)["recovered"])["complete"] is True
    assert "; recovered:" not in capsys.readouterr().out.splitlines()[-1]


def test_recover_refuses_to_overwrite_its_input(
    corpus: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "log.mcap"
    log.write_bytes(corpus["truncated_chunk"].read_bytes())
    before = sha256(log)
    assert main(["annotate", str(log), "-o", str(log), "--recover"]) == ExitCode.OUTPUT_ERROR
    assert "overwrite the input" in capsys.readouterr().err
    assert sha256(log) == before and [p.name for p in tmp_path.iterdir()] == ["log.mcap"]


def test_debug_shows_the_traceback(corpus: dict[str, Path], tmp_path: Path) -> None:
    out = str(tmp_path / "out.mcap")
    for argv in (["--debug", "annotate", str(corpus["empty"]), "-o", out],):
        with pytest.raises(SourceError, match="it is empty"):
            main(argv)
    with pytest.raises(SourceError, match="it is empty"):
        main(["annotate", "--debug", str(corpus["empty"]), "-o", out])
    assert list(tmp_path.iterdir()) == []


# --- as real processes ------------------------------------------------------------------------


def cli(*argv: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "doseqslam_logs.cli.main", *map(str, argv)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


@pytest.mark.parametrize(
    ("case", "extra", "expect"),
    [
        item
        for item in BEHAVIOUR
        if (item[0], item[1])
        in {
            ("truncated_chunk", ()),
            ("no_camera_bag_lz4", ()),
            ("corrupt_jpeg", ()),
            ("corrupt_jpeg", FAIL),
            ("bag_unindexed", ()),
            ("bad_crc", RECOVER),
        }
    ],
    ids=lambda value: value if isinstance(value, str) else None,
)
def test_annotate_as_a_process(
    corpus: dict[str, Path], tmp_path: Path, case: str, extra: tuple[str, ...], expect: Expect
) -> None:
    """In a real process also what C libraries print to file descriptor 2 (libjpeg's
    "Corrupt JPEG data" warnings) shows: it must not."""
    log = corpus[case]
    before = sha256(log)
    argv = ["annotate", str(log), "-o", str(tmp_path / "out.mcap"), *extra]
    proc = cli(*argv)
    assert sha256(log) == before
    values = offsets(corpus, log)
    check_run(log, tmp_path, argv, proc.returncode, proc.stdout, proc.stderr, expect, values)


# Runs the CLI with every mcap write slowed down, so that a signal surely arrives mid-write.
SLOW_WRITER = textwrap.dedent(
    """
    import os, signal, sys, time
    from mcap.writer import Writer
    from doseqslam_logs.cli.main import main

    # A shell starts background jobs with SIGINT ignored (CI may run us that way), and Python
    # then installs no KeyboardInterrupt handler: restore it, the test is about our cleanup.
    signal.signal(signal.SIGINT, signal.default_int_handler)

    # The BLOCK_WRITER-th MCAP writer of the run (1: the first output or --recover's copy of
    # the input, 2: the output after that copy) blocks at its first message until a signal
    # ends the process: the signal always lands mid-write, however loaded the machine is.
    block = int(os.environ["BLOCK_WRITER"])
    writers = []
    original_init, original_add = Writer.__init__, Writer.add_message

    def init(self, *args, **kwargs):
        writers.append(self)
        original_init(self, *args, **kwargs)

    def add(self, *args, **kwargs):
        if writers.index(self) + 1 >= block:
            deadline = time.monotonic() + 60  # never outlive a lost signal by much
            while time.monotonic() < deadline:
                time.sleep(0.05)
        return original_add(self, *args, **kwargs)

    Writer.__init__, Writer.add_message = init, add
    sys.exit(main(sys.argv[1:]))
    """
)


def start_slow_annotate(
    log: Path, output: Path, *extra: str, block_writer: int = 1
) -> subprocess.Popen[str]:
    argv = ["annotate", str(log), "-o", str(output), *extra]
    return subprocess.Popen(
        [sys.executable, "-c", SLOW_WRITER, *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "BLOCK_WRITER": str(block_writer)},
    )


def wait_for_temps(
    process: subprocess.Popen[str], folder: Path, name: str, count: int = 1
) -> list[Path]:
    """The hidden temporary files of `name`, once `count` of them exist: 1 when the first
    write began, 2 when --recover's copy of the input is being annotated into the output."""
    deadline = time.monotonic() + 60
    while True:
        temps = [p for p in folder.iterdir() if p.name.startswith(f".{name}.")]
        if len(temps) >= count:
            time.sleep(0.2)  # the writer is blocked at its first message by now
            return temps
        assert process.poll() is None, "the run ended before it could be stopped"
        assert time.monotonic() < deadline, "the run never started writing"
        time.sleep(0.02)


def test_sigkill_mid_write_leaves_no_output_and_the_next_run_cleans_up(
    corpus: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log, output = corpus["good"], tmp_path / "out.mcap"
    before = sha256(log)
    process = start_slow_annotate(log, output)
    try:
        [temp] = wait_for_temps(process, tmp_path, output.name)
        process.send_signal(signal.SIGKILL)
        process.communicate(timeout=30)
    finally:
        process.kill()
    assert process.returncode == -signal.SIGKILL
    assert not output.exists() and sha256(log) == before
    # A killed process cannot clean up: its hidden temporary file stays, until the next run.
    assert [p.name for p in tmp_path.iterdir()] == [temp.name]
    assert main(["annotate", str(log), "-o", str(output)]) == 0
    capsys.readouterr()
    assert [p.name for p in tmp_path.iterdir()] == ["out.mcap"]


@pytest.mark.parametrize(
    ("sig", "temps", "code", "word"),
    [
        (signal.SIGTERM, 1, ExitCode.TERMINATED, "terminated"),  # while copying the input
        (signal.SIGTERM, 2, ExitCode.TERMINATED, "terminated"),  # while writing the output
        (signal.SIGINT, 2, ExitCode.INTERRUPTED, "interrupted"),
    ],
)
def test_sigterm_and_sigint_mid_write_clean_up(
    corpus: dict[str, Path],
    tmp_path: Path,
    sig: signal.Signals,
    temps: int,
    code: int,
    word: str,
) -> None:
    log, output = corpus["truncated_chunk"], tmp_path / "out.mcap"
    before = sha256(log)
    # --recover: its temporary copy of the input must go too.
    process = start_slow_annotate(log, output, "--recover", block_writer=temps)
    try:
        wait_for_temps(process, tmp_path, output.name, temps)
        process.send_signal(sig)
        _, err = process.communicate(timeout=30)
    finally:
        process.kill()
    assert process.returncode == code
    assert err == f"doseqslam-logs: {word}\n"
    assert list(tmp_path.iterdir()) == [] and sha256(log) == before


# --- the pieces -------------------------------------------------------------------------------


def test_stale_temporaries_of_dead_processes_are_removed(tmp_path: Path) -> None:
    final = tmp_path / "out.mcap"
    finished = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        capture_output=True,
        text=True,
        check=True,
    )
    dead_pid = int(finished.stdout)
    dead = tmp_path / f".out.mcap.{dead_pid}.0123abcd.tmp"
    alive = tmp_path / f".out.mcap.{os.getppid()}.0123abcd.tmp"  # pytest's parent runs
    other = tmp_path / f".other.mcap.{dead_pid}.0123abcd.tmp"  # another output's
    for path in (dead, alive, other):
        path.write_bytes(b"partial")
    assert remove_stale_temps(final) == [dead]
    with atomic_output(final) as stream:
        stream.write(b"whole")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [alive.name, other.name, "out.mcap"]
    )
    with scratch_file(final) as scratch:
        assert scratch.exists() and re.fullmatch(
            r"\.out\.mcap\.\d+\.[0-9a-f]{8}\.tmp", scratch.name
        )
    assert not scratch.exists()


@pytest.mark.parametrize("opener", ["atomic_output", "scratch_file"])
def test_an_interrupt_just_after_the_temporary_is_made_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, opener: str
) -> None:
    # SIGTERM becomes a KeyboardInterrupt that lands between any two lines; here between the
    # open() that made the temporary file and the line that would have noted its name (a
    # run stopped as the write stage began left `.out.mcap.PID.RANDOM.tmp` behind).
    real_open = os.open

    def open_then_interrupted(path: str, flags: int, mode: int = 0o777) -> int:
        os.close(real_open(path, flags, mode))
        raise KeyboardInterrupt

    monkeypatch.setattr("doseqslam_logs.sinks.atomic.os.open", open_then_interrupted)
    context = {"atomic_output": atomic_output, "scratch_file": scratch_file}[opener]
    with pytest.raises(KeyboardInterrupt), context(tmp_path / "out.mcap"):
        pass
    assert list(tmp_path.iterdir()) == []


def test_a_jpeg_that_libjpeg_decodes_around_damage_is_corrupt(shared_data: Path) -> None:
    """OpenCV returns pixels for a JPEG with damaged scan data (gray or garbled rows) and
    libjpeg only complains on stderr: that complaint makes it a corrupt image."""
    [jpeg] = make_bad_inputs.rtabmap_jpegs(shared_data, 1)
    damaged = make_bad_inputs.corrupt_scan(jpeg)
    assert cv2.imdecode(np.frombuffer(damaged, np.uint8), cv2.IMREAD_GRAYSCALE) is not None
    msg = ImageMessage("/cam", 1, 1, "compressed", "jpeg", 0, 0, 0, False, damaged)
    with pytest.raises(ImageDecodeError, match=r"is corrupt \(Corrupt JPEG data: ") as info:
        decode_gray(msg)
    assert info.value.problem == "corrupt compressed image"
    assert decode_gray(replace(msg, data=jpeg)).shape == (384, 512)


def message(log_s: float, stamp_s: float, pixels: int = 7) -> ImageMessage:
    data = bytes([pixels]) * 16
    log_ns, stamp_ns = round(log_s * 1e9), round(stamp_s * 1e9)
    return ImageMessage("/cam", log_ns, stamp_ns, "raw", "mono8", 4, 4, 4, False, data)


HOUR = 3600.0


@pytest.mark.parametrize("jump", [-3 * HOUR, 3 * HOUR, -20.0, 20.0, -1e6 * HOUR])
def test_camera_clock_jumps_are_bridged_with_the_log_time(jump: float) -> None:
    """Frames 0-3 stamped t, then t + jump; log times advance 0.5 s per frame. The detector's
    time moves by the log time across the jump and by the camera clock elsewhere."""
    msgs = [message(100 + 0.5 * i, 10 + 0.5 * i + (jump if i >= 4 else 0), i) for i in range(8)]
    counts = FrameCounts()
    frames = list(decoded_frames(msgs, counts))
    times = [f.timestamp_ns / 1e9 for f in frames]
    assert times == pytest.approx([10 + 0.5 * i for i in range(8)])
    assert counts.clock_jumps == 1 and counts.skipped_total == 0
    assert [f.header_stamp_ns for f in frames] == [m.header_stamp_ns for m in msgs]
    assert "jump" in counts.first_clock_jump


def test_small_backward_steps_are_skipped_not_bridged() -> None:
    """Within CLOCK_JUMP_NS a stamp before the previous frame is an out-of-order frame."""
    step = CLOCK_JUMP_NS / 1e9 / 2
    msgs = [message(100, 50), message(100.5, 50 - step), message(101, 51)]
    counts = FrameCounts()
    assert [f.timestamp_ns for f in decoded_frames(msgs, counts)] == [50 * 10**9, 51 * 10**9]
    assert counts.skipped == {SKIP_BACKWARDS: 1} and counts.clock_jumps == 0


def test_one_wild_stamp_is_bridged_there_and_back() -> None:
    msgs = [message(100 + i, 10 + i + (5 * HOUR if i == 2 else 0), i) for i in range(5)]
    counts = FrameCounts()
    times = [f.timestamp_ns / 1e9 for f in decoded_frames(msgs, counts)]
    assert times == pytest.approx([10, 11, 12, 13, 14]) and counts.clock_jumps == 2


def test_log_time_source_ignores_the_camera_clock() -> None:
    msgs = [message(100 + i, 10 + i + (-3 * HOUR if i >= 2 else 0), i) for i in range(4)]
    counts = FrameCounts()
    frames = list(decoded_frames(msgs, counts, time_source="log"))
    assert [f.timestamp_ns / 1e9 for f in frames] == [100, 101, 102, 103]
    assert counts.clock_jumps == 0


@pytest.mark.parametrize("missing", [0, 5], ids=["first frame", "frame 5"])
@pytest.mark.parametrize("stamp", [0, None], ids=["stamp 0", "no stamp"])
@pytest.mark.parametrize("lag", [1.2, -1.2, 3 * HOUR], ids=["log late", "log early", "3 h"])
def test_a_frame_without_stamp_keeps_its_place_among_stamped_ones(
    missing: int, stamp: int | None, lag: float
) -> None:
    """Log times = header stamps + lag at 2 Hz; one frame has no usable stamp (an invalid one,
    negative seconds, arrives here as None). Its raw log time would be `lag` off the camera
    clock: ahead of the next two frames (skipped as earlier), or behind the previous one."""
    msgs = [message(100 + 0.5 * i + lag, 100 + 0.5 * i, i) for i in range(8)]
    msgs[missing] = replace(msgs[missing], header_stamp_ns=stamp)
    counts = FrameCounts()
    times = [f.timestamp_ns / 1e9 for f in decoded_frames(msgs, counts)]
    assert len(times) == 8 and counts.skipped_total == 0
    assert np.diff(times) == pytest.approx([0.5] * 7)
    assert counts.log_time_fallbacks == 1
    # Before any stamp the frame is on the log clock, and the clocks 3 h apart are a jump.
    assert counts.clock_jumps == (1 if missing == 0 and lag == 3 * HOUR else 0)


def test_log_times_out_of_order_do_not_look_like_clock_jumps() -> None:
    msgs = [message(100, 10), message(80, 10.5), message(101, 11)]
    counts = FrameCounts()
    assert len(list(decoded_frames(msgs, counts))) == 3 and counts.clock_jumps == 0


def test_a_corrupt_chunk_of_another_topic_is_not_copied_as_if_sound(
    shared_data: Path, tmp_path: Path
) -> None:
    """The camera chunks are sound; the chunk of another topic fails its CRC. The copy of the
    input must notice (exit 3, --recover suggested), not rewrite it under a fresh valid CRC."""
    import base64

    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    jpeg = (shared_data / "rtabmap_samples_loop" / "images" / "1.jpg").read_bytes()
    log = tmp_path / "other_topic_crc.mcap"
    with log.open("wb") as stream:
        writer = Writer(stream, compression=CompressionType.NONE)
        writer.start(profile="", library="test")
        image = writer.register_schema("foxglove.CompressedImage", "jsonschema", b"{}")
        other = writer.register_schema("note", "jsonschema", b"{}")
        cam = writer.register_channel("/cam", "json", image)
        notes = writer.register_channel("/notes", "json", other)

        def frame(i: int) -> bytes:
            doc = {
                "timestamp": {"sec": i, "nsec": 0},
                "frame_id": "c",
                "format": "jpeg",
                "data": base64.b64encode(jpeg).decode(),
            }
            return json.dumps(doc).encode()

        for i in range(3):
            writer.add_message(cam, i * 10**9, frame(i), i * 10**9)
        writer.flush()  # end the camera chunk
        writer.add_message(notes, 3 * 10**9, b'{"text": "hello"}', 3 * 10**9)
        writer.flush()
        for i in range(4, 7):
            writer.add_message(cam, i * 10**9, frame(i), i * 10**9)
        writer.finish()
    with log.open("rb") as stream:
        chunks = make_reader(stream).get_summary().chunk_indexes
    notes_chunk = next(c for c in chunks if c.message_start_time == 3 * 10**9)
    data = bytearray(log.read_bytes())
    data[notes_chunk.chunk_start_offset + 33] ^= 0xFF  # the chunk's uncompressed CRC
    log.write_bytes(bytes(data))
    output = tmp_path / "out.mcap"
    code = main(["annotate", str(log), "-o", str(output), "--set", "kappa_s=1"])
    assert code == ExitCode.UNREADABLE_INPUT and not output.exists()
