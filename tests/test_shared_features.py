"""One feature extraction a frame (issue #35 item 5, issue #37 item 1): with the verified
defaults, the detector's segmentation and place index take, of the verification's ORB
features, those ORB would keep for their budget, instead of extracting their own;
`--vset shared_features=false` gives the two extractions back."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from doseqslam_logs.detector import DOSeqSLAM, Parameters
from doseqslam_logs.detector import segmentation as segmentation_module
from doseqslam_logs.detector.segmentation import ORB_LEVELS, OrbFeatures, orb_level_quota
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.verification import DEFAULT_VERIFICATION
from doseqslam_logs.verification.params import (
    shares_features,
    verified_detector_parameters,
)

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_logs" / "drive_loops.ros2.mcap"


@pytest.fixture(scope="module")
def orb_frames() -> list[np.ndarray]:
    """Six frames of the sample drive, as the segmentation's ORB sees them (320 px)."""
    from itertools import islice

    from doseqslam_logs.detector.segmentation import feature_image
    from doseqslam_logs.pipeline.decode import FrameCounts, decoded_frames
    from doseqslam_logs.sources import open_source, pick_image_topic

    with open_source(SAMPLE) as source:
        messages = source.image_messages(pick_image_topic(source, None), None, None)
        frames = islice(decoded_frames(messages, FrameCounts()), 0, 240, 40)
        return [feature_image(frame.image, 320, 320) for frame in frames]


def _descriptors(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n, 32), dtype=np.uint8)


@given(st.integers(1, 5000))
def test_the_level_quota_spends_the_whole_budget_strongest_level_first(n: int) -> None:
    quota = orb_level_quota(n)
    # ORB's rounding can overspend a tiny budget (7 gives 8 features, as OpenCV's ORB does).
    assert len(quota) == ORB_LEVELS and sum(quota) == max(n, sum(quota[:-1]))
    assert sum(quota) <= n + ORB_LEVELS
    assert all(q >= 0 for q in quota)
    assert list(quota[:-1]) == sorted(quota[:-1], reverse=True)  # each level smaller than the last


def test_the_level_quota_is_orbs(orb_frames: list[np.ndarray]) -> None:
    # On each pyramid level ORB keeps its quota, or every corner the level has when fewer.
    large = cv2.ORB_create(nfeatures=5000)
    for budget in (7, 60):
        small = cv2.ORB_create(nfeatures=budget)
        for gray in orb_frames:
            kept = np.bincount([k.octave for k in small.detect(gray, None)], minlength=ORB_LEVELS)
            found = np.bincount([k.octave for k in large.detect(gray, None)], minlength=ORB_LEVELS)
            assert kept.tolist() == np.minimum(orb_level_quota(budget), found).tolist()


def test_the_features_orb_keeps_for_half_the_budget_are_mostly_each_levels_strongest(
    orb_frames: list[np.ndarray],
) -> None:
    # Not all of them: ORB first keeps twice a level's quota by FAST score, then ranks those by
    # Harris response, so a larger budget ranks more corners (six frames: 1,843 of 1,859).
    small, large = cv2.ORB_create(nfeatures=500), cv2.ORB_create(nfeatures=1000)
    same = total = 0
    for gray in orb_frames:
        kept, descriptors = large.detectAndCompute(gray, None)
        order = np.argsort([-k.response for k in kept], kind="stable")
        levels = np.array([kept[i].octave for i in order], np.uint8)
        supplied = OrbFeatures(descriptors[order], levels).as_if_asked_for(500)
        _, own = small.detectAndCompute(gray, None)
        assert len(supplied) == len(own)
        same += len({bytes(row) for row in supplied} & {bytes(row) for row in own})
        total += len(own)
    assert same >= 0.97 * total


def test_the_detector_takes_what_orb_would_keep_from_supplied_features() -> None:
    params = verified_detector_parameters()
    detector = DOSeqSLAM(params)
    gray = np.zeros((240, 320), np.uint8)  # no corner: its own ORB would find nothing
    levels = np.repeat(np.arange(ORB_LEVELS, dtype=np.uint8), 125)  # 1000, 125 a level
    supplied = OrbFeatures(_descriptors(1000), levels)
    prepared = detector.prepare(gray, supplied)
    expected = supplied.as_if_asked_for(params.max_features)
    assert prepared.feature_count == params.max_features == len(expected)
    assert np.array_equal(prepared.segmentation.descriptors, expected)
    assert prepared.place_descriptors is not None
    assert np.array_equal(prepared.place_descriptors, expected)
    # Without them it extracts its own (none on a flat frame).
    assert detector.prepare(gray).feature_count == 0
    # An empty set is a frame without features, not an error.
    empty = OrbFeatures(_descriptors(0), np.empty(0, np.uint8))
    assert detector.prepare(gray, empty).feature_count == 0


def test_a_segmentation_that_is_not_orb_ignores_them() -> None:
    detector = DOSeqSLAM(Parameters(feature_detector="klt"))
    gray = np.zeros((240, 320), np.uint8)
    supplied = OrbFeatures(_descriptors(50), np.zeros(50, np.uint8))
    assert detector.prepare(gray, supplied).feature_count == -1


@pytest.mark.parametrize(
    ("detector_change", "verification_change", "shared"),
    [
        ({}, {}, True),  # the default
        ({}, {"shared_features": False}, False),
        ({"feature_image_max_side": 240}, {"shared_features": True}, False),  # another image
        ({"feature_image_enlarge": False}, {"shared_features": True}, False),  # not enlarged
        ({"feature_detector": "sift"}, {"shared_features": True}, False),
        ({}, {"feature_detector": "sift", "shared_features": True}, False),
        ({}, {"max_features": 400}, False),  # fewer than the segmentation's 500
        ({"max_features": 1000}, {}, True),
    ],
)
def test_features_are_shared_only_where_both_extract_the_same(
    detector_change: dict[str, Any], verification_change: dict[str, Any], shared: bool
) -> None:
    detector = verified_detector_parameters(**detector_change)
    verification = DEFAULT_VERIFICATION.replace(**verification_change)
    assert shares_features(detector, verification) is shared


@pytest.mark.slow
@pytest.mark.parametrize("shared", [True, False])
def test_annotate_extracts_the_segmentations_orb_only_when_not_shared(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, shared: bool
) -> None:
    calls = []
    own = segmentation_module.DescriptorSegmenter.prepare

    def counted(self: Any, gray: Any) -> Any:
        calls.append(1)
        return own(self, gray)

    monkeypatch.setattr(segmentation_module.DescriptorSegmenter, "prepare", counted)
    verification = DEFAULT_VERIFICATION.replace(shared_features=shared)
    # The replay is what counts (the verification and write stages are not): 100 frames do.
    end_ns = _log_time_of_frame(100)
    options = AnnotateOptions(verification=verification, end_ns=end_ns, sidecar=True)
    result = annotate_log(SAMPLE, tmp_path / "out.mcap", options=options)
    assert result.replay.frames == 100
    assert len(calls) == (0 if shared else 100)


def _log_time_of_frame(index: int) -> int:
    from doseqslam_logs.sources import open_source, pick_image_topic

    with open_source(SAMPLE) as source:
        messages = source.image_messages(pick_image_topic(source, None), None, None)
        return next(m.log_time_ns for i, m in enumerate(messages) if i == index)
