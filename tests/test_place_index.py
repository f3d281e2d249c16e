"""The place index (detector/place_index.py): retrieval on a real log, and its invariants."""

from __future__ import annotations

from functools import cache
from itertools import pairwise
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from doseqslam_logs.detector import Parameters
from doseqslam_logs.detector.place_index import (
    DESCRIPTOR_BYTES,
    PlaceIndex,
    PlaceIndexParams,
    hamming,
    memory_bound,
    popcount,
)
from doseqslam_logs.detector.segmentation import DescriptorSegmenter
from doseqslam_logs.sources import decode_gray, open_source, pick_image_topic

REPO = Path(__file__).resolve().parents[1]
LOG = REPO / "sample_logs" / "drive_loops.ros2.mcap"
GT = REPO / "sample_logs" / "drive_loops.gt.npz"
MIN_AGE = 80  # frames: 40 s at 2 Hz, the detector's kappa
TOLERANCE = 2  # a result within 2 frames of a ground-truth cell is a hit
K = 5

Descriptors = npt.NDArray[np.uint8]
# Hypothesis runs tens of examples per test; an index allocates its tables (16 MB at the
# defaults), so the property tests use fewer tables where the count does not matter.
SMALL = PlaceIndexParams(tables=2, bucket_slots=2)
FAST = settings(max_examples=40, deadline=None)

descriptor_sets = arrays(np.uint8, st.tuples(st.integers(0, 40), st.just(DESCRIPTOR_BYTES)))


def gray_frames(path: Path) -> list[npt.NDArray[np.uint8]]:
    """The log's frames in grey, decoded as the pipeline decodes them."""
    with open_source(path) as source:
        return [decode_gray(m) for m in source.image_messages(pick_image_topic(source))]


@cache
def loop_log() -> tuple[list[Descriptors], npt.NDArray[np.uint8]]:
    """ORB descriptors of drive_loops as the pipeline extracts them, and its ground truth."""
    segmenter = DescriptorSegmenter(Parameters(feature_detector="orb"), "orb")
    descriptors = []
    for gray in gray_frames(LOG):
        found = segmenter.prepare(gray).descriptors
        descriptors.append(np.zeros((0, 32), np.uint8) if found is None else found)
    return descriptors, np.load(GT)["gt"]


@cache
def online_results() -> list[list[tuple[int, float]]]:
    """Each frame queried against the frames at least MIN_AGE older, then added."""
    descriptors, _ = loop_log()
    index = PlaceIndex()
    results = []
    for i, desc in enumerate(descriptors):
        results.append(index.query(desc, i - MIN_AGE + 1, K) if i >= MIN_AGE else [])
        index.add(i, desc)
    return results


def is_hit(gt_row: npt.NDArray[np.uint8], frame: int) -> bool:
    return bool(gt_row[max(0, frame - TOLERANCE) : frame + TOLERANCE + 1].any())


# -- retrieval on a real log --------------------------------------------------------------------


def test_most_revisits_of_a_real_log_are_found_in_the_top_five() -> None:
    descriptors, gt = loop_log()
    assert len(descriptors) == 240
    results = online_results()
    loops = [i for i in range(MIN_AGE, len(gt)) if gt[i, : i - MIN_AGE + 1].any()]
    assert len(loops) > 100
    top_k = np.mean([any(is_hit(gt[i], j) for j, _ in results[i]) for i in loops])
    top_1 = np.mean([bool(results[i]) and is_hit(gt[i], results[i][0][0]) for i in loops])
    # Measured on x86-64: 0.992 (122 of 123) in the top 5, 0.959 first. The thresholds leave
    # room for another processor's JPEG decoding and ORB moving a few descriptors.
    assert top_k >= 0.85, top_k
    assert top_1 >= 0.75, top_1


def test_a_query_with_no_revisit_scores_far_below_a_revisit() -> None:
    _, gt = loop_log()
    results = online_results()
    top = [results[i][0][1] if results[i] else 0.0 for i in range(len(gt))]
    loops = [top[i] for i in range(MIN_AGE, len(gt)) if gt[i].any()]
    others = [top[i] for i in range(MIN_AGE, len(gt)) if not gt[i].any()]
    assert len(others) > 20  # the first lap's second half: a database, no revisit
    # Measured: the best non-revisit scores 0.004, the median revisit 0.17 and every revisit
    # more than 0.027. The margins are several times wider.
    assert max(others) < np.median(loops) / 4
    assert np.mean([s > max(others) for s in loops]) >= 0.8


def test_results_are_older_than_before_best_first_and_reproducible() -> None:
    descriptors, _ = loop_log()
    again = PlaceIndex()
    for i, desc in enumerate(descriptors[:200]):
        again.add(i, desc)
    for i, result in enumerate(online_results()[MIN_AGE:200], start=MIN_AGE):
        assert all(j <= i - MIN_AGE for j, _ in result)
        assert [s for _, s in result] == sorted((s for _, s in result), reverse=True)
    # The same frames give the same answer, bit for bit, from another index.
    query = descriptors[230]
    first = again.query(query, 150, K)
    assert first == again.query(query, 150, K)
    rebuilt = PlaceIndex()
    for i, desc in enumerate(descriptors[:200]):
        rebuilt.add(i, desc)
    assert rebuilt.query(query, 150, K) == first


# -- the arithmetic -----------------------------------------------------------------------------


@given(st.lists(st.integers(0, 2**64 - 1), max_size=50))
def test_popcount_counts_set_bits(values: list[int]) -> None:
    counts = popcount(np.array(values, dtype=np.uint64))
    assert counts.tolist() == [bin(v).count("1") for v in values]


@given(st.lists(st.binary(min_size=64, max_size=64), max_size=20))
def test_hamming_matches_a_naive_bit_count(pairs: list[bytes]) -> None:
    a = np.array([list(p[:32]) for p in pairs], dtype=np.uint8).reshape(-1, 32)
    b = np.array([list(p[32:]) for p in pairs], dtype=np.uint8).reshape(-1, 32)
    naive = [sum(bin(x ^ y).count("1") for x, y in zip(p[:32], p[32:], strict=True)) for p in pairs]
    assert hamming(a, b).tolist() == naive


# -- properties of the index --------------------------------------------------------------------


def random_frames(seed: int, count: int, size: int = 60) -> list[Descriptors]:
    """Frames that revisit a few places: each descriptor a noisy copy of a place's."""
    rng = np.random.default_rng(seed)
    places = rng.integers(0, 256, (4, size, DESCRIPTOR_BYTES), dtype=np.uint8)
    frames = []
    for _ in range(count):
        noise = rng.random((size, DESCRIPTOR_BYTES * 8)) < 0.04
        frames.append(places[rng.integers(0, 4)] ^ np.packbits(noise, axis=1))
    return frames


@FAST
@given(st.integers(0, 2**32 - 1), st.integers(1, 30), st.integers(0, 35), st.integers(1, 8))
def test_query_respects_before_and_k_and_orders_results(
    seed: int, count: int, before: int, k: int
) -> None:
    index = PlaceIndex(SMALL)
    frames = random_frames(seed, count + 1)
    for i, frame in enumerate(frames[:-1]):
        index.add(2 * i, frame)  # frame indices need only increase
    result = index.query(frames[-1], before, k)
    assert len(result) <= k
    assert all(j < before and j % 2 == 0 for j, _ in result)
    assert all(0.0 <= s <= 1.0 + 1e-9 for _, s in result)
    # Best first; equal scores, the older frame first.
    assert result == sorted(result, key=lambda r: (-r[1], r[0]))


@FAST
@given(st.integers(0, 2**32 - 1), st.integers(1, 25))
def test_same_frames_give_the_same_index(seed: int, count: int) -> None:
    frames = random_frames(seed, count + 1)
    twins = [PlaceIndex(SMALL), PlaceIndex(SMALL)]
    for index in twins:
        for i, frame in enumerate(frames[:-1]):
            index.add(i, frame)
    a, b = (index.query(frames[-1], count, 5) for index in twins)
    assert a == b
    assert twins[0].memory_bytes == twins[1].memory_bytes
    assert twins[0].word_count == twins[1].word_count
    assert a == twins[0].query(frames[-1], count, 5)  # querying changes nothing


@FAST
@given(descriptor_sets, st.data())
def test_a_word_within_15_bits_is_always_found(words: Descriptors, data: st.DataObject) -> None:
    """Multi-index hashing's guarantee: 16 substrings, so a word within 15 bits agrees with
    the query exactly on one of them."""
    index = PlaceIndex(PlaceIndexParams(bucket_slots=64, min_frames=1))
    index.add(0, words)
    if len(words) == 0:
        return
    target = data.draw(st.integers(0, len(words) - 1))
    flips = data.draw(st.lists(st.integers(0, 255), max_size=15, unique=True))
    query = words[target : target + 1].copy()
    for bit in flips:
        query[0, bit // 8] ^= 1 << (bit % 8)
    (found,) = index.words_of(query)
    # An empty index makes descriptor i word i. The word found is the target or a nearer one.
    assert found >= 0
    assert hamming(query[0], words[found]) <= len(flips)


@FAST
@given(descriptor_sets, descriptor_sets)
def test_the_nearest_word_is_the_nearest_sharing_a_substring(
    words: Descriptors, queries: Descriptors
) -> None:
    """Against a brute force over the words that share a 16-bit substring with the query
    (with buckets large enough to hold every word of this small vocabulary)."""
    params = PlaceIndexParams(bucket_slots=64, min_frames=1, radius=100)
    index = PlaceIndex(params)
    index.add(0, words)  # an empty index: each descriptor becomes a word, ids 0, 1, ...
    keys_w, keys_q = words.view("<u2"), queries.view("<u2")
    for query, keys, found in zip(queries, keys_q, index.words_of(queries), strict=True):
        shares = (keys_w == keys).any(axis=1)
        distance = hamming(query, words)
        near = np.flatnonzero(shares & (distance <= params.radius))
        # Ties: the smallest id, the first of equal descriptors.
        expected = near[np.lexsort((near, distance[near]))][0] if len(near) else -1
        assert found == expected


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_memory_stays_within_its_bound_and_the_vocabulary_within_its_cap(seed: int) -> None:
    """One table with one slot per bucket caps the vocabulary at 65,536 words (plus one
    frame's new words); 400 frames of 400 random descriptors try to make 160,000."""
    params = PlaceIndexParams(tables=1, bucket_slots=1, min_frames=1, max_descriptors=400)
    index = PlaceIndex(params)
    rng = np.random.default_rng(seed)
    for i in range(400):
        index.add(i, rng.integers(0, 256, (400, DESCRIPTOR_BYTES), dtype=np.uint8))
        assert index.word_count <= params.max_words
        assert index.memory_bytes <= memory_bound(params, index.frame_count)
    # Random keys leave about e^-2.4 of the buckets empty: the cap is reached, not avoided.
    assert index.word_count > 0.85 * 65_536


def test_words_seen_on_one_frame_only_are_purged() -> None:
    rng = np.random.default_rng(3)
    params = PlaceIndexParams(purge_age=3, min_frames=2)
    index = PlaceIndex(params)
    stable = rng.integers(0, 256, (20, DESCRIPTOR_BYTES), dtype=np.uint8)
    for i in range(10):
        once = rng.integers(0, 256, (30, DESCRIPTOR_BYTES), dtype=np.uint8)
        index.add(i, np.concatenate([stable, once]))
    # The stable words and the last purge_age frames' one-off words remain.
    assert index.word_count == 20 + 3 * 30
    assert (index.words_of(stable) >= 0).all()


def test_a_query_reads_only_the_newest_postings_of_each_word() -> None:
    """The posting cap bounds a query's work: a place seen on 50 frames is found on its 8
    newest only; postings of frames too recent for `before` count against the cap."""
    rng = np.random.default_rng(5)
    place = rng.integers(0, 256, (50, DESCRIPTOR_BYTES), dtype=np.uint8)
    index = PlaceIndex(PlaceIndexParams(posting_cap=8))
    for i in range(10):  # elsewhere first: a word on every frame would have no weight (idf 0)
        index.add(i, rng.integers(0, 256, (50, DESCRIPTOR_BYTES), dtype=np.uint8))
    for i in range(10, 60):
        index.add(i, place)
    assert sorted(j for j, _ in index.query(place, 60, 20)) == list(range(52, 60))
    assert sorted(j for j, _ in index.query(place, 55, 20)) == [52, 53, 54]


def test_islands_merge_neighbouring_frames() -> None:
    descriptors, gt = loop_log()
    index = PlaceIndex(PlaceIndexParams(island_gap=2))
    for i, desc in enumerate(descriptors[:150]):
        index.add(i, desc)
    result = index.query(descriptors[200], 120, 5)
    frames = sorted(j for j, _ in result)
    assert all(b - a > 2 for a, b in pairwise(frames))
    assert is_hit(gt[200], result[0][0])


@pytest.mark.parametrize(
    "descriptors",
    [np.zeros((3, 31), np.uint8), np.zeros((3, 32), np.float32), np.zeros(32, np.uint8)],
)
def test_descriptors_must_be_n_by_32_bytes(descriptors: npt.NDArray[np.generic]) -> None:
    with pytest.raises(ValueError, match="descriptors must be"):
        PlaceIndex(SMALL).add(0, descriptors)  # type: ignore[arg-type]


def test_frame_indices_must_increase() -> None:
    index = PlaceIndex(SMALL)
    index.add(5, np.zeros((1, 32), np.uint8))
    with pytest.raises(ValueError, match="must increase"):
        index.add(5, np.zeros((1, 32), np.uint8))


def test_parameters_are_checked() -> None:
    for bad in ({"tables": 0}, {"tables": 17}, {"radius": -1}, {"posting_cap": 0}):
        with pytest.raises(ValueError):
            PlaceIndexParams(**bad)


# -- postings no query can read are dropped -------------------------------------------------------


def test_dropping_unreadable_postings_changes_no_result(monkeypatch) -> None:
    """The same frames into an index that compacts its postings and one that keeps them all:
    every query gives the same frames and the same scores, bit for bit."""
    descriptors, _ = loop_log()
    params = PlaceIndexParams(posting_cap=4, purge_age=4)  # compactions happen early and often
    compacting = PlaceIndex(params)
    keeping = PlaceIndex(params)
    monkeypatch.setattr(keeping._postings, "compact", lambda vocabulary, cap: None)
    for i, desc in enumerate(descriptors):
        for index in (compacting, keeping):
            index.add(i, desc)
        if i % 7 == 0:
            for query in (desc, descriptors[i // 2]):
                for before in (i + 1, i // 2, i - 30):
                    assert compacting.query(query, before, 10) == keeping.query(query, before, 10)
    assert compacting.posting_count < keeping.posting_count  # compactions happened


def test_postings_held_stay_flat_when_words_come_and_go() -> None:
    """Words seen once are purged, and their postings dropped: after 2,000 frames of fresh
    descriptors the index holds the postings of the last frames only."""
    rng = np.random.default_rng(8)
    index = PlaceIndex(PlaceIndexParams(tables=2, purge_age=4, min_frames=2))
    held = []
    for i in range(2_000):
        index.add(i, rng.integers(0, 256, (100, DESCRIPTOR_BYTES), dtype=np.uint8))
        held.append(index.posting_count)
    assert max(held) <= 2 * 100 * (4 + 2)
    assert max(held[1000:]) <= max(held[:1000])


def test_a_word_seen_on_every_frame_keeps_its_newest_postings_only() -> None:
    rng = np.random.default_rng(9)
    landmark = rng.integers(0, 256, (50, DESCRIPTOR_BYTES), dtype=np.uint8)
    index = PlaceIndex(PlaceIndexParams(posting_cap=8))
    for i in range(1_000):
        index.add(i, landmark)
    assert index.posting_count <= 2 * 50 * 8 + 50
