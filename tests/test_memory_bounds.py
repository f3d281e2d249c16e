"""Memory that must not grow with the log: the frame store's spill (detector/difference.py,
pipeline/frame_spill.py)."""

from __future__ import annotations

import gc
import weakref
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from detector_helpers import DictSpill

from doseqslam_logs.detector import Parameters, make_detector
from doseqslam_logs.detector.difference import FrameStore, sad_columns, sad_rows
from doseqslam_logs.errors import OutputError
from doseqslam_logs.pipeline import annotate as annotate_module
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.pipeline.frame_spill import FileSpill, spilled_frame_store

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


def test_annotate_frees_its_detector_before_the_later_stages(tmp_path, monkeypatch) -> None:
    """The detector's place index and frame vectors grow with the log: nothing may hold them
    once the replay is over."""
    made: list[weakref.ref[object]] = []
    real = annotate_module.make_detector

    def tracked(*args: Any) -> Any:
        detector = real(*args)
        made.append(weakref.ref(detector))
        return detector

    alive_at: dict[str, bool] = {}

    def stage(name: str) -> None:
        gc.collect()
        alive_at[name] = any(ref() is not None for ref in made)

    monkeypatch.setattr(annotate_module, "make_detector", tracked)
    options = AnnotateOptions(verification=None, visualization=False)
    annotate_log(SAMPLE, tmp_path / "out.mcap", Parameters(), options, stage=stage)
    assert alive_at == {"replay": True, "write": False}
