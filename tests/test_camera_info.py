"""Issue #40, item 2: a CameraInfo whose K cannot be a camera is reported, never used as if
the log had none. Each unusable message is counted by reason; the first usable one is the
camera's; with none, verification assumes a pinhole camera (`Intrinsics.assumed`) and says so,
and no metric pose is fitted with it."""

from __future__ import annotations

import contextlib
import io
import json
import math
import struct
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.cli.main import main
from doseqslam_logs.sources.camera_info import (
    MAX_CAMERA_INFOS,
    CameraInfo,
    _camera_info,
    find_camera_info,
)
from doseqslam_logs.verification import Intrinsics

REPO = Path(__file__).resolve().parents[1]
LOOPS = REPO / "sample_logs" / "drive_loops.ros2.mcap"
IMAGE = "/camera/image/compressed"
INFO_TOPIC = "/camera/camera_info"


def _k(fx: float, fy: float, cx: float, cy: float) -> list[float]:
    return [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]


def _message(k: object) -> SimpleNamespace:
    return SimpleNamespace(k=k, width=256, height=192)


@pytest.mark.parametrize(
    ("k", "reason"),
    [
        ([0.0] * 9, "K all zero"),
        (_k(math.nan, 180, 128, 96), "K not finite"),
        (_k(180, math.inf, 128, 96), "K not finite"),
        (_k(-180, 180, 128, 96), "focal length not positive"),
        (_k(0, 0, 128, 96), "focal length not positive"),
        ([1.0] * 8, "K of 8 values"),
        (None, "no K"),
        ("not numbers", "no K"),
    ],
)
def test_a_k_that_cannot_be_a_camera_is_named(k: object, reason: str) -> None:
    assert _camera_info(INFO_TOPIC, _message(k)) == reason


@given(
    st.floats(1e-3, 1e6),
    st.floats(1e-3, 1e6),
    st.floats(-1e6, 1e6),
    st.floats(-1e6, 1e6),
)
def test_a_finite_k_with_positive_focal_lengths_is_a_camera(
    fx: float, fy: float, cx: float, cy: float
) -> None:
    info = _camera_info(INFO_TOPIC, _message(_k(fx, fy, cx, cy)))
    assert info == CameraInfo(INFO_TOPIC, 256, 192, fx, fy, cx, cy)


@given(st.integers(1, 10_000), st.integers(1, 10_000))
def test_the_assumed_camera_looks_across_the_larger_side_from_the_centre(
    width: int, height: int
) -> None:
    k = Intrinsics.assumed(width, height)
    assert k.fx == k.fy == max(width, height)
    assert (k.cx, k.cy) == (width / 2, height / 2)


def _copy_with_k(out: Path, k_of: dict[int, list[float]]) -> Path:
    """drive_loops with the i-th CameraInfo's K replaced by k_of[i] (the others as they are)."""
    true_k = find_camera_info(LOOPS, IMAGE).info
    assert true_k is not None
    packed = struct.pack("<9d", *_k(true_k.fx, true_k.fy, true_k.cx, true_k.cy))
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    infos = 0
    with LOOPS.open("rb") as stream, out.open("wb") as sink:
        writer = Writer(sink, compression=CompressionType.ZSTD)
        writer.start(profile="ros2")
        for schema, channel, message in make_reader(stream).iter_messages():
            assert schema is not None
            data = message.data
            if channel.topic == INFO_TOPIC:
                if infos in k_of:
                    at = data.find(packed)
                    assert at > 0
                    data = data[:at] + struct.pack("<9d", *k_of[infos]) + data[at + 72 :]
                infos += 1
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id]
                )
            writer.add_message(channels[channel.id], message.log_time, data, message.publish_time)
        writer.finish()
    assert infos > MAX_CAMERA_INFOS
    return out


def test_zeros_before_the_calibration_are_skipped_and_counted(tmp_path: Path) -> None:
    log = _copy_with_k(tmp_path / "late.mcap", {i: [0.0] * 9 for i in range(3)})
    search = find_camera_info(log, IMAGE)
    assert search.info is not None and search.info.fx > 0
    assert search.unusable == {"K all zero": 3}
    assert search.describe_unusable() == (
        f"3 CameraInfo of {INFO_TOPIC} with a K that is not a camera (K all zero: 3)"
    )


def test_a_topic_of_unusable_k_is_read_no_further_than_its_limit(tmp_path: Path) -> None:
    log = _copy_with_k(tmp_path / "zero.mcap", {i: [0.0] * 9 for i in range(500)})
    search = find_camera_info(log, IMAGE)
    assert search.info is None and search.unusable == {"K all zero": MAX_CAMERA_INFOS}


@pytest.mark.slow
def test_a_log_whose_k_is_all_zero_is_verified_with_an_assumed_camera_and_no_false_pair(
    tmp_path: Path,
) -> None:
    """Before: the fundamental matrix, 119 pairs of which 11 false, and every pair's reason
    "no CameraInfo". Now: a warning, 58 pairs (measured), all true."""
    log = _copy_with_k(tmp_path / "zero.mcap", {i: [0.0] * 9 for i in range(500)})
    out = tmp_path / "zero.out.mcap"
    printed, warned = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(warned):
        assert main(["annotate", str(log), "-o", str(out), "--json"]) == 0
    assert "with a K that is not a camera (K all zero: 100); verified with an assumed" in (
        warned.getvalue()
    )
    assert json.loads(printed.getvalue())["verification"]["intrinsics_source"] == "assumed"
    annotated = read_annotations(out)
    assert annotated.metadata.intrinsics_source == "assumed"
    reported = annotated.reported_loop_closures
    assert len(reported) >= 40
    gt = np.load(REPO / "sample_logs" / "drive_loops.gt.npz")["gt"]
    assert [lc for lc in reported if not gt[lc.query.index, lc.matched.index]] == []
    # no metric pose from a guessed camera, and the reason says why
    assert {lc.metric_method for lc in reported} == {""}
    assert {lc.metric_reason for lc in reported} == {
        f"no intrinsics (100 CameraInfo of {INFO_TOPIC} with a K that is not a camera "
        "(K all zero: 100); no --intrinsics)"
    }
