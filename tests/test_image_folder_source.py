"""An image folder is a Source (`ImageFolderSource`): frame i is the i-th image in natural
order at i / fps seconds, read in any time window, and `evaluate --images` runs annotate's own
run over it (`pipeline.annotate.decide_log`)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from doseqslam_logs.detector import make_detector
from doseqslam_logs.errors import SourceError
from doseqslam_logs.pipeline.annotate import AnnotateOptions, OpenLog, decide_log
from doseqslam_logs.pipeline.feature_spill import feature_spill_for
from doseqslam_logs.pipeline.replay import replay
from doseqslam_logs.sources import pick_image_topic
from doseqslam_logs.sources.image_folder import (
    FOLDER_TOPIC,
    ImageFolderSource,
    folder_frames,
    folder_time_ns,
)
from doseqslam_logs.sources.images import decode_gray
from doseqslam_logs.verification import DEFAULT_VERIFICATION, verified_detector_parameters

N_IMAGES = 12


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """12 small PNGs named so that natural order differs from string order (2 before 10)."""
    path = tmp_path_factory.mktemp("images")
    rng = np.random.default_rng(5)
    for i in range(N_IMAGES):
        cv2.imwrite(str(path / f"img{i}.png"), rng.integers(0, 255, (24, 32), dtype=np.uint8))
    (path / "notes.txt").write_text("not an image")
    return path


def test_the_folder_is_one_camera_topic_of_its_images_in_natural_order(folder: Path) -> None:
    with ImageFolderSource(folder, 2.0) as source:
        assert pick_image_topic(source) == FOLDER_TOPIC
        (channel,) = source.channels()
        assert channel.message_count == N_IMAGES and channel.last_log_time_ns == 5_500_000_000
        messages = list(source.image_messages(FOLDER_TOPIC))
        for i, message in enumerate(messages):
            expected = cv2.imread(str(folder / f"img{i}.png"), cv2.IMREAD_GRAYSCALE)
            assert np.array_equal(decode_gray(message), expected)
            assert message.log_time_ns == folder_time_ns(i, 2.0) and message.header_stamp_ns is None
        assert list(source.messages(FOLDER_TOPIC)) == []
        assert list(source.image_messages("/other")) == []


@settings(max_examples=200, deadline=None)
@given(
    fps=st.floats(0.1, 1000.0),
    start=st.one_of(st.none(), st.integers(-(10**9), 10**11)),
    end=st.one_of(st.none(), st.integers(-(10**9), 10**11)),
)
def test_a_time_window_holds_exactly_the_frames_stamped_in_it(
    folder: Path, fps: float, start: int | None, end: int | None
) -> None:
    with ImageFolderSource(folder, fps) as source:
        got = [t for t, _ in source.raw_messages(FOLDER_TOPIC, start, end)]
    wanted = [
        folder_time_ns(i, fps)
        for i in range(N_IMAGES)
        if (start is None or folder_time_ns(i, fps) >= start)
        and (end is None or folder_time_ns(i, fps) < end)
    ]
    assert got == wanted


def test_an_undecodable_image_stops_the_run_with_its_name(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "1.png"), np.zeros((8, 8), np.uint8))
    (tmp_path / "2.png").write_bytes(b"\x89PNG\r\n\x1a\n broken")
    with ImageFolderSource(tmp_path, 1.0) as source, pytest.raises(SourceError, match=r"2\.png"):
        list(source.image_messages(FOLDER_TOPIC))


def test_the_run_over_a_folder_decides_as_the_detector_over_its_frames(
    shared_data: Path,
) -> None:
    images = shared_data / "rtabmap_samples_loop" / "images"
    params = verified_detector_parameters(kappa_s=10.0)
    # As the folder's run did before it was annotate's: the same frames, features shared.
    with feature_spill_for(DEFAULT_VERIFICATION, params) as features:
        direct = replay(folder_frames(images, 1.0), make_detector(params), side=features)
    with ImageFolderSource(images, 1.0) as source:
        options = AnnotateOptions(time_source="log")
        decided = decide_log(OpenLog(source, None, images, None), params, options)
    assert decided.replayed.result.decisions == direct.decisions
    assert decided.replayed.counts.used == 84 and decided.replayed.counts.log_time_fallbacks == 0
    verification = decided.verification
    assert verification is not None and verification.motion_evidence == "images"
    assert verification.stats.accepted >= 35  # RTAB-Map: 40 of 44 revisits at kappa 10 s
