"""Segmentation: the running common set of features (paper eq. 5)."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
from detector_helpers import noise_frames, rtabmap_frames

from doseqslam_logs.detector import Parameters
from doseqslam_logs.detector.segmentation import (
    DescriptorSegmenter,
    KltSegmenter,
    _Features,
    make_segmenter,
    resolve_detector_name,
)


def features(count: int) -> _Features:
    return _Features(np.zeros((count, 32), np.uint8) if count else None)


def scripted(detected: list[int], lost_per_frame: int) -> list[bool]:
    """Frames detect `detected[i]` features; every frame loses `lost_per_frame` common ones."""
    seg = DescriptorSegmenter(Parameters(min_features=10), "orb")
    frames = iter(detected)
    seg.prepare = lambda gray: features(next(frames))  # type: ignore[method-assign]
    seg._surviving = lambda current: features(  # type: ignore[method-assign]
        max(seg._common.count - lost_per_frame, 0)
    )
    gray = np.zeros((8, 8), np.uint8)
    return [seg.starts_sequence(gray) for _ in detected]


def test_common_set_shrinking_below_min_features_keeps_filtering_until_one_is_left() -> None:
    # 12 common features losing 2 a frame: 10, 8, 6, 4, 2, 0 -> the sequence ends at frame 6.
    starts = scripted([12] + [50] * 9, lost_per_frame=2)
    assert [i for i, s in enumerate(starts) if s] == [0, 6]


def test_featureless_frames_join_the_current_sequence() -> None:
    # Frames 1-2 are dark (3 features): they join; frame 3 keeps 20 common, frame 4 none.
    starts = scripted([40, 3, 3, 40, 40, 3, 40, 40], lost_per_frame=20)
    assert [i for i, s in enumerate(starts) if s] == [0, 4, 7]


def test_a_stream_starting_dark_is_seeded_by_its_first_textured_frame() -> None:
    starts = scripted([3, 3, 40, 40, 40], lost_per_frame=20)
    assert [i for i, s in enumerate(starts) if s] == [0, 4]


def test_unrelated_views_end_a_sequence_within_two_frames(shared_data) -> None:
    """A few chance matches between similar corridor views may survive one frame (|C| > 1),
    never two: no run of two frames without a new sequence."""
    frames = rtabmap_frames(shared_data)
    for name in ("orb", "sift", "klt"):
        seg = make_segmenter(Parameters(feature_detector=name))
        starts = [seg.starts_sequence(frames[i]) for i in range(0, 84, 12)]
        assert starts[0] and all(a or b for a, b in pairwise(starts)), (name, starts)


def test_real_corridor_frames_form_short_sequences(shared_data) -> None:
    """RTAB-Map at 1 Hz: consecutive views share features for a few frames, not forever."""
    for name in ("orb", "klt"):
        seg = make_segmenter(Parameters(feature_detector=name))
        starts = [i for i, f in enumerate(rtabmap_frames(shared_data)) if seg.starts_sequence(f)]
        lengths = np.diff([*starts, 84])
        assert 10 <= len(starts) <= 60 and lengths.max() <= 20, (name, lengths)


def test_klt_tracks_the_same_view_and_ends_on_a_flat_one() -> None:
    seg = KltSegmenter(Parameters(feature_detector="klt"))
    frame = noise_frames(1, seed=2, shape=(120, 160))[0]
    assert seg.starts_sequence(frame) is True
    assert seg.starts_sequence(frame) is False  # the same view: every point tracks
    assert seg.starts_sequence(np.zeros_like(frame)) is True  # nothing left to track


def test_auto_resolves_to_an_available_detector() -> None:
    assert resolve_detector_name("auto") in ("surf", "sift", "orb")
    assert resolve_detector_name("akaze") == "akaze"
