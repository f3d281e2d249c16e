"""Memory that must not grow with the log: the frame store's spill (detector/difference.py,
pipeline/frame_spill.py)."""

from __future__ import annotations

import gc
import math
import tempfile
import weakref
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from detector_helpers import DictSpill
from test_sinks import make_decisions, make_frame_times, write_json_mcap

from doseqslam_logs.detector import Parameters, make_detector
from doseqslam_logs.detector.difference import FrameStore, sad_columns, sad_rows
from doseqslam_logs.errors import OutputError
from doseqslam_logs.pipeline.annotate import AnnotateOptions, StageObserver, annotate_log
from doseqslam_logs.pipeline.frame_spill import FileSpill, spilled_frame_store
from doseqslam_logs.sinks.mcap_writer import Annotations, write_annotated_mcap
from doseqslam_logs.sinks.message_spool import SpooledMessages, in_order

SAMPLE = Path(__file__).resolve().parents[1] / "sample_logs" / "drive_loops.ros2.mcap"


def filled(store: FrameStore, count: int, seed: int = 0) -> FrameStore:
    rng = np.random.default_rng(seed)
    for _ in range(count):
        store.append(rng.standard_normal(store.dimension).astype(np.float32))
    return store


@pytest.mark.parametrize("precision", ["uint8", "float32"])
def test_a_spilled_store_reads_back_what_it_stored(precision) -> None:
    memory = filled(FrameStore(16, precision, block_frames=8), 100)
    spill = DictSpill()
    spilled = filled(FrameStore(16, precision, block_frames=8, spill=spill), 100)
    assert spill.chunks  # blocks were spilled ...
    np.testing.assert_array_equal(spilled.rows(0, 99), memory.rows(0, 99))
    for first, stop in ((0, 1), (3, 21), (7, 9), (40, 100), (95, 100)):  # across blocks
        got = np.concatenate(spilled.span(first, stop))
        np.testing.assert_array_equal(got, np.concatenate(memory.span(first, stop)))
    assert spill.reads  # ... and read back
    queries = memory.rows(90, 97)
    np.testing.assert_array_equal(sad_rows(queries, spilled, 80), sad_rows(queries, memory, 80))
    np.testing.assert_array_equal(
        sad_columns(queries, spilled, 13, 61), sad_columns(queries, memory, 13, 61)
    )


def test_a_spilled_store_keeps_only_its_newest_blocks_in_memory() -> None:
    store = FrameStore(32, "uint8", block_frames=10, spill=DictSpill(), resident_blocks=2)
    for count in range(1, 500):
        filled(store, 1, seed=count)
        assert store.nbytes <= 3 * 10 * 32  # two full blocks and the one being filled
        assert store.nbytes + store.spilled_bytes == -(-count // 10) * 10 * 32


def test_a_file_spill_round_trips_and_refuses_missing_bytes() -> None:
    with FileSpill() as spill:
        data = np.arange(3000, dtype=np.uint16).view(np.uint8)
        spill.write(4096, data.data.cast("B"))
        out = np.zeros(1000, np.uint8)
        spill.read_into(4096 + 500, out.data.cast("B"))
        np.testing.assert_array_equal(out, data[500:1500])
        with pytest.raises(OSError, match="missing"):
            spill.read_into(4096 + 5999, out.data.cast("B"))


def test_a_file_spill_that_cannot_be_created_is_an_output_error(tmp_path) -> None:
    with pytest.raises(OutputError, match="temporary file"):
        FileSpill(tmp_path / "no such folder")


def test_seqslam_decides_the_same_with_a_spilled_store() -> None:
    """DOSeqSLAM's own check is in test_place_search (repeated laps, both searches)."""
    params = Parameters(method="seqslam", kappa_s=5)
    rng = np.random.default_rng(4)
    places = rng.integers(0, 256, (40, 48, 64), dtype=np.uint8)
    frames = [places[t % 40] + rng.integers(0, 8, (48, 64), dtype=np.uint8) for t in range(200)]
    decisions = []
    spill = DictSpill()
    for store in (None, FrameStore(2048, "uint8", block_frames=16, spill=spill)):
        detector = make_detector(params, store)
        made = []
        for t, gray in enumerate(frames):
            made += detector.push(t * 100_000_000, gray)
        decisions.append(made + detector.finish())
    assert any(d.candidates for d in decisions[0]) and spill.reads
    assert decisions[0] == decisions[1]


def test_the_pipeline_store_fits_the_parameters_and_a_wrong_one_is_refused() -> None:
    params = Parameters()
    with spilled_frame_store(params) as store:
        assert store.dimension == params.image_width * params.image_height
        make_detector(params, store)
    with pytest.raises(ValueError, match="frame store"):
        make_detector(params, FrameStore(16, "uint8"))


def test_annotate_frees_its_detector_before_the_later_stages(tmp_path) -> None:
    """The detector's place index and frame vectors grow with the log: nothing may hold them
    once the replay is over."""

    class Watch(StageObserver):
        def __init__(self) -> None:
            self.made: list[weakref.ref[object]] = []
            self.alive_at: dict[str, bool] = {}

        def detector_made(self, detector: object) -> None:
            self.made.append(weakref.ref(detector))

        def started(self, stage: str) -> None:
            gc.collect()
            self.alive_at[stage] = any(ref() is not None for ref in self.made)

    watch = Watch()
    options = AnnotateOptions(verification=None, visualization=False)
    annotate_log(SAMPLE, tmp_path / "out.mcap", Parameters(), options, observer=watch)
    assert len(watch.made) == 1
    assert watch.alive_at == {"replay": True, "write": False}


# -- the output messages' spool ----------------------------------------------------------------


def spooled_and_listed(start_ns: int = 1_000_000_000) -> tuple[Annotations, Annotations]:
    """The same decisions' messages, spooled and as a list (test_sinks' helpers: both kinds)."""
    made = [
        Annotations.from_decisions(
            make_decisions(), make_frame_times(start_ns), "doseqslam", "h", {"run": "x"}, spool=s
        )
        for s in (True, False)
    ]
    return made[0], made[1]


def test_spooled_messages_read_back_equal_in_the_given_and_the_sorted_order() -> None:
    spooled, listed = spooled_and_listed()
    messages = spooled.messages
    assert isinstance(messages, SpooledMessages) and isinstance(listed.messages, list)
    assert len(messages) == len(listed.messages) > 5
    same = repr  # NaN fields: equal values whose objects differ compare unequal with ==
    assert same(list(messages)) == same(listed.messages)
    assert same(messages[-1]) == same(listed.messages[-1])
    assert same(messages[1:3]) == same(listed.messages[1:3])
    shuffled = SpooledMessages(listed.messages[::-1] + listed.messages[:2])  # ties, in order
    by_key = sorted(listed.messages[::-1] + listed.messages[:2], key=lambda m: m.sort_key)
    assert same(list(shuffled.in_order())) == same(by_key) == same(list(in_order(by_key)))
    spooled.close()
    shuffled.close()
    with pytest.raises(ValueError):  # closed: its file is gone
        messages[0]


def test_spooled_and_listed_messages_write_the_same_bytes(tmp_path) -> None:
    log = tmp_path / "in.mcap"
    spooled, listed = spooled_and_listed(write_json_mcap(log, "ros2"))
    for name, made in (("spooled", spooled), ("listed", listed)):
        write_annotated_mcap(log, tmp_path / f"{name}.mcap", made)
    spooled.close()
    assert (tmp_path / "spooled.mcap").read_bytes() == (tmp_path / "listed.mcap").read_bytes()


def test_a_message_that_cannot_be_made_leaves_no_spool_open(monkeypatch) -> None:
    opened = []
    real = tempfile.TemporaryFile

    def tracked(*args: Any, **kwargs: Any) -> Any:
        opened.append(real(*args, **kwargs))
        return opened[-1]

    monkeypatch.setattr(tempfile, "TemporaryFile", tracked)
    with pytest.raises(ValueError, match="not 'doseqslam'"):
        Annotations.from_decisions(
            make_decisions("seqslam"), make_frame_times(0), "doseqslam", "h", {}, spool=True
        )
    assert opened and all(file.closed for file in opened)


def test_read_records_share_their_repeated_values(tmp_path) -> None:
    """An 8-hour log reads 290,000 LoopClosure records: each holds its own numbers only (the
    all-NaN poses and the repeated strings shared, no per-record dict): 1.6 kB a record held
    on a 5-minute drive's 2,473, against 5.0 kB before."""
    import tracemalloc

    from doseqslam_logs.annotations.reader import read_annotations

    out = tmp_path / "drive_loops.annotated.mcap"
    annotate_log(SAMPLE, out, Parameters(), AnnotateOptions())
    tracemalloc.start()
    try:
        records = read_annotations(out).loop_closures
        held, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    unposed = [r for r in records if math.isnan(r.metric_covariance[0])]
    assert len(unposed) >= 10
    assert all(r.metric_covariance is unposed[0].metric_covariance for r in unposed)
    assert all(r.parameters_hash is records[0].parameters_hash for r in records)
    assert not hasattr(records[0], "__dict__")
    assert held / len(records) < 4_200  # 5,600 bytes before (3,300 now; 1,600 on 2,473)
