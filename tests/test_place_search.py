"""The indexed place search (issue #17): parameters, windows, repeated laps, bounded work."""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from detector_helpers import DictSpill, sequence_decision

from doseqslam_logs.detector import DOSeqSLAM, Parameters, PreparedFrame
from doseqslam_logs.detector import place_search as place_search_module
from doseqslam_logs.detector.difference import FrameStore, sad_columns, sad_rows
from doseqslam_logs.detector.enhance import enhance
from doseqslam_logs.detector.events import Alternative, SequenceDecision
from doseqslam_logs.detector.params import LATER_FIELDS
from doseqslam_logs.detector.place_search import Exclusion, PlaceSearch, Window
from doseqslam_logs.errors import ParameterError
from doseqslam_logs.verification import DEFAULT_VERIFICATION
from doseqslam_logs.verification.stage import verify_in_threads

LAP = 100  # frames (one a second) per lap of the synthetic route
SEQUENCE = 5  # frames per sequence


class EveryN:
    """Sequence boundaries every SEQUENCE frames."""

    name = "orb"

    def __init__(self) -> None:
        self.count = 0

    def prepare(self, gray: Any) -> None:
        return None

    def update(self, prepared: Any) -> bool:
        self.count += 1
        return (self.count - 1) % SEQUENCE == 0

    def restart(self, prepared: Any) -> None:
        self.count = 1

    def starts_sequence(self, gray: Any) -> bool:
        return self.update(None)


class Route:
    """A closed route of LAP places, one frame a second: each place has its frame vector and
    ORB-like landmarks, each landmark seen from 3 consecutive places (a word must recur within
    a few frames to outlive the index's purge), with bit noise on every lap."""

    def __init__(self) -> None:
        rng = np.random.default_rng(5)
        self.vectors = rng.standard_normal((LAP, 2048)).astype(np.float32)
        self.landmarks = rng.integers(0, 256, (LAP, 80, 32), dtype=np.uint8)

    def frame(self, t: int) -> PreparedFrame:
        rng = np.random.default_rng([9, t])
        place = t % LAP
        vector = self.vectors[place] + 0.4 * rng.standard_normal(2048).astype(np.float32)
        seen = self.landmarks[[(place - k) % LAP for k in range(3)]].reshape(-1, 32)
        flips = np.packbits(rng.random((len(seen), 256)) < 0.03, axis=1)
        return PreparedFrame(vector, None, seen ^ flips)


def run(params: Parameters, frames: int, store: FrameStore | None = None) -> list[SequenceDecision]:
    detector = DOSeqSLAM(params, segmenter=EveryN(), store=store)
    route = Route()
    decisions = []
    for t in range(frames):
        decisions += detector.push_prepared(t * 1_000_000_000, route.frame(t))
    return decisions + detector.finish()


def true_match(decision: SequenceDecision) -> bool:
    return all(
        abs(c.match_index - c.query_index) % LAP in (0, 1, LAP - 1) for c in decision.candidates
    )


# -- parameters ----------------------------------------------------------------------------------


def test_place_search_fields_are_left_out_at_their_defaults() -> None:
    """The rule that keeps every earlier parameter set's bytes: LATER_FIELDS at their default
    are not in to_dict, so neither in the TOML, the canonical JSON nor the hash."""
    p = Parameters()
    assert not set(LATER_FIELDS) & set(p.to_dict())
    assert p.hash == "c928f1ee81baca3f"  # the hash of Parameters() before the place search
    assert Parameters(kappa_s=10).hash == "07235e6e0a3fe873"
    assert "place" not in p.to_toml() and "place" not in p.canonical_json()
    assert Parameters.from_dict({**p.to_dict(), "place_search": "full"}) == p


def test_place_search_fields_are_kept_and_read_back_when_set() -> None:
    p = Parameters(place_search="index", place_count=6)
    values = p.to_dict()
    assert values["place_search"] == "index" and values["place_count"] == 6
    assert "place_queries" not in values  # still at its default
    assert Parameters.from_toml(p.to_toml()) == p
    assert p.hash != Parameters().hash
    assert p.replace(place_search="full", place_count=4) == Parameters()
    with pytest.raises(ParameterError):
        Parameters(place_search="nearest")  # type: ignore[arg-type]
    with pytest.raises(ParameterError):
        Parameters.from_dict({"place_count": 0})


# -- windows ---------------------------------------------------------------------------------


@pytest.mark.parametrize("precision", ["uint8", "float32"])
def test_sad_columns_are_the_full_rows_cells(precision) -> None:
    rng = np.random.default_rng(1)
    store = FrameStore(64, precision, block_frames=16)  # windows cross blocks
    for _ in range(100):
        store.append(rng.standard_normal(64).astype(np.float32))
    queries = store.rows(90, 97)
    full = sad_rows(queries, store, 80)
    window = sad_columns(queries, store, 13, 61)
    assert window.shape == (8, 48)
    np.testing.assert_allclose(window, full[:, 13:61], rtol=1e-6)


def test_a_window_is_enhanced_as_the_full_row_is() -> None:
    """The window is padded by epsilon / 2 (up to the database's ends) before enhancement and
    cropped: its cells are the full row's, at the database's edges as well."""
    rng = np.random.default_rng(2)
    params = Parameters()
    store = FrameStore(2048, "uint8")
    for _ in range(300):
        store.append(rng.standard_normal(2048).astype(np.float32))
    search = PlaceSearch(params)
    full = enhance(sad_rows(store.rows(280, 289), store, 250), params.enhancement_window)
    for first, stop in ((0, 40), (100, 160), (210, 250)):
        scored = search.score(store, 280, 289, Window(first, stop, 1.0), 250)
        assert scored is not None
        np.testing.assert_allclose(scored.enhanced, full[:, first:stop], rtol=1e-5, atol=1e-5)


# -- repeated laps -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def laps() -> dict[str, list[SequenceDecision]]:
    frames = 5 * LAP
    return {
        "full": run(Parameters(alternatives=3), frames),
        "index": run(Parameters(place_search="index", alternatives=3), frames),
    }


def test_index_mode_accepts_the_revisits_that_gamma_rejects_on_repeated_laps(laps) -> None:
    """From the third lap on, the second-best trajectory of the paper's search is another visit
    of the same place: gamma -> 1 and the paper's th = 0.75 rejects nearly every revisit. The
    index mode normalizes against non-matching trajectories and accepts them, at true places."""
    later = {mode: [d for d in ds if d.first_index >= 2 * LAP + 50] for mode, ds in laps.items()}
    full_accepted = [d for d in later["full"] if d.accepted]
    index_accepted = [d for d in later["index"] if d.accepted]
    assert len(later["index"]) >= 50
    assert len(full_accepted) <= len(later["full"]) // 5
    assert len(index_accepted) >= 0.9 * len(later["index"])
    assert all(true_match(d) for d in index_accepted)


def test_the_other_visits_of_a_place_are_the_alternatives(laps) -> None:
    late = [d for d in laps["index"] if d.first_index >= 4 * LAP + 50 and d.accepted]
    assert late
    for d in late:
        visits = {a.start // LAP for a in d.alternatives if abs(a.start - d.best_start) > 10}
        assert len(visits) >= 2  # the place was seen on 4 earlier laps
        for a in d.alternatives:
            assert len(a.match_indices) == len(d.candidates)


@pytest.mark.parametrize("search", ["index", "full"])
def test_the_decisions_are_the_same_with_older_frame_vectors_spilled(laps, search) -> None:
    """The pipeline's store keeps older blocks of frame vectors in a file (pipeline.frame_spill):
    the windows read back from it give the same decisions, bit for bit."""
    spill = DictSpill()
    store = FrameStore(2048, "uint8", block_frames=64, spill=spill)
    params = Parameters(place_search=search, alternatives=3)
    assert run(params, 5 * LAP, store) == laps[search]
    assert spill.reads and store.nbytes <= 3 * 64 * 2048


def test_full_mode_has_no_index_and_the_paper_decision(laps) -> None:
    detector = DOSeqSLAM(Parameters())
    assert not detector.indexed
    assert all(d.second_score is None or d.gamma <= 1.0 for d in laps["full"])
    early = [d for d in laps["full"] if LAP + 50 <= d.first_index < 2 * LAP]
    assert early and all(d.accepted and true_match(d) for d in early)  # one earlier visit


def test_the_columns_scored_per_sequence_do_not_grow_with_the_log(monkeypatch) -> None:
    """Index mode computes SAD only in place_count windows of bounded width: the columns per
    sequence are the same on the ninth lap as on the sixth (place_count windows by then)."""
    widths: list[tuple[int, int]] = []  # (query frame, columns)
    real = place_search_module.sad_columns

    def counting(queries, store, first, stop):
        widths.append((len(store), stop - first))
        return real(queries, store, first, stop)

    monkeypatch.setattr(place_search_module, "sad_columns", counting)
    params = Parameters(place_search="index")
    run(params, 9 * LAP)
    # One window: its starts (the island's spread, at most place_margin + the length apart,
    # and the velocities' spread), +- (place_margin + the exclusion), the trajectory's length,
    # +- epsilon / 2 of padding: a bound in the parameters and the sequence's length alone.
    pad = params.place_margin + 2 * SEQUENCE
    spread = params.place_margin + 3 * SEQUENCE
    window = 2 * pad + spread + 2 * SEQUENCE + params.enhancement_window
    assert max(columns for _, columns in widths) <= window
    per_store: dict[int, int] = {}
    for size, columns in widths:
        per_store[size] = per_store.get(size, 0) + columns
    sixth = [c for s, c in per_store.items() if 5 * LAP <= s < 6 * LAP]
    ninth = [c for s, c in per_store.items() if 8 * LAP <= s < 9 * LAP - SEQUENCE]
    assert np.median(ninth) <= np.median(sixth) <= params.place_count * window


def test_windows_of_an_empty_index_propose_nothing() -> None:
    search = PlaceSearch(Parameters(place_search="index"))
    search.keep(0, None, 0)
    assert search.windows(0, 0, 0, Exclusion(0, 0)) == []


# -- verification at a high frame rate ------------------------------------------------------------


def strided_decision(alternatives: tuple[Alternative, ...]) -> SequenceDecision:
    """30 frames at 10 Hz (stride 5), matched to frames 10, 11, ..."""
    return replace(sequence_decision(30, 100_000_000, 30), alternatives=alternatives)


def test_alternatives_are_tried_at_high_frame_rates_and_given_up_after_one_hopeless_check() -> None:
    """Stride 5: the detector's own trajectory is checked for candidates 0 and 5 and given up
    after those two hopeless checks, each alternative for candidate 0 alone (a second guess,
    given up after one); then the whole sequence is given up."""
    read: list[int] = []

    def blank(indices):
        read.extend(indices)
        return ((i, np.zeros((48, 64), np.uint8)) for i in indices)

    alternatives = (  # inside the database (frames 0-89), off the own windows' 10-frame grid
        Alternative(40, 1.0, 1.5, tuple(range(40, 70))),
        Alternative(72, 1.0, 1.6, tuple(range(72, 102))),
    )
    [plain], plain_stats = verify_in_threads(
        [strided_decision(())], lambda: nullcontext(blank), DEFAULT_VERIFICATION
    )
    read.clear()
    [tried], stats = verify_in_threads(
        [strided_decision(alternatives)], lambda: nullcontext(blank), DEFAULT_VERIFICATION
    )
    # A search's first step reads its window's 10-frame grid and its match: the alternatives'
    # matches for candidate 0 (40, 72) were searched, those for candidate 5 (45, 77) never.
    assert {40, 72} <= set(read) and not {45, 77} & set(read)
    assert plain_stats.pairs < stats.pairs <= plain_stats.pairs + 2 * 6
    reasons = [check.verdict.reason for check in tried.checks]
    assert [reasons[z] for z in (10, 15, 20, 25)] == ["sequence given up"] * 4
    assert [c.proposal for c in tried.checks] == [0] * 30  # rejected: the detector's own check
    assert [c.verdict for c in plain.checks] == [
        c.verdict for c in tried.checks
    ]  # same verdicts on blank frames


def test_keyframes_alone_join_the_index_and_still_find_the_revisits() -> None:
    """place_index_interval_s: a frame joins the index only that long after the last one
    that did (here every other frame of the 1-frame-a-second route); the sequence's own
    frames still query it, and the revisits found are the same true places."""
    params = Parameters(place_search="index", alternatives=3, place_index_interval_s=2.0)
    detector = DOSeqSLAM(params, segmenter=EveryN())
    route = Route()
    decisions = []
    for t in range(4 * LAP):
        decisions += detector.push_prepared(t * 1_000_000_000, route.frame(t))
    decisions += detector.finish()
    assert detector._places is not None
    indexed = detector._places.index.frame_count
    assert 0 < indexed <= (4 * LAP) // 2 + 1
    later = [d for d in decisions if d.first_index >= 2 * LAP + 50]
    accepted = [d for d in later if d.accepted]
    assert len(accepted) >= 0.9 * len(later) and all(true_match(d) for d in accepted)
    with pytest.raises(ParameterError):
        Parameters(place_index_interval_s=-1.0)
