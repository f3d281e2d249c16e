"""One feature extraction a frame (issue #35 item 5, issue #37 item 1): with
`--vset shared_features=true` and the verified detector defaults, the detector's segmentation
and place index take the verification's ORB features instead of extracting their own (off by
default: docs/research/2026-12-06-shared-features.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from doseqslam_logs.detector import DOSeqSLAM, Parameters
from doseqslam_logs.detector import segmentation as segmentation_module
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.verification import DEFAULT_VERIFICATION
from doseqslam_logs.verification.params import (
    shares_features,
    verified_detector_parameters,
)

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_logs" / "drive_loops.ros2.mcap"


def _descriptors(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n, 32), dtype=np.uint8)


def test_the_detector_takes_the_strongest_supplied_descriptors() -> None:
    params = verified_detector_parameters()
    detector = DOSeqSLAM(params)
    gray = np.zeros((240, 320), np.uint8)  # no corner: its own ORB would find nothing
    supplied = _descriptors(1000)
    prepared = detector.prepare(gray, supplied)
    assert prepared.feature_count == params.max_features
    assert np.array_equal(prepared.segmentation.descriptors, supplied[: params.max_features])
    assert prepared.place_descriptors is not None
    assert np.array_equal(prepared.place_descriptors, supplied[: params.max_features])
    # Without them it extracts its own (none on a flat frame).
    assert detector.prepare(gray).feature_count == 0
    # An empty set is a frame without features, not an error.
    assert detector.prepare(gray, _descriptors(0)).feature_count == 0


def test_a_segmentation_that_is_not_orb_ignores_them() -> None:
    detector = DOSeqSLAM(Parameters(feature_detector="klt"))
    gray = np.zeros((240, 320), np.uint8)
    assert detector.prepare(gray, _descriptors(50)).feature_count == -1


@pytest.mark.parametrize(
    ("detector_change", "verification_change", "shared"),
    [
        ({}, {}, False),  # the default
        ({}, {"shared_features": True}, True),
        ({"feature_image_max_side": 240}, {"shared_features": True}, False),  # another image
        ({"feature_image_enlarge": False}, {"shared_features": True}, False),  # not enlarged
        ({"feature_detector": "sift"}, {"shared_features": True}, False),
        ({}, {"feature_detector": "sift", "shared_features": True}, False),
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
    result = annotate_log(
        SAMPLE, tmp_path / "out.mcap", options=AnnotateOptions(verification=verification)
    )
    assert result.replay.frames == 240
    assert len(calls) == (0 if shared else 240)
