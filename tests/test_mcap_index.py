"""Ranged reads through the message indexes give what mcap's SeekingReader gives, faster."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import SeekingReader
from mcap.writer import IndexType, Writer

from doseqslam_logs.errors import SourceError
from doseqslam_logs.sources.mcap_index import indexed_topic_messages
from doseqslam_logs.sources.mcap_source import McapSource, _iter_topic

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
LOOPS = SAMPLES / "drive_loops.ros2.mcap"


def summary_of(path: Path):
    with McapSource(path) as source:
        return source.summary if source.indexed else None


def indexed_files(shared_data: Path) -> list[Path]:
    files = sorted(shared_data.rglob("*.mcap")) + sorted(SAMPLES.glob("*.mcap"))
    return [f for f in files if summary_of(f) is not None]


def reference(path: Path, topic: str, start: int | None, end: int | None) -> list[tuple]:
    with path.open("rb") as file:
        reader = SeekingReader(file, validate_crcs=True)
        records = _iter_topic(reader, topic, start, end, ordered=True)
        return [(c.id, m.log_time, m.publish_time, m.sequence, m.data) for _, c, m in records]


def by_index(path: Path, topic: str, start: int | None, end: int | None) -> list[tuple] | None:
    summary = summary_of(path)
    assert summary is not None
    with path.open("rb") as file:
        records = indexed_topic_messages(file, summary, topic, start, end)
        if records is None:
            return None
        return [(c.id, m.log_time, m.publish_time, m.sequence, m.data) for _, c, m in records]


def test_every_topic_of_the_real_files_reads_the_same(shared_data) -> None:
    files = indexed_files(shared_data)
    assert len(files) >= 4  # real MCAP files of other tools and our samples
    compared = 0
    for path in files:
        summary = summary_of(path)
        assert summary is not None
        first = min(c.message_start_time for c in summary.chunk_indexes)
        last = max(c.message_end_time for c in summary.chunk_indexes)
        middle = (first + (last - first) // 3, first + (last - first) // 2)
        for topic in sorted({channel.topic for channel in summary.channels.values()}):
            for start, end in ((None, None), middle):
                expected = reference(path, topic, start, end)
                assert by_index(path, topic, start, end) == expected, (path, topic)
                compared += bool(expected)
    assert compared >= 10


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 130_000_000_000), st.integers(0, 20_000_000_000))
def test_any_range_of_a_sample_reads_the_same(offset, span) -> None:
    start = 1_700_000_000_000_000_000 + offset
    for topic in ("/camera/image/compressed", "/camera/camera_info"):
        expected = reference(LOOPS, topic, start, start + span)
        assert by_index(LOOPS, topic, start, start + span) == expected


def test_chunks_without_message_indexes_fall_back(tmp_path) -> None:
    path = tmp_path / "unindexed.mcap"
    with path.open("wb") as stream:
        writer = Writer(stream, index_types=IndexType.ALL & ~IndexType.MESSAGE)
        writer.start()
        schema = writer.register_schema("s", "jsonschema", b"{}")
        channel = writer.register_channel("/t", "json", schema)
        for t in range(5):
            writer.add_message(channel, t, b"{}", t)
        writer.finish()
    summary = summary_of(path)
    assert summary is not None
    with path.open("rb") as file:
        assert indexed_topic_messages(file, summary, "/t", None, None) is None


def test_a_corrupt_chunk_is_an_error_not_wrong_frames(tmp_path) -> None:
    damaged = tmp_path / "damaged.mcap"
    shutil.copy(LOOPS, damaged)
    summary = summary_of(damaged)
    assert summary is not None
    chunk = summary.chunk_indexes[len(summary.chunk_indexes) // 2]
    with damaged.open("r+b") as file:  # a byte of the compressed records, near the end
        file.seek(chunk.chunk_start_offset + chunk.chunk_length - 10)
        byte = file.read(1)
        file.seek(-1, 1)
        file.write(bytes([byte[0] ^ 0xFF]))
    start, end = chunk.message_start_time, chunk.message_end_time + 1
    topic, unreadable = "/camera/image/compressed", "cannot read the messages"
    with McapSource(damaged) as source, pytest.raises(SourceError, match=unreadable):
        list(source.image_messages(topic, start, end))
