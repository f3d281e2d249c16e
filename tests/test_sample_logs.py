"""The committed sample logs: made by our generator, found by the detector, bounded when parked."""

from __future__ import annotations

import filecmp
import json
import sys
from pathlib import Path

import pytest

from doseqslam_logs.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.detector import Parameters, make_detector
from doseqslam_logs.evaluation.groundtruth import load_ground_truth
from doseqslam_logs.evaluation.metrics import evaluate
from doseqslam_logs.log_frames import FrameCounts, decoded_frames
from doseqslam_logs.replay import replay
from doseqslam_logs.sources import open_source, pick_image_topic

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "sample_logs"
sys.path.insert(0, str(REPO / "tools"))

import make_sample_logs as generator  # noqa: E402

# (log, ground truth, minimum recall at the default threshold, as docs/results.md documents)
CASES = [
    ("drive_loops.ros2.mcap", "drive_loops", 0.35),
    ("drive_loops.foxglove.mcap", "drive_loops", 0.35),
    ("drive_loops.bag", "drive_loops", 0.35),
    ("drive_loops.rosbag2", "drive_loops", 0.35),
    ("drive_varrate.bag", "drive_varrate", 0.03),
    ("drive_parked.ros2.mcap", "drive_parked", 0.0),
]


def run_detector(log: Path, params: Parameters):
    with open_source(log) as source:
        messages = source.image_messages(pick_image_topic(source))
        detector = make_detector(params)
        result = replay(decoded_frames(messages, FrameCounts()), detector)
    return result, detector


@pytest.mark.parametrize(("log", "stem", "min_recall"), CASES)
def test_default_detector_finds_the_sample_loops_with_full_precision(log, stem, min_recall):
    params = Parameters()
    result, _ = run_detector(SAMPLES / log, params)
    gt = load_ground_truth(SAMPLES / f"{stem}.gt.npz")
    assert result.frames == gt.n_frames
    ev = evaluate(result.decisions, gt, params.threshold)
    assert ev.fp == 0 and ev.precision == 1.0
    assert ev.recall >= min_recall
    assert ev.r_p100 >= ev.recall > 0 or min_recall == 0.0


def test_the_same_drive_gives_the_same_decisions_in_every_container() -> None:
    decisions = {
        log: run_detector(SAMPLES / log, Parameters())[0].decisions
        for log, stem, _ in CASES
        if stem == "drive_loops"
    }
    first = next(iter(decisions.values()))
    assert all(d == first for d in decisions.values())


def test_a_parked_camera_keeps_sequences_and_memory_bounded() -> None:
    facts = json.loads((SAMPLES / "drive_parked.json").read_text())
    first, last = facts["parked"]["frames"]
    assert last - first + 1 >= 100  # a minute at 2 Hz
    for cap, min_pieces in ((40, 3), (300, 1)):
        result, detector = run_detector(
            SAMPLES / "drive_parked.ros2.mcap", Parameters(max_sequence_length=cap)
        )
        assert max(d.length for d in result.decisions) <= cap
        assert len(detector._sequences) <= 3  # only the undecided tail is held
        assert detector.memory_bytes <= 4096 * 2048 + 8 * result.frames  # one vector block
        parked = [d for d in result.decisions if d.first_index <= last and d.last_index >= first]
        assert len(parked) >= min_pieces  # the small cap cuts the parked minute


def test_committed_samples_regenerate_byte_for_byte(tmp_path) -> None:
    generator.make_samples(tmp_path, jobs=1)
    committed = sorted(p.relative_to(SAMPLES) for p in SAMPLES.rglob("*") if p.is_file())
    made = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file())
    assert made == committed
    _, mismatch, errors = filecmp.cmpfiles(SAMPLES, tmp_path, [str(p) for p in made], shallow=False)
    assert mismatch == [] and errors == []


def test_samples_stay_small() -> None:
    total = sum(p.stat().st_size for p in SAMPLES.rglob("*") if p.is_file())
    assert total <= 8 * 1024 * 1024


def test_annotating_a_sample_writes_loop_closures(tmp_path) -> None:
    result = annotate_log(
        SAMPLES / "drive_loops.ros2.mcap", tmp_path / "out.mcap", Parameters(), AnnotateOptions()
    )
    assert result.replay.loop_closures >= 40 and result.written.copied_messages == 960
