"""verification/hamming.py: the two nearest binary descriptors, the same from faiss and OpenCV."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from doseqslam_logs.verification import hamming


@settings(max_examples=200, deadline=None)
@given(
    st.integers(1, 60),
    st.integers(2, 60),
    st.sampled_from([32, 61, 64]),  # ORB, AKAZE (OpenCV's path), BRISK
    st.integers(1, 6),  # palette size: few distinct descriptors make many distance ties
    st.integers(0, 2**32 - 1),
)
def test_the_same_distances_and_every_unique_nearest_as_opencv(
    n_query, n_database, width, palette, seed
) -> None:
    rng = np.random.default_rng(seed)
    colours = rng.integers(0, 256, (palette, width), dtype=np.uint8)
    noise = rng.integers(0, 2, (n_query, width)).astype(np.uint8)
    queries = colours[rng.integers(0, palette, n_query)] ^ noise
    database = colours[rng.integers(0, palette, n_database)]
    distances, indices = hamming.two_nearest(queries, database)
    expected_distances, expected_indices = hamming.opencv_two_nearest(queries, database)
    np.testing.assert_array_equal(distances, expected_distances)
    unique = distances[:, 0] < distances[:, 1]  # what a ratio test below 1 can keep
    np.testing.assert_array_equal(indices[unique, 0], expected_indices[unique, 0])
    assert distances.dtype == np.int32 and indices.dtype == np.int64


def test_orb_descriptors_are_matched_by_faiss_not_opencv(monkeypatch) -> None:
    """The faster path is the one taken for ORB (a table popcount in OpenCV's portable build:
    3.6x slower on the hour's frames, docs/performance.md)."""
    assert hamming._faiss is not None

    def refuse(queries, database):
        raise AssertionError("OpenCV matched ORB descriptors")

    monkeypatch.setattr(hamming, "opencv_two_nearest", refuse)
    rng = np.random.default_rng(3)
    database = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    distances, indices = hamming.two_nearest(database[::-1].copy(), database)
    np.testing.assert_array_equal(distances[:, 0], 0)
    np.testing.assert_array_equal(indices[:, 0], np.arange(49, -1, -1))
    akaze = rng.integers(0, 256, (50, 61), dtype=np.uint8)  # not whole 64-bit words
    with pytest.raises(AssertionError, match="OpenCV"):
        hamming.two_nearest(akaze, akaze)
