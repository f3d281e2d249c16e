"""`/doseqslam/loop_closures` holds the loop closures the run reports and nothing else; the pairs
it decided on but does not report (verification rejected or skipped them) are on
`/doseqslam/candidates`, the same LoopClosure messages. Every reader takes both topics, and an
output with every pair on /doseqslam/loop_closures (as earlier versions wrote it) reads the same.
"""

from __future__ import annotations

import json
import shutil
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from doseqslam_logs.annotations.reader import plain, read_annotations
from doseqslam_logs.annotations.records import (
    CANDIDATE,
    LOOP_CLOSURE,
    REJECTED,
    SKIPPED,
    LoopClosureRecord,
)
from doseqslam_logs.cli.main import main
from doseqslam_logs.sources.mcap_source import DESERIALIZERS

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
GROUND_TRUTH = SAMPLES / "drive_loops.gt.npz"


def topic_messages(path: Path, topic: str) -> list[tuple[int, LoopClosureRecord]]:
    """(log time, record) of every message of one topic, in the file's log-time order."""
    found = []
    with path.open("rb") as stream:
        reader = make_reader(stream)
        for schema, channel, message in reader.iter_messages(topics=[topic], log_time_order=True):
            decode = DESERIALIZERS[(channel.message_encoding, schema.encoding)](schema)
            record = LoopClosureRecord.from_message(plain(decode(message.data)))
            found.append((message.log_time, record))
    return found


def statistics_counts(path: Path) -> dict[str, int]:
    """The messages per topic that the output's Statistics record promises."""
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics is not None
    counts = summary.statistics.channel_message_counts
    return {ch.topic: counts.get(cid, 0) for cid, ch in summary.channels.items()}


def rewrite_with_one_loop_closure_topic(new: Path, old: Path) -> None:
    """`new` as versions before the candidates topic wrote it: every LoopClosure message on
    /doseqslam/loop_closures (log-time order, sequence numbers counted on it), every other
    record as it was."""
    with new.open("rb") as stream, old.open("wb") as out:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None
        header = reader.get_header()
        writer = Writer(out)
        writer.start(profile=header.profile, library=header.library)
        schemas = {
            sid: writer.register_schema(s.name, s.encoding, s.data)
            for sid, s in summary.schemas.items()
        }
        channels = {
            ch.topic: writer.register_channel(
                ch.topic, ch.message_encoding, schemas[ch.schema_id], dict(ch.metadata)
            )
            for ch in summary.channels.values()
            if ch.topic != CANDIDATE.topic
        }
        channels[CANDIDATE.topic] = channels[LOOP_CLOSURE.topic]
        loop_closures = 0
        for _, channel, message in reader.iter_messages(log_time_order=True):
            sequence = message.sequence
            if channel.topic in (LOOP_CLOSURE.topic, CANDIDATE.topic):
                sequence, loop_closures = loop_closures, loop_closures + 1
            writer.add_message(
                channels[channel.topic],
                message.log_time,
                message.data,
                message.publish_time,
                sequence,
            )
        for a in reader.iter_attachments():
            writer.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
        for m in reader.iter_metadata():
            writer.add_metadata(m.name, dict(m.metadata))
        writer.finish()  # type: ignore[no-untyped-call]


def as_text(records: Any) -> list[str]:
    """Records compared by their text: a missing float is NaN, never equal to itself."""
    return [repr(record) for record in records]


def run_cli(capsys: pytest.CaptureFixture[str], *args: str | Path) -> tuple[int, str]:
    capsys.readouterr()
    code = main([str(a) for a in args])
    return code, capsys.readouterr().out


# --- the two topics -------------------------------------------------------------------------


@pytest.fixture(scope="module", params=["drive_loops.ros2.mcap", "drive_parked.ros2.mcap"])
def annotated(request: pytest.FixtureRequest, annotated_sample: Callable[..., Path]) -> Path:
    return annotated_sample(request.param)  # `annotate` with its defaults: verification on


def test_the_loop_closures_topic_holds_exactly_the_reported_pairs(annotated: Path) -> None:
    reported = topic_messages(annotated, LOOP_CLOSURE.topic)
    metadata = read_annotations(annotated).metadata
    # The metadata's count is the summary line's "N loop closures".
    assert len(reported) == metadata.loop_closures > 0
    assert all(record.reported for _, record in reported)
    assert [t for t, _ in reported] == sorted(t for t, _ in reported)
    assert all(t == record.query.log_time_ns for t, record in reported)


def test_the_candidates_topic_holds_every_other_pair(annotated: Path) -> None:
    candidates = topic_messages(annotated, CANDIDATE.topic)
    metadata = read_annotations(annotated).metadata
    assert len(candidates) == metadata.verified_pairs - metadata.loop_closures > 0
    assert not any(record.reported for _, record in candidates)
    verdicts = Counter(record.verification for _, record in candidates)
    assert set(verdicts) <= {REJECTED, SKIPPED} and verdicts[REJECTED] > 0
    assert [t for t, _ in candidates] == sorted(t for t, _ in candidates)


def test_the_two_topics_together_are_every_pair_the_run_decided_on(annotated: Path) -> None:
    # The sequences record the accepted decisions' pairs, independently of the LoopClosure
    # messages: between them the two topics hold each exactly once.
    both = topic_messages(annotated, LOOP_CLOSURE.topic)
    both += topic_messages(annotated, CANDIDATE.topic)
    decided = Counter(
        pair
        for sequence in read_annotations(annotated).sequences
        if sequence.accepted
        for pair in zip(
            sequence.candidate_query_indices, sequence.candidate_match_indices, strict=True
        )
    )
    assert Counter((r.query.index, r.match.index) for _, r in both) == decided
    in_order = sorted(both, key=lambda item: (item[0], item[1].query.index))
    assert as_text(read_annotations(annotated).loop_closures) == as_text(r for _, r in in_order)


def test_the_statistics_record_promises_both_topics_counts(annotated: Path) -> None:
    counts = statistics_counts(annotated)
    for topic in (LOOP_CLOSURE.topic, CANDIDATE.topic):
        assert counts[topic] == len(topic_messages(annotated, topic))


def test_info_lists_the_candidates_channel_with_its_count(annotated: Path, capsys) -> None:
    code, out = run_cli(capsys, "info", annotated, "--json")
    channels = {c["topic"]: c["message_count"] for c in json.loads(out)["other_channels"]}
    assert code == 0
    assert channels[CANDIDATE.topic] == len(topic_messages(annotated, CANDIDATE.topic))
    assert channels[LOOP_CLOSURE.topic] == len(topic_messages(annotated, LOOP_CLOSURE.topic))


# --- outputs of earlier versions ------------------------------------------------------------


@pytest.fixture(scope="module", params=["drive_loops.ros2.mcap", "drive_loops.bag"])
def layouts(
    request: pytest.FixtureRequest,
    annotated_sample: Callable[..., Path],
    tmp_path_factory: pytest.TempPathFactory,
) -> dict[str, Path]:
    """The same run in both layouts, each as `annotated.mcap` in its own folder (the commands
    run there print the same relative names)."""
    root = tmp_path_factory.mktemp("layouts")
    (root / "new").mkdir()
    (root / "old").mkdir()
    new, old = root / "new" / "annotated.mcap", root / "old" / "annotated.mcap"
    shutil.copyfile(annotated_sample(request.param), new)
    rewrite_with_one_loop_closure_topic(new, old)
    assert not topic_messages(old, CANDIDATE.topic)
    assert any(not r.reported for _, r in topic_messages(old, LOOP_CLOSURE.topic))
    return {"new": new, "old": old}


def in_each_layout(
    layouts: dict[str, Path],
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    *args: str,
) -> dict[str, tuple[int, str, dict[str, str]]]:
    """Exit code, stdout and the files written, of `doseqslam-logs ARGS` run in each layout's
    folder (`annotated.mcap` there)."""
    results = {}
    for name, path in layouts.items():
        monkeypatch.chdir(path.parent)
        before = set(path.parent.iterdir())
        code, out = run_cli(capsys, *args)
        written = {p.name: p.read_text() for p in set(path.parent.iterdir()) - before}
        for p in set(path.parent.iterdir()) - before:
            p.unlink()
        results[name] = (code, out, written)
    return results


def test_the_reader_gives_the_same_records_in_both_layouts(layouts) -> None:
    new, old = read_annotations(layouts["new"]), read_annotations(layouts["old"])
    assert as_text(old.loop_closures) == as_text(new.loop_closures)
    assert as_text(old.sequences) == as_text(new.sequences)
    assert old.metadata.recorded == new.metadata.recorded
    assert old.frame_times is not None and new.frame_times is not None
    assert np.array_equal(old.frame_times.log_times_ns, new.frame_times.log_times_ns)


def test_diff_of_the_two_layouts_finds_no_difference(layouts, capsys) -> None:
    code, out = run_cli(capsys, "diff", layouts["old"], layouts["new"], "--json")
    doc = json.loads(out)
    assert code == 0 and doc["equal"] is True
    verdicts = doc["verdict_changes"]
    assert verdicts["changed"] == 0 and verdicts["compared"] == doc["a"]["loop_closures"]
    assert doc["counts"]["only_a"] == doc["counts"]["only_b"] == 0
    assert {k: v for k, v in doc["a"].items() if k != "path"} == {
        k: v for k, v in doc["b"].items() if k != "path"
    }
    assert doc["metadata_differences"] == [] and doc["parameter_differences"] == []
    code, table = run_cli(capsys, "diff", layouts["old"], layouts["new"])
    assert "parameters: no difference" in table and "metadata: no difference" in table
    assert table.rstrip().endswith("result: reported loop closures are the same (exit 0)")


@pytest.mark.parametrize(
    "args",
    [
        ("evaluate", "annotated.mcap", "--gt", str(GROUND_TRUTH), "--json"),
        ("export", "annotated.mcap", "--format", "csv", "-o", "loops.csv"),
        ("export", "annotated.mcap", "--format", "jsonl", "--include-rejected", "-o", "all.jsonl"),
        ("export", "annotated.mcap", "--format", "csv", "--include-rejected"),
        ("export", "annotated.mcap", "--format", "g2o", "-o", "graph.g2o"),
        ("export", "annotated.mcap", "--format", "tum", "-o", "odom.tum"),
    ],
    ids=lambda args: " ".join(a for a in args if a != str(GROUND_TRUTH)),
)
def test_the_commands_print_and_write_the_same_in_both_layouts(
    layouts, monkeypatch, capsys, args: tuple[str, ...]
) -> None:
    results = in_each_layout(layouts, monkeypatch, capsys, *args)
    assert results["old"] == results["new"]
    code, out, written = results["new"]
    assert code == 0 and (out or written)


def test_optimize_gives_the_same_graph_in_both_layouts(layouts, monkeypatch, capsys) -> None:
    pytest.importorskip("gtsam")
    args = ("optimize", "annotated.mcap", "-o", "optimized.mcap", "--json")
    results: dict[str, Any] = {}
    for name, path in layouts.items():
        monkeypatch.chdir(path.parent)
        code, out = run_cli(capsys, *args)
        results[name] = (code, json.loads(out))
    assert results["old"] == results["new"] and results["new"][0] == 0


def test_info_names_the_same_run_in_both_layouts(layouts, capsys) -> None:
    runs = {}
    for name, path in layouts.items():
        code, out = run_cli(capsys, "info", path, "--json")
        runs[name] = (code, json.loads(out)["doseqslam_run"])
    assert runs["old"] == runs["new"] and runs["new"][1]["loop_closures"] > 0
