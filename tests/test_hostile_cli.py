"""Issue #21: outputs that are not ours, crashes and Python's messages become one-line errors.

Every hostile input is built here, in tmp_path, from the 12 RTAB-Map frames of the bad-input
corpus (tests/make_bad_inputs.py). Each run goes through the command line in-process and checks
the promise of docs/robustness.md: the documented exit code, one `doseqslam-logs: error:` line,
no traceback, inputs unchanged, and only regular files ever written under an output name.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import stat
import struct
from collections.abc import Iterator
from pathlib import Path

import make_bad_inputs
import numpy as np
import pytest

from doseqslam_logs.cli.main import main
from doseqslam_logs.errors import ExitCode

pytestmark = pytest.mark.slow  # the pipeline runs

OUTPUT_ERROR, USAGE = ExitCode.OUTPUT_ERROR, ExitCode.USAGE


@pytest.fixture(scope="module")
def jpegs(shared_data: Path) -> list[bytes]:
    return make_bad_inputs.rtabmap_jpegs(shared_data)


@pytest.fixture(scope="module")
def good_log(jpegs: list[bytes], tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("logs") / "good.mcap"
    return make_bad_inputs.write_log(path, make_bad_inputs.good_items(jpegs))


@pytest.fixture(scope="module")
def annotated(good_log: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("annotated") / "out.mcap"
    assert main(["annotate", str(good_log), "-o", str(out), "--no-verify"]) == 0
    return out


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def cli(capsys: pytest.CaptureFixture[str], *args: str | Path) -> tuple[int, str, str]:
    code = main([str(arg) for arg in args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def assert_one_error(err: str, *fragments: str) -> None:
    lines = [line for line in err.splitlines() if "warning" not in line]
    assert len(lines) == 1 and lines[0].startswith("doseqslam-logs: error: "), err
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in lines[0], err


def assert_fails(
    capsys: pytest.CaptureFixture[str], code: int, fragment: str, *args: str | Path
) -> None:
    status, _, err = cli(capsys, *args)
    assert status == code, err
    assert_one_error(err, fragment)


def leftovers(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if p.name.startswith(".")]


# --- 1. outputs are only ever regular files ---------------------------------------------------


def _fifo(path: Path) -> Path:
    os.mkfifo(path)
    return path


def _socket(path: Path) -> Path:
    import socket

    server = socket.socket(socket.AF_UNIX)
    server.bind(str(path))
    server.close()
    return path


def _directory(path: Path) -> Path:
    path.mkdir()
    return path


def _link_to_dev_null(path: Path) -> Path:
    path.symlink_to("/dev/null")
    return path


NOT_OURS = {
    "a FIFO": _fifo,
    "a socket": _socket,
    "a directory": _directory,
    "a character device": _link_to_dev_null,
}


def _writing_commands(log: Path, annotated: Path, out: Path) -> dict[str, list[str | Path]]:
    return {
        "annotate": ["annotate", log, "-o", out, "--no-verify"],
        "annotate --recover": ["annotate", log, "-o", out, "--no-verify", "--recover"],
        "export": ["export", annotated, "--format", "csv", "-o", out],
    }


@pytest.mark.parametrize("kind", NOT_OURS)
@pytest.mark.parametrize("command", ["annotate", "annotate --recover", "export"])
def test_an_existing_non_regular_output_is_refused_and_left_alone(
    kind: str,
    command: str,
    good_log: Path,
    annotated: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = NOT_OURS[kind](tmp_path / "out.mcap")
    before = os.lstat(out)
    args = _writing_commands(good_log, annotated, out)[command]
    assert_fails(capsys, OUTPUT_ERROR, f"the output exists and is {kind}: refusing", *args)
    after = os.lstat(out)
    assert (after.st_mode, after.st_ino) == (before.st_mode, before.st_ino)
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)
    assert leftovers(tmp_path) == []


def test_a_symlink_to_a_regular_file_is_replaced_and_its_target_untouched(
    annotated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / "target.csv"
    target.write_text("keep me\n")
    link = tmp_path / "out.csv"
    link.symlink_to(target)
    status, _, err = cli(capsys, "export", annotated, "--format", "csv", "-o", link)
    assert status == 0, err
    assert not link.is_symlink() and link.read_text().startswith("query")
    assert target.read_text() == "keep me\n"


def test_a_batch_output_that_is_not_ours_fails_that_log_only(
    good_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "a.mcap").write_bytes(good_log.read_bytes())
    outdir = tmp_path / "out"
    outdir.mkdir()
    os.mkfifo(outdir / "a.annotated.mcap")
    status, _, err = cli(capsys, "batch", logs, "-o", outdir, "--no-verify", "-j", "1")
    assert status == ExitCode.DIFFERENT, err
    assert stat.S_ISFIFO(os.lstat(outdir / "a.annotated.mcap").st_mode)
    assert "is a FIFO: refusing to replace it" in (outdir / "manifest.jsonl").read_text()


def test_batch_into_an_existing_file_is_an_output_error(
    good_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    outdir = tmp_path / "out"
    outdir.write_text("not a folder")
    assert_fails(capsys, OUTPUT_ERROR, "is not a folder", "batch", good_log, "-o", outdir)
    assert outdir.read_text() == "not a folder"


def test_export_onto_its_input_is_an_output_error_as_for_annotate(
    good_log: Path, annotated: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    digest = sha256(annotated)
    export = ("export", annotated, "--format", "csv", "-o", annotated)
    assert_fails(capsys, OUTPUT_ERROR, "the output would replace the input", *export)
    annotate = ("annotate", good_log, "-o", good_log)
    assert_fails(capsys, OUTPUT_ERROR, "the output would overwrite the input", *annotate)
    assert sha256(annotated) == digest


# --- 2. crashes become one-line errors --------------------------------------------------------


def test_an_output_name_longer_than_name_max_is_an_output_error(
    good_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / ("a" * 256)
    assert_fails(
        capsys,
        OUTPUT_ERROR,
        "its name is 256 bytes long, the limit is 255",
        *("annotate", good_log, "-o", out, "--no-verify"),
    )


def test_a_legal_long_output_name_is_written(
    good_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / ("b" * 245 + ".mcap")
    status, _, err = cli(capsys, "annotate", good_log, "-o", out, "--no-verify")
    assert status == 0, err
    assert out.is_file() and leftovers(tmp_path) == []


@pytest.mark.parametrize(
    ("value", "fragment"),
    [
        ("2023-13-45T99:99Z", "not a time: '2023-13-45T99:99Z'"),
        ("2023-13-45T10:00:00Z", "month must be in 1..12"),
        ("1969-12-31T23:59:59Z", "not a log time"),
        (str(2**64), "not a log time"),
    ],
)
def test_a_bad_start_time_is_a_usage_error(
    value: str, fragment: str, good_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["annotate", str(good_log), "-o", str(tmp_path / "o.mcap"), "-S", value])
    err = capsys.readouterr().err
    assert exit_info.value.code == USAGE and fragment in err and "Traceback" not in err


# --- 4. smaller inconsistencies ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("window", "fragment"),
    [
        (("-S", "2100-01-01T00:00:00Z"), "with log time in [4102444800000000000, its end)"),
        (("-E", "1"), "with log time in [its start, 1)"),
    ],
)
def test_a_window_without_images_is_an_error_not_an_empty_output(
    window: tuple[str, str],
    fragment: str,
    good_log: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "o.mcap"
    args = ("annotate", good_log, "-o", out, "--no-verify", *window)
    assert_fails(capsys, ExitCode.BAD_IMAGE, fragment, *args)
    assert not out.exists()


# --- timestamps no clock can have -------------------------------------------------------------


def _raw_log(
    jpegs: list[bytes],
    path: Path,
    headers: dict[int, tuple[int, int]] | None = None,
    log_times: dict[int, int] | None = None,
) -> Path:
    """The 12 frames as mono8 sensor_msgs/Image; frame k gets header stamp headers[k] =
    (sec, nanosec) and log time log_times[k] when given."""
    from rosbags.typesys import Stores, get_typestore

    types = get_typestore(Stores.ROS2_HUMBLE).types
    headers, log_times = headers or {}, log_times or {}
    items: list[make_bad_inputs.Item] = []
    for i, data in enumerate(jpegs):
        frame = make_bad_inputs.mono8_frame(data, make_bad_inputs.stamp(i))
        log_time = log_times.get(i, frame.stamp_ns + make_bad_inputs.LATENCY_NS)
        overrides = {}
        if i in headers:
            stamp = types["builtin_interfaces/msg/Time"](sec=headers[i][0], nanosec=headers[i][1])
            overrides["header"] = types["std_msgs/msg/Header"](stamp=stamp, frame_id="camera")
        items.append((frame, log_time, overrides))
    return make_bad_inputs.write_log(path, items)


@pytest.mark.parametrize(
    "header",
    [
        (-5, 0),  # a legal int32: before 1970, no log time can be that
        (1_700_000_002, 4_000_000_000),  # nanosec >= 1e9: not +4 s
        (2**31 - 1, 999_999_999),  # fine
    ],
    ids=["negative seconds", "nanosec 4e9", "latest"],
)
def test_an_invalid_header_stamp_falls_back_to_the_log_time_counted(
    header: tuple[int, int],
    jpegs: list[bytes],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    log = _raw_log(jpegs, tmp_path / "log.mcap", headers={5: header})
    status, out, err = cli(capsys, "annotate", log, "-o", tmp_path / "o.mcap", "--no-verify")
    assert status == 0, err
    if header[0] == 2**31 - 1:  # valid: a jump to 2038 and back, bridged
        assert "0 skipped frames" in out and "2 camera clock jumps bridged" in out
        return
    assert "12 frames of /camera/image_raw" in out and "0 skipped frames" in out
    assert "1 frames without header stamp used the log time" in out


@pytest.mark.parametrize("frame", [0, 5])
@pytest.mark.parametrize("lag_ms", [1200, -1200])
def test_a_negative_header_stamp_costs_no_other_frame(
    frame: int,
    lag_ms: int,
    jpegs: list[bytes],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """The recorder logs every frame 1.2 s after (or before) its stamp, more than the 0.5 s
    between frames: the frame whose stamp has sec = -5 must not, timed by its raw log time,
    jump ahead of the next frames (they were skipped as earlier) or behind the previous one."""
    lag = lag_ms * 1_000_000
    log_times = {i: make_bad_inputs.stamp(i) + lag for i in range(len(jpegs))}
    log = _raw_log(jpegs, tmp_path / "log.mcap", headers={frame: (-5, 0)}, log_times=log_times)
    for on_error in ("skip", "fail"):
        args = ("annotate", log, "-o", tmp_path / "o.mcap", "--no-verify", "--on-error", on_error)
        status, out, err = cli(capsys, *args)
        assert status == 0, err
        assert "12 frames of /camera/image_raw" in out and "0 skipped frames" in out
        assert "1 frames without header stamp used the log time" in out
        assert "clock jump" not in out + err


@pytest.mark.parametrize("log_time", [2**64 - 1, 2**63 - 1, 2**31 * 10**9])
@pytest.mark.parametrize("frame", [5, 11])
def test_a_log_time_past_2038_skips_that_frame_counted(
    log_time: int,
    frame: int,
    jpegs: list[bytes],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    log = _raw_log(jpegs, tmp_path / "log.mcap", log_times={frame: log_time})
    digest = sha256(log)
    out_path = tmp_path / "o.mcap"
    status, out, err = cli(capsys, "annotate", log, "-o", out_path, "--no-verify")
    assert status == 0, err
    assert "11 frames" in out and "1 skipped frames (1 log time out of range)" in out
    assert f"at log time {log_time}: later than 2147483647999999999" in err
    assert sha256(log) == digest and out_path.is_file()
    fail = ("annotate", log, "-o", out_path, "--no-verify", "--on-error", "fail")
    assert_fails(capsys, ExitCode.BAD_IMAGE, "log time out of range", *fail)


# --- parameters and options that are not numbers ----------------------------------------------


FLOAT_PARAMETERS = [
    "kappa_s",
    "velocity_min",
    "velocity_max",
    "velocity_step",
    "threshold",
    "match_ratio",
    "place_index_interval_s",
]
FLOAT_VERIFICATION = [
    "ratio",
    "ransac_threshold_px",
    "confidence",
    "second_guess_factor",
    "query_interval_s",
    "max_rotation_deg",
    "planar_share",
    "leave_distance_m",
    "heading_drift_deg",
    "heading_drift_deg_per_m",
    "relocate_spacing_m",
    "relocate_margin_m",
    "confirmed_rotation_deg",
    "confirm_distance_m",
]


def test_the_lists_hold_every_float_parameter() -> None:
    from dataclasses import fields

    from doseqslam_logs.detector.params import Parameters
    from doseqslam_logs.verification.params import VerificationParameters

    def floats(cls: type) -> list[str]:
        return [f.name for f in fields(cls) if isinstance(f.default, float)]

    assert floats(Parameters) == FLOAT_PARAMETERS
    assert floats(VerificationParameters) == FLOAT_VERIFICATION


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "+inf"])
@pytest.mark.parametrize(
    "option", [("--set", n) for n in FLOAT_PARAMETERS] + [("--vset", n) for n in FLOAT_VERIFICATION]
)
def test_a_non_finite_parameter_is_a_usage_error(
    option: tuple[str, str],
    value: str,
    good_log: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    flag, name = option
    args = ("annotate", good_log, "-o", tmp_path / "o.mcap", flag, f"{name}={value}")
    assert_fails(capsys, USAGE, f"{name} must be a finite number, got", *args)


def test_a_config_file_that_is_not_text_is_a_usage_error(
    good_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "params.toml"
    config.write_bytes(b"kappa_s = 1\n\xff\xfe\x00binary")
    args = ("annotate", good_log, "-o", tmp_path / "o.mcap", "--config", config)
    assert_fails(capsys, USAGE, "not a parameters file: not UTF-8 text (byte 12", *args)


@pytest.mark.parametrize("fps", ["1e-300", "inf", "nan", "0", "-2", "2e9", "two"])
def test_a_frame_rate_no_folder_can_have_is_a_usage_error(
    fps: str, shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    images = shared_data / "rtabmap_samples_loop" / "images"
    gt = shared_data / "rtabmap_samples_loop" / "samples_GT.bmp"
    with pytest.raises(SystemExit) as exit_info:
        main(["evaluate", "--images", str(images), "--fps", fps, "--gt", str(gt)])
    err = capsys.readouterr().err
    assert exit_info.value.code == USAGE and "Traceback" not in err
    assert f"argument --fps: must be a frame rate from 1e-06 to 1e+09, got '{fps}'" in err


@pytest.mark.parametrize("bad", [np.nan, np.inf])
@pytest.mark.parametrize("suffix", [".npy", ".mat"])
def test_a_ground_truth_with_nan_or_inf_is_refused(
    bad: float, suffix: str, annotated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import scipy.io
    from scipy import sparse

    matrix = np.zeros((12, 12))
    matrix[:, :] = bad if np.isnan(bad) else 0.0
    matrix[7, 2] = bad
    gt = tmp_path / f"gt{suffix}"
    if suffix == ".npy":
        np.save(gt, matrix)
    else:
        scipy.io.savemat(gt, {"gt": sparse.csc_matrix(matrix)})
    cells = 144 if np.isnan(bad) else 1
    message = f"{cells} of {144 if suffix == '.npy' else cells} ground-truth cells are NaN"
    assert_fails(capsys, USAGE, message, "evaluate", annotated, "--gt", gt)


# --- 3. damaged records: our words, not Python's ----------------------------------------------

FOOTER_AT = -(8 + 29)  # the footer record (opcode, length, 20 bytes) before the closing magic


def _records(data: bytes, start: int, end: int) -> Iterator[tuple[int, int, int]]:
    """(opcode, offset, content length) of each record in data[start:end]."""
    while start < end:
        (length,) = struct.unpack_from("<Q", data, start + 1)
        yield data[start], start, length
        start += 9 + length


def _summary_records(data: bytes) -> list[tuple[int, int, int]]:
    footer = len(data) + FOOTER_AT
    summary_start, offsets_start = struct.unpack_from("<QQ", data, footer + 9)
    return list(_records(data, summary_start, offsets_start or footer))


def chunk_index_shifted_by_7(good: bytes) -> bytes:
    """Every chunk index points 7 bytes past its chunk: the reader parses the middle of one."""
    data = bytearray(good)
    for opcode, at, _ in _summary_records(good):
        if opcode == 0x08:  # ChunkIndex: start time, end time, chunk start offset, ...
            (offset,) = struct.unpack_from("<Q", data, at + 9 + 16)
            struct.pack_into("<Q", data, at + 9 + 16, offset + 7)
    return bytes(data)


def chunk_index_cut_to_8_bytes(good: bytes) -> bytes:
    """The first chunk index record holds 8 bytes of its 78 (the rest of the file follows)."""
    data = bytearray(good)
    _, at, length = next(r for r in _summary_records(good) if r[0] == 0x08)
    struct.pack_into("<Q", data, at + 1, 8)
    del data[at + 9 + 8 : at + 9 + length]
    return bytes(data)


def unchunked_message_shorter_than_its_header(good: Path) -> bytes:
    """The log rewritten without chunks; its 6th message record says it is 10 bytes long,
    less than a message's own 22-byte header."""
    from mcap.writer import Writer

    out = io.BytesIO()
    writer = Writer(out, use_chunking=False)
    writer.start("ros2", "test")
    for _ in make_bad_inputs.copied_messages(good, writer):
        pass
    writer.finish()
    data = bytearray(out.getvalue())
    messages = [at for opcode, at, _ in _records(data, 8, len(data) + FOOTER_AT) if opcode == 5]
    struct.pack_into("<Q", data, messages[5] + 1, 10)
    return bytes(data)


@pytest.mark.parametrize(
    ("damage", "words"),
    [
        ("chunk index shifted by 7", "a record holds a name or text that is not UTF-8"),
        ("chunk index cut to 8 bytes", "a record is shorter than its fields"),
        ("message shorter than its header", "a record's length or offset is impossible"),
    ],
)
def test_damaged_records_are_described_in_our_words(
    damage: str, words: str, good_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    good = good_log.read_bytes()
    data = {
        "chunk index shifted by 7": lambda: chunk_index_shifted_by_7(good),
        "chunk index cut to 8 bytes": lambda: chunk_index_cut_to_8_bytes(good),
        "message shorter than its header": lambda: unchunked_message_shorter_than_its_header(
            good_log
        ),
    }[damage]()
    log = tmp_path / "damaged.mcap"
    log.write_bytes(data)
    for args in (("info", log), ("annotate", log, "-o", tmp_path / "o.mcap", "--no-verify")):
        status, _, err = cli(capsys, *args)
        assert status == ExitCode.UNREADABLE_INPUT, err
        assert_one_error(err, f"({words}: the file is corrupt)")
        assert not re.search(r"[A-Za-z]+Error\b|unpack|codec|read length", err), err
    assert log.read_bytes() == data and not (tmp_path / "o.mcap").exists()


def _truncated_bmp(shared_data: Path, path: Path) -> Path:
    import cv2

    image = cv2.imread(str(shared_data / "rtabmap_samples_loop" / "images" / "1.jpg"))
    ok, encoded = cv2.imencode(".bmp", image)
    assert ok
    path.write_bytes(encoded.tobytes()[: encoded.size // 2])
    return path


def test_opencv_prints_nothing_of_its_own_for_a_truncated_bmp(
    shared_data: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    images = tmp_path / "images"
    images.mkdir()
    for name in ("1.jpg", "2.jpg"):
        (images / name).write_bytes(
            (shared_data / "rtabmap_samples_loop" / "images" / name).read_bytes()
        )
    _truncated_bmp(shared_data, images / "3.bmp")
    np.save(tmp_path / "gt.npy", np.zeros((3, 3)))
    gt_bmp = _truncated_bmp(shared_data, tmp_path / "gt.bmp")
    runs = [
        (
            ["--gt", str(tmp_path / "gt.npy")],
            ExitCode.UNREADABLE_INPUT,
            "3.bmp: cannot decode image",
        ),
        (["--gt", str(gt_bmp)], USAGE, "gt.bmp: not a readable image"),
    ]
    for gt, code, message in runs:
        capfd.readouterr()
        status = main(["evaluate", "--images", str(images), "--fps", "1", "--no-verify", *gt])
        err = capfd.readouterr().err
        assert status == code, err
        assert_one_error(err, message)
        assert "[ERROR" not in err and "OpenCV" not in err, err


def test_a_non_utf8_input_name_is_recorded_escaped(
    good_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from mcap.reader import make_reader

    log = tmp_path / os.fsdecode(b"caf\xe9.mcap")  # a Latin-1 name
    log.write_bytes(good_log.read_bytes())
    out = tmp_path / "o.mcap"
    status, _, err = cli(capsys, "annotate", log, "-o", out, "--no-verify")
    assert status == 0, err
    with out.open("rb") as stream:
        records = [m for m in make_reader(stream).iter_metadata() if m.name == "doseqslam"]
    assert records[0].metadata["source_file"] == "caf\\xe9.mcap"


def test_a_ros1_bag_named_mcap_is_read_as_ros1(
    jpegs: list[bytes], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = make_bad_inputs.write_log(tmp_path / "log.bag", make_bad_inputs.good_items(jpegs), "bag")
    named_mcap = tmp_path / "log.mcap"
    named_mcap.write_bytes(bag.read_bytes())
    lines = []
    for log in (bag, named_mcap):
        status, out, err = cli(capsys, "annotate", log, "-o", tmp_path / "o.mcap", "--no-verify")
        assert status == 0, err
        lines.append(out.split(": ", 1)[1].split(", 0.")[0])  # without the path and timing
    assert lines[0] == lines[1] and lines[0].startswith("12 frames of /camera/image/compressed")


def _without_metadata_index(annotated: Path, target: Path) -> Path:
    """The annotated log with a summary that has no MetadataIndex (and no summary offsets),
    as a tool that rewrites summaries may leave it: the metadata record is in the data only."""
    data = annotated.read_bytes()
    summary_start = struct.unpack_from("<Q", data, len(data) + FOOTER_AT + 9)[0]
    kept = b"".join(
        data[at : at + 9 + length]
        for opcode, at, length in _summary_records(data)
        if opcode != 0x0D  # MetadataIndex
    )
    footer = struct.pack("<BQQQI", 0x02, 20, summary_start, 0, 0)  # CRC 0: not computed
    target.write_bytes(data[:summary_start] + kept + footer + data[-8:])
    return target


def test_evaluate_reads_an_annotated_log_whose_summary_lacks_the_metadata_index(
    annotated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    np.save(tmp_path / "gt.npy", np.eye(12))
    rewritten = _without_metadata_index(annotated, tmp_path / "rewritten.mcap")
    reports = []
    for log in (annotated, rewritten):
        status, out, err = cli(capsys, "evaluate", log, "--gt", tmp_path / "gt.npy", "--json")
        assert status == 0, err
        reports.append({**json.loads(out), "log": None})
    assert reports[0] == reports[1] and reports[0]["tool_version"]


def test_a_truncated_annotated_log_says_so(
    annotated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(annotated.read_bytes()[:-30])
    args = ("export", cut, "--format", "csv")
    assert_fails(capsys, ExitCode.UNREADABLE_INPUT, "truncated MCAP file: it ends without", *args)


def test_evaluate_plot_refuses_a_picture_name_that_is_not_a_regular_file(
    annotated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("matplotlib")
    np.save(tmp_path / "gt.npy", np.eye(12))
    pictures = tmp_path / "pictures"
    pictures.mkdir()
    os.mkfifo(pictures / "difference_matrix.png")
    args = ("evaluate", annotated, "--gt", tmp_path / "gt.npy", "--plot", pictures)
    assert_fails(
        capsys, OUTPUT_ERROR, "difference_matrix.png: the output exists and is a FIFO", *args
    )
    assert sorted(p.name for p in pictures.iterdir()) == ["difference_matrix.png"]


def test_a_batch_manifest_that_is_a_fifo_is_refused_not_waited_on(
    good_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    outdir = tmp_path / "out"
    outdir.mkdir()
    os.mkfifo(outdir / "manifest.jsonl")  # opening it would block until someone reads
    args = ("batch", good_log, "-o", outdir, "--no-verify")
    assert_fails(capsys, OUTPUT_ERROR, "manifest.jsonl: the output exists and is a FIFO", *args)
    assert sorted(p.name for p in outdir.iterdir()) == ["manifest.jsonl"]
