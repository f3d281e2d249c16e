"""The fast paths of issue #7: the SAD kernel, chunked enhancement, the threaded replay."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from doseqslam_logs.detector import Parameters, PreparedFrame, make_detector
from doseqslam_logs.detector import enhance as enhance_module
from doseqslam_logs.detector.difference import FrameStore, sad_rows, sad_sums_uint8
from doseqslam_logs.pipeline.decode import FrameCounts, decoded_frames
from doseqslam_logs.pipeline.replay import LOOKAHEAD_FRAMES, replay
from doseqslam_logs.sources import open_source, pick_image_topic
from doseqslam_logs.sources.frame import Frame

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_logs" / "drive_loops.ros2.mcap"
DIMENSION = 2048


def naive_sums(queries: np.ndarray, database: np.ndarray) -> np.ndarray:
    return np.abs(queries[:, None, :].astype(np.int64) - database[None, :, :]).sum(axis=2)


@settings(max_examples=60, deadline=None)
@given(
    st.integers(1, 60),  # query rows: both layouts of the kernel (SHORT_QUERIES = 48)
    st.integers(0, 150),  # database frames
    st.integers(1, 70),  # frames per store block: chunks end inside and at block ends
    st.integers(1, 33),  # queries per group: groups end inside and at the last query
    st.integers(1, 80),  # database frames per kernel call
    st.integers(0, 2**32 - 1),
)
def test_sad_kernel_equals_the_naive_sums(rows, frames, block, group, chunk, seed) -> None:
    rng = np.random.default_rng(seed)
    # Few distinct vectors: many equal distances, which the kernel's sort must not mix up.
    palette = rng.integers(0, 256, (4, 24), dtype=np.uint8)
    database = palette[rng.integers(0, 4, frames)]
    database[:, 0] = rng.integers(0, 256, frames)  # and some distinct ones
    queries = rng.integers(0, 256, (rows, 24), dtype=np.uint8)
    blocks = [database[s : s + block] for s in range(0, frames, block)]
    sums = sad_sums_uint8(queries, blocks, group, chunk)
    np.testing.assert_array_equal(sums, naive_sums(queries, database))
    np.testing.assert_array_equal(sad_sums_uint8(queries, blocks), sums)  # the defaults


def test_sad_rows_uint8_of_real_sized_vectors() -> None:
    rng = np.random.default_rng(3)
    store = FrameStore(DIMENSION, "uint8", block_frames=100)
    vectors = rng.normal(0, 1, (333, DIMENSION)).astype(np.float32)
    for vector in vectors:
        store.append(vector)
    stored = store.rows(0, 332)
    queries = store.rows(300, 310)
    rows = sad_rows(queries, store, 290)
    expected = naive_sums(queries, stored[:290]) / (16.0 * DIMENSION)
    assert rows.dtype == np.float32 and rows.shape == (11, 290)
    np.testing.assert_array_equal(rows, expected.astype(np.float32))


def test_enhancement_does_not_depend_on_the_chunk_size(monkeypatch) -> None:
    rng = np.random.default_rng(5)
    rows = (rng.integers(20_000, 60_000, (7, 3000)) / 32768.0).astype(np.float32)
    monkeypatch.setattr(enhance_module, "CHUNK_ELEMENTS", 1 << 24)  # one chunk
    whole = enhance_module.enhance(rows, 10)
    monkeypatch.setattr(enhance_module, "CHUNK_ELEMENTS", 1 << 15)  # one row per chunk
    chunked = enhance_module.enhance(rows, 10)
    np.testing.assert_array_equal(whole, chunked)


# ---------------------------------------------------------------------------------------------
# The threaded replay


@pytest.fixture(scope="module")
def sample_frames() -> list[Frame]:
    with open_source(SAMPLE) as source:
        messages = source.image_messages(pick_image_topic(source))
        return list(decoded_frames(messages, FrameCounts()))


def test_threaded_replay_gives_the_serial_decisions_and_stage_times(sample_frames) -> None:
    serial = replay(sample_frames, make_detector(Parameters()), workers=1)
    threaded = replay(iter(sample_frames), make_detector(Parameters()), workers=2)
    assert threaded.decisions == serial.decisions and threaded.loop_closures > 0
    assert threaded.frames == len(sample_frames)
    stages = threaded.stage_seconds
    assert {"wait", "preprocess", "features", "segmentation", "sad", "enhance"} <= set(stages)
    assert all(seconds >= 0 for seconds in stages.values()) and stages["features"] > 0


def reader_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "frame-reader"]


def test_an_error_while_reading_reaches_the_caller_and_stops_the_threads(sample_frames) -> None:
    closed = []

    def failing() -> Iterator[Frame]:
        try:
            yield from sample_frames[:30]
            raise OSError("disk gone")
        finally:
            closed.append(True)

    with pytest.raises(OSError, match="disk gone"):
        replay(failing(), make_detector(Parameters()), workers=2)
    assert closed == [True] and not reader_threads()


class _Failing:
    """A detector whose push fails at one frame, counting the frames it was given."""

    def __init__(self, fail_at: int) -> None:
        self.inner = make_detector(Parameters())
        self.fail_at = fail_at
        self.pushed = 0
        self.feature_detector = self.inner.feature_detector
        self.memory_bytes = 0

    def prepare(self, gray: np.ndarray, supplied: object = None) -> PreparedFrame:
        return self.inner.prepare(gray)

    def push_prepared(self, timestamp_ns: int, frame: PreparedFrame) -> list:
        self.pushed += 1
        if self.pushed == self.fail_at:
            raise RuntimeError("detector failed")
        time.sleep(0.001)
        return []

    def finish(self) -> list:
        return []


def test_a_failing_detector_stops_the_reader_and_closes_the_frames() -> None:
    produced = []
    closed = []

    def frames() -> Iterator[Frame]:
        image = np.zeros((48, 64), np.uint8)
        try:
            for i in range(100_000):
                produced.append(i)
                yield Frame(i, i * 10**8, i * 10**8, None, image)
        finally:
            closed.append(True)

    detector = _Failing(fail_at=50)
    with pytest.raises(RuntimeError, match="detector failed"):
        replay(frames(), detector, workers=2)  # type: ignore[arg-type]
    assert closed == [True] and not reader_threads()
    # The reader ran ahead by at most the lookahead, the frames in prepare and one in hand.
    assert 50 <= len(produced) <= 50 + LOOKAHEAD_FRAMES + 2 * 2 + 2


def test_bench_annotate_measures_decoding_of_the_sample() -> None:
    from bench import annotate as bench_annotate

    figures = bench_annotate.measure_decode(SAMPLE, None)
    assert figures["frames"] == 240 and figures["log_s"] > 0 and figures["wall_s"] > 0
    cut = bench_annotate.measure_decode(SAMPLE, 0.5)  # the first 30 s only
    assert 0 < cut["frames"] < 240 and cut["log_s"] <= 30.5
    figures.update(cpu_s=1.0, peak_rss_mb=50.0, load=1.0)
    table = bench_annotate.table([("sample", "decode", figures)])
    assert table.splitlines()[2].startswith("| sample | decode | 240 |")
