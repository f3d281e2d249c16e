"""The verification's features extracted during the replay and read back from disk
(pipeline/feature_spill.py): the same features, frames decoded once."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from doseqslam_logs.detector import make_detector
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.pipeline.decode import FrameCounts, decoded_frames
from doseqslam_logs.pipeline.feature_spill import FeatureSpill
from doseqslam_logs.pipeline.replay import replay
from doseqslam_logs.pipeline.reread import LogFrameReader
from doseqslam_logs.sources import open_source, pick_image_topic
from doseqslam_logs.verification import (
    DEFAULT_VERIFICATION,
    FrameFeatures,
    extract_features,
    verified_detector_parameters,
)

SAMPLE = Path(__file__).resolve().parents[1] / "sample_logs" / "drive_loops.ros2.mcap"


def assert_same(a: FrameFeatures, b: FrameFeatures) -> None:
    assert a.detector == b.detector and a.scale == b.scale
    assert a.keypoints.dtype == b.keypoints.dtype == np.float32
    assert a.descriptors.dtype == b.descriptors.dtype == np.uint8
    np.testing.assert_array_equal(a.keypoints, b.keypoints)
    np.testing.assert_array_equal(a.descriptors, b.descriptors)


@settings(max_examples=40, deadline=None)
@given(
    counts=st.lists(st.integers(0, 40), min_size=1, max_size=8),
    width=st.sampled_from([32, 61, 64, 128]),
    scale=st.floats(0.01, 8.0),
    seed=st.integers(0, 2**16),
)
def test_features_read_back_bit_for_bit(counts, width, scale, seed) -> None:
    rng = np.random.default_rng(seed)
    kept = [
        FrameFeatures(
            keypoints=rng.uniform(-1, 5000, (n, 2)).astype(np.float32),
            descriptors=rng.integers(0, 256, (n, width), dtype=np.uint8),
            detector="orb",
            scale=scale,
        )
        for n in counts
    ]
    with FeatureSpill(DEFAULT_VERIFICATION) as spill:
        for index, features in enumerate(kept):
            spill.keep(index, features)
        assert spill.frames == len(kept)
        for index in reversed(range(len(kept))):  # any order, any number of times
            got = spill.get(index)
            assert got is not None
            assert_same(got, kept[index])
        assert spill.get(len(kept)) is None and spill.get(-1) is None


def test_frames_must_be_kept_in_order() -> None:
    empty = extract_features(np.zeros((48, 64), np.uint8), DEFAULT_VERIFICATION)
    with FeatureSpill(DEFAULT_VERIFICATION) as spill:
        spill.keep(0, empty)
        with pytest.raises(ValueError, match="frame 2"):
            spill.keep(2, empty)
        got = spill.get(0)
        assert got is not None and got.count == 0 and got.descriptors.shape == (0, 32)


@pytest.mark.parametrize("workers", [1, 2])
def test_the_replay_keeps_each_frames_features_as_verification_extracts_them(workers) -> None:
    """Frame index for frame index, whatever the number of workers (that the re-read frames
    are the replay's decoded frames, test_outputs_unchanged shows: the same bytes out)."""
    params = verified_detector_parameters()
    with open_source(SAMPLE) as source, FeatureSpill(DEFAULT_VERIFICATION) as spill:
        topic = pick_image_topic(source, None)
        frames = decoded_frames(source.image_messages(topic), FrameCounts(), "header", "skip")
        times = []

        def recorded(stream):
            for frame in stream:
                times.append(frame)
                yield frame

        result = replay(recorded(frames), make_detector(params), workers=workers, side=spill)
        assert spill.frames == result.frames == len(times) > 100
        counts = []
        for index in [0, 1, result.frames // 2, result.frames - 1]:
            stored = spill.get(index)
            assert stored is not None
            assert_same(stored, extract_features(times[index].image, DEFAULT_VERIFICATION))
            counts.append(stored.count)
        assert max(counts) > 50


@pytest.mark.slow
def test_annotate_verifies_without_decoding_a_frame_again(tmp_path, monkeypatch) -> None:
    """With the replay's features, verification reads no frame of the log (before: every
    frame it checked was re-read and its features extracted again)."""
    decoded: list[int] = []
    real = LogFrameReader.__call__

    def counting(self, indices):
        decoded.extend(indices)
        return real(self, indices)

    read_by_stage: dict[str, int] = {}

    def stage(name: str) -> None:  # frames read before each stage began
        read_by_stage[name] = len(decoded)

    monkeypatch.setattr(LogFrameReader, "__call__", counting)
    options = AnnotateOptions(verification=DEFAULT_VERIFICATION, visualization=False)
    params = verified_detector_parameters()
    result = annotate_log(SAMPLE, tmp_path / "out.mcap", params, options, stage=stage)
    assert result.verification is not None
    stats = result.verification.stats
    assert stats.pairs > 100 and stats.frames_stored > 50 and stats.frames_loaded == 0
    assert read_by_stage["metric"] == 0  # (the metric stage reads frames for its own features)
