"""Messages -> frames: time source, skipped frames and their counts; time arguments."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from doseqslam_logs.cli.times import parse_time_ns
from doseqslam_logs.errors import ImageDecodeError, SourceError, UsageError
from doseqslam_logs.pipeline.decode import SKIP_BACKWARDS, SKIP_DECODE, FrameCounts, decoded_frames
from doseqslam_logs.sources.base import ImageMessage


def mono(
    log_time: int, stamp: int | None, pixels: int = 7, size: int | None = None
) -> ImageMessage:
    data = bytes([pixels]) * (size if size is not None else 16)
    return ImageMessage("/cam", log_time, stamp, "raw", "mono8", 4, 4, 4, False, data)


def test_header_time_with_log_time_fallback_for_zero_stamps() -> None:
    counts = FrameCounts()
    frames = list(decoded_frames([mono(10, 5), mono(20, 0), mono(30, None), mono(40, 41)], counts))
    # A frame without a stamp moves on by its log time since the previous frame, on the
    # camera clock (5 + 10, + 10), not to its raw log time (20, 30: 15 ns behind the camera).
    assert [f.timestamp_ns for f in frames] == [5, 15, 25, 41]
    assert counts.log_time_fallbacks == 2 and counts.used == 4
    assert [f.index for f in frames] == [0, 1, 2, 3]


def test_log_time_source_ignores_header_stamps() -> None:
    frames = list(decoded_frames([mono(10, 500), mono(20, 5)], FrameCounts(), "log"))
    assert [f.timestamp_ns for f in frames] == [10, 20]


def test_backward_stamps_and_bad_images_are_skipped_and_counted() -> None:
    counts = FrameCounts()
    msgs = [mono(1, 100), mono(2, 50), mono(3, 100), mono(4, 101, size=3), mono(5, 102)]
    frames = list(decoded_frames(msgs, counts))
    assert [f.timestamp_ns for f in frames] == [100, 100, 102]  # equal stamps are kept
    assert counts.skipped == {SKIP_BACKWARDS: 1, SKIP_DECODE: 1}
    assert counts.messages == 5 and counts.used == 3 and counts.skipped_total == 2
    assert "50 < 100" in counts.first_skip[SKIP_BACKWARDS]


def test_on_error_fail_raises_the_first_problem() -> None:
    with pytest.raises(ImageDecodeError):
        list(decoded_frames([mono(1, 1, size=3)], FrameCounts(), on_error="fail"))
    with pytest.raises(SourceError, match="earlier than the previous"):
        list(decoded_frames([mono(1, 9), mono(2, 8)], FrameCounts(), on_error="fail"))


def test_frames_are_decoded_pixels() -> None:
    frame = next(decoded_frames([mono(1, 1, pixels=200)], FrameCounts()))
    assert frame.image.shape == (4, 4) and (frame.image == 200).all()
    assert frame.image.dtype == np.uint8


def test_time_arguments() -> None:
    assert parse_time_ns("1700000000123456789") == 1700000000123456789
    assert parse_time_ns("2023-11-14T22:13:20Z") == 1_700_000_000 * 10**9
    assert parse_time_ns("2023-11-14T23:13:20.000000001+01:00") == 1_700_000_000 * 10**9 + 1
    for bad in ("yesterday", "2023-11-14T22:13:20", "2023-13-14T22:13:20Z", "-5", ""):
        with pytest.raises(UsageError):
            parse_time_ns(bad)


@given(
    st.datetimes(
        min_value=datetime(1971, 1, 1),
        max_value=datetime(2200, 1, 1),
        timezones=st.just(timezone.utc),
    ),
    st.integers(0, 999),
    st.integers(-12 * 60, 14 * 60),
)
def test_rfc3339_round_trips_to_nanoseconds(moment, nanos, offset_minutes) -> None:
    expected = int(moment.timestamp()) * 10**9 + moment.microsecond * 1000 + nanos
    zone = timezone(timedelta(minutes=offset_minutes))
    local = moment.astimezone(zone)
    fraction = f"{local.microsecond:06d}{nanos:03d}"
    text = local.strftime("%Y-%m-%dT%H:%M:%S") + "." + fraction + local.strftime("%z")
    text = text[:-2] + ":" + text[-2:]
    assert parse_time_ns(text) == expected
