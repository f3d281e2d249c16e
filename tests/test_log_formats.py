"""One entry per log format (sources.formats): a new format added as one module and one entry
(tests/toy_format.py) is opened, annotated end to end, copied into the output and found by a
batch, with nothing else changed."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest
from mcap.reader import make_reader
from toy_format import TOPIC, TOY, write_toy_log

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.batch.discovery import discover_logs
from doseqslam_logs.errors import SourceError
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.sources import formats, open_source, pick_image_topic
from doseqslam_logs.sources.formats import FORMATS, format_of, log_file_suffixes

SAMPLE = Path(__file__).resolve().parents[1] / "sample_logs" / "drive_loops.ros2.mcap"


@pytest.fixture
def toy_registered(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(formats, "FORMATS", [*FORMATS, TOY])


@pytest.fixture(scope="module")
def toy_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The sample's frames as a toy log, each at its header stamp (the sample's frame time)."""
    with open_source(SAMPLE) as source:
        messages = source.image_messages(pick_image_topic(source))
        frames = [(m.header_stamp_ns or m.log_time_ns, m.data) for m in messages]
    path = tmp_path_factory.mktemp("toy") / "drive.toy"
    write_toy_log(path, frames)
    return path


def pairs(path: Path) -> list[tuple[int, int]]:
    return [(lc.query.index, lc.match.index) for lc in read_annotations(path).loop_closures]


def test_an_unregistered_format_is_not_a_log_and_the_message_lists_the_formats(
    toy_log: Path,
) -> None:
    with pytest.raises(SourceError, match=r"not a log file \(not MCAP, ROS 1 \.bag, rosbag2"):
        format_of(toy_log)
    assert ".toy" not in log_file_suffixes()


def test_a_registered_toy_format_is_opened_by_its_content(
    toy_registered: None, toy_log: Path, tmp_path: Path
) -> None:
    renamed = tmp_path / "drive.mcap"  # told by its magic, not by its name
    renamed.write_bytes(toy_log.read_bytes())
    assert format_of(renamed) is TOY
    with open_source(renamed) as source:
        assert pick_image_topic(source) == TOPIC
        assert sum(1 for _ in source.image_messages(TOPIC)) == 240


def test_a_registered_toy_format_annotates_end_to_end(
    toy_registered: None, toy_log: Path, tmp_path: Path, annotated_sample
) -> None:
    out = tmp_path / "drive.annotated.mcap"
    result = annotate_log(toy_log, out)
    assert result.written.input_kind == "toy" and result.written.copied_messages == 240
    assert result.loop_closures > 0
    with out.open("rb") as stream:
        topics = Counter(c.topic for _, c, _ in make_reader(stream).iter_messages())
    assert topics[TOPIC] == 240 and topics["/doseqslam/loop_closures"] > 0
    # The paper's decision sees the same frames at the same times: the same pairs as the
    # sample's own run.
    paper = tmp_path / "paper.mcap"
    annotate_log(toy_log, paper, options=AnnotateOptions(verification=None))
    expected = annotated_sample("drive_loops.ros2.mcap", "--no-verify")
    assert pairs(paper) == pairs(expected) and len(pairs(paper)) > 30


def test_a_batch_finds_the_toy_logs_by_the_formats_names(
    toy_registered: None, toy_log: Path, tmp_path: Path
) -> None:
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "a.toy").write_bytes(toy_log.read_bytes())
    (tmp_path / "logs" / "notes.txt").write_text("not a log")
    found = discover_logs([str(tmp_path / "logs")], tmp_path / "out")
    assert [f.path.name for f in found] == ["a.toy"]
    assert found[0].relative_output == Path("a.toy.annotated.mcap")
