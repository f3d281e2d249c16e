"""The verification stage: the detector's decisions in, each candidate pair checked geometrically.

Runs after the detector, on the decisions whose sequences it accepted (f < th), one decision
at a time. Frames are not kept by the detector, so the stage asks a `FrameLoader` for the
frames a decision needs (the query frames and the +-refine_radius window around each match)
and keeps their features in a least-recently-used cache bounded in bytes: memory stays bounded
whatever the log length, and frames near each other in time (the usual case: a sequence's
queries, a match window) are loaded in one read.

Each candidate (q, m) is checked against every frame of m +- r inside the sequence's database;
the frame with the most inliers is the refined match, and the pair is accepted when its inliers
reach `min_inliers` (`refine_match`). With intrinsics and `bracket` (the default), the refined
match must then be bracketed: among the verified frames next to it, the match camera passes
from behind the query to ahead of it, and the nearer frame of that sign change becomes the
refined match; else the pair is rejected "not bracketed" (`geometry.bracketed_match`: the
same facades seen from several metres away overlap, but are not the same place); a pair
whose relative rotation exceeds `max_rotation_deg` is rejected by the check itself.
When every verified frame of the window sees the match camera on one side of the query, the
query's place lies beyond the window on the other: the check walks that way (`_walk`), a
stride at a time while the frames pass with a pose, up to WALK_RADII * r past the window, and
brackets the match where the side changes. Next checks of the sequence follow that offset.
The walk exists because at a high frame rate a proposed trajectory is often a few seconds off
along the route, past the window. With a pose topic, where the match's frames are far apart
(a low frame rate), an accepted pair then moves to the frame nearest the query camera as PnP
with the odometry's baseline places it; a pair turned past max_rotation_deg is kept only where
that places it near its match, and one not bracketed is accepted where it places it
(`_placed_by_odometry`, verification.position).

When a pair fails and the detector recorded next-best trajectories of the sequence
(`SequenceDecision.alternatives`), the same query is checked against each of them in turn, at
the match that trajectory gives it, +- r: the first that passes is kept (`PairCheck.proposal`
says which). A wrong trajectory is the detector's usual failure on a revisit (a similar stretch
scores a little lower than the true one), and the check tells them apart. An alternative that
is hopeless (under half of min_inliers) for two queries in a row is not tried again in that
sequence, the rule of high frame rates below: a trajectory wrong at two queries stays wrong,
and checking it further costs frame pairs for almost no true pair. Rejected pairs are kept
with their verdict.
A pair found anywhere but at the detector's own match (an alternative, or the previous
sequence's place continued, below) is a second guess and needs `second_guess_factor` times
the inliers (`_second_guess`): every further place tried for a query is one more chance to
pass a look-alike a few metres off.

High frame rates (`query_stride` > 1: more than one frame per `query_interval_s`): neighbouring
frames are near copies, and checking each of them against 2r + 1 frames would cost more than
the detector. There the stage checks every s-th candidate of a sequence (the others are
recorded as skipped, not reported), and searches the window coarse to fine: the match and
every frame whose index is a multiple of 2s, then the multiples of s within 2s of the best,
then the two frames s // 2 on either side of the best, then s // 4, ... down to 1 (at s = 5:
2, then 1), each finer step only when the best so far is not hopeless (under half of
min_inliers). Near copies pass or fail together, so halving around the best finds almost
every pair an exhaustive search of the window finds, for a fraction of its frame pairs.
The next checked candidate of the sequence first looks at the frame at the previous one's
offset from its match and the grid frames beside it: accepted there, it is done; rejected but
not hopeless there (not bracketed, too few inliers, turned too far), it is rejected too, the
tracking having found the place; hopeless there after a hopeless previous one, it is rejected;
otherwise (hopeless after a previous one that was not) its whole window is searched. A near
miss is not searched again because that search seldom turns it into an accepted pair and
takes a large share of the frame pairs checked.
Two hopeless checks in a row give a proposal up, one an alternative (a second guess); once
every proposal is, the sequence's remaining candidates are skipped too (reason "sequence
given up"). The candidates of a sequence lie on one trajectory of the detector, so a
trajectory that is wrong at two queries stays wrong. At s = 1 every candidate gets the
exhaustive window.
At s > 1 the next-best trajectories are proposals of their own, each checked by the rules above
(tracked, coarse to fine, given up after one hopeless check): a revisit whose true visit is an
alternative (the indexed place search proposes the other visits of a place so) is found there,
at a cost of at most one hopeless check per wrong alternative and sequence (`_strided`).

Sequences at a high frame rate are short (about 2 s of a 10 Hz drive), and on a revisit the
next one drives on through the place the last one was verified at. So each sequence is handed
the previous one's last accepted pair (`Hint`) and looks first where it puts the sequence's
first query at the same speed: a tracked check there (proposal CONTINUED, -1), before the
detector's own search. Threads verify fixed chains of CHAIN_DECISIONS decisions, each handing
its hint to the next within the chain, so the results are the same on any number of threads.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import AbstractContextManager
from dataclasses import dataclass, field, fields

import numpy as np
import numpy.typing as npt

from .. import waiting
from ..detector.events import Candidate, SequenceDecision
from .geometry import (
    NOT_BRACKETED,
    Crossing,
    FrameFeatures,
    GrayImage,
    Intrinsics,
    Verdict,
    best_verdict,
    bracketed_match,
    crossing,
    crossing_side,
    extract_features,
    pair_min_inliers,
    side_of_query,
    turned_past,
    turned_too_far,
    verify_pair,
)
from .motion import (
    ODOMETRY_DISAGREES,
    STATIONARY,
    CameraPath,
    agrees_with_odometry,
    frames_between,
    left_by_images,
)
from .params import VerificationParameters
from .position import nearest_frame, neighbour, neighbours_of, query_position, spacing_m

# Sorted frame indices in, (index, gray frame) out for each of them.
FrameLoader = Callable[[Sequence[int]], Iterator[tuple[int, GrayImage]]]
StoredFeatures = Callable[[int], FrameFeatures | None]

# Shared by the verification threads. The stage's reads are local (a sequence's windows), so a
# small cache serves them: a larger one re-reads fewer frames but saves no wall time, and costs
# its size in resident memory.
DEFAULT_CACHE_BYTES = 64 * 2**20

# The reasons of a candidate left unchecked at a high frame rate (verification = "skipped"):
# the query stride left it out, or its sequence was given up after two hopeless checks.
SKIPPED_REASON = "not checked"
GIVEN_UP_REASON = "sequence given up"
SKIPPED_REASONS = (SKIPPED_REASON, GIVEN_UP_REASON)
# Hopeless checks in a row after which a sequence's remaining candidates are skipped.
GIVE_UP_AFTER = 2
# At a high frame rate, a next-best trajectory is given up after this many: it is a second
# guess, and a second search of one whose first was hopeless costs frame pairs and, on the
# tuning runs, never found a pair.
GIVE_UP_ALTERNATIVE_AFTER = 1
# A window is searched on every (COARSE_GRID * s)-th frame first, then finer (module docstring).
COARSE_GRID = 2
# A check that passes but is not bracketed walks on at most this many refine_radius past its
# window, towards the side where its frames say the query's place lies (`Verifier._walk`).
WALK_RADII = 2
# A bracketing looks at the query's checked frames this many refine_radius either side of the
# refined match, besides its window (`Verifier._bracketed`).
BRACKET_RADII = 2
# The rejection of a pair found on a second guess under its higher bar (`_second_guess`).
SECOND_GUESS_REASON = "too few inliers for a second guess"
# `PairCheck.proposal` of a pair accepted where the previous sequence's verified place
# continues (`Hint`), at a high frame rate.
CONTINUED = -1
# Decisions verified in a row by one thread, each handing its verified place to the next
# (`Hint`): fixed, so the results do not depend on the number of threads.
CHAIN_DECISIONS = 16


class Cancelled(Exception):
    """The stage was told to stop (Ctrl-C or SIGTERM on the main thread): raised inside a
    verification thread at its next frame pair or frame load, so that it ends in milliseconds
    instead of finishing the decision, or the whole stage, first."""


@dataclass(frozen=True)
class PairCheck:
    """One candidate pair after verification."""

    candidate: Candidate
    refined_match_index: int  # the frame of match +- r with the most inliers
    verdict: Verdict
    # 0: the detector's match; k > 0: the match on the sequence's k-th next-best trajectory
    # (decision.alternatives[k - 1]), whose +- r window held the refined match; CONTINUED:
    # the previous sequence's verified place, continued (`Hint`), at `continued_match`.
    proposal: int = 0
    continued_match: int = -1

    @property
    def accepted(self) -> bool:
        return self.verdict.accepted

    @property
    def skipped(self) -> bool:
        """Left unchecked at a high frame rate (query stride, or its sequence given up)."""
        return self.verdict.reason in SKIPPED_REASONS


@dataclass(frozen=True)
class Hint:
    """Where the previous sequence's last accepted pair put its query: at a high frame rate
    the next sequence usually drives on through the same place, so its first check looks
    there first (at query q: match + (q - query), the same speed), before the detector's
    proposals. Verified as any proposal, so a wrong hint costs a hopeless check or two."""

    query_index: int
    match_index: int

    def match_for(self, query_index: int) -> int:
        return self.match_index + (query_index - self.query_index)


@dataclass(frozen=True)
class VerifiedDecision:
    """A detector decision and the checks of its candidates (none when not verified)."""

    decision: SequenceDecision
    checks: tuple[PairCheck, ...]

    @property
    def accepted_pairs(self) -> int:
        return sum(check.accepted for check in self.checks)

    @property
    def max_inliers(self) -> int:
        return max((check.verdict.inliers for check in self.checks), default=0)

    @property
    def hint(self) -> Hint | None:
        """The last accepted pair, for the next sequence (None: none accepted)."""
        accepted = [check for check in self.checks if check.accepted]
        if not accepted:
            return None
        last = accepted[-1]
        return Hint(last.candidate.query_index, last.refined_match_index)


@dataclass
class VerificationStats:
    """What the stage did and what it cost (seconds of wall time on the calling thread)."""

    decisions: int = 0
    candidates: int = 0
    accepted: int = 0
    from_alternatives: int = 0  # of the accepted: on a next-best trajectory (proposal > 0)
    continued: int = 0  # of the accepted: where the previous sequence's place went on
    skipped: int = 0  # candidates left unchecked (counted in `candidates`)
    given_up: int = 0  # of the skipped: after their sequence's two hopeless checks
    stationary: int = 0  # candidates rejected by the motion rule (verification.motion)
    odometry_disagrees: int = 0  # candidates whose fit's turn the pose topic's contradicts
    motion_by_images: int = 0  # motion-rule decisions taken on image evidence (no poses)
    relocated: int = 0  # accepted pairs moved to a nearer frame by their position (position)
    placed: int = 0  # pairs not bracketed, accepted where their position puts them (position)
    pairs: int = 0  # verify_pair calls (a candidate costs up to 2r + 1)
    frames_loaded: int = 0  # frames decoded for features (re-reads of evicted frames included)
    frames_stored: int = 0  # frames whose features came from `Verifier.stored_features`
    load_s: float = 0.0
    features_s: float = 0.0
    pairs_s: float = 0.0
    peak_cache_bytes: int = 0

    @property
    def total_s(self) -> float:
        return self.load_s + self.features_s + self.pairs_s

    @property
    def ms_per_pair(self) -> float:
        return 1e3 * self.pairs_s / self.pairs if self.pairs else 0.0

    def add(self, other: VerificationStats) -> None:
        """Sums another thread's figures into these: seconds add up over the threads, and
        so do the threads' cache peaks (an upper bound of their joint peak)."""
        for item in fields(self):
            setattr(self, item.name, getattr(self, item.name) + getattr(other, item.name))


def lone_side_holds(side: int, beyond: Verdict | None, confirmed: bool) -> bool:
    """Whether a crossing's side of one frame (`side`: -1 before it, +1 after) stands
    against the verdict of the frame a step beyond it (None: past the database's ends).
    `confirmed` (above one frame a step, neighbours near copies): that frame must lie on the
    same side. Else (low rates, where a side of one frame is common, its neighbour metres
    away and failing) it may be silent, but not on the other side: a flipped estimate among
    frames of one spot (a parked pass seen from 5 m) is no crossing."""
    if beyond is None:
        return not confirmed
    found = crossing_side(beyond)
    return found == side or (not confirmed and found == 0)


def query_stride(decision: SequenceDecision, interval_s: float) -> int:
    """Candidates per checked one: the frames of the sequence within `interval_s` (>= 1).

    From the sequence's mean frame interval, in integer nanoseconds so that a steady rate
    gives the same stride on every machine (10 Hz and 0.5 s: 5; 2 Hz or slower: 1).
    """
    if decision.length < 2 or interval_s <= 0:
        return 1
    span_ns = decision.last_timestamp_ns - decision.first_timestamp_ns
    frame_ns = max(1, span_ns // (decision.length - 1))
    return max(1, round(interval_s * 1e9) // frame_ns)


class FeatureCache:
    """Per-frame features, least recently used evicted first once over `max_bytes`."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.bytes = 0
        self._items: OrderedDict[int, FrameFeatures] = OrderedDict()

    def get(self, index: int) -> FrameFeatures | None:
        features = self._items.get(index)
        if features is not None:
            self._items.move_to_end(index)
        return features

    def put(self, index: int, features: FrameFeatures) -> None:
        old = self._items.pop(index, None)
        if old is not None:
            self.bytes -= old.nbytes
        self._items[index] = features
        self.bytes += features.nbytes
        while self.bytes > self.max_bytes and len(self._items) > 1:
            _, evicted = self._items.popitem(last=False)
            self.bytes -= evicted.nbytes

    def __len__(self) -> int:
        return len(self._items)


@dataclass
class Verifier:
    """Checks the candidates of accepted decisions; see the module docstring."""

    params: VerificationParameters
    load_frames: FrameLoader
    intrinsics: Intrinsics | None = None
    cache_bytes: int = DEFAULT_CACHE_BYTES
    stats: VerificationStats = field(default_factory=VerificationStats)
    # Set by whoever runs the stage to stop it: checked before every frame pair and load.
    cancel: threading.Event = field(default_factory=threading.Event)
    # Features extracted earlier (by the replay: pipeline.feature_spill), by frame index; a
    # frame it lacks (None) is loaded and extracted here.
    stored_features: StoredFeatures | None = None
    # The camera's positions from a pose topic, for the motion rule (None: image evidence).
    camera_path: CameraPath | None = None

    def __post_init__(self) -> None:
        self._cache = FeatureCache(self.cache_bytes)
        # The fit's own rotation limit: confirmed_rotation_deg where a pose topic can confirm
        # the pairs turned past max_rotation_deg (`_placed_by_odometry`).
        self._fit_params = self.params
        limit = self.params.confirmed_rotation_deg
        if self._can_place() and limit > self.params.max_rotation_deg:
            self._fit_params = dataclasses.replace(self.params, max_rotation_deg=limit)

    def _can_place(self) -> bool:
        """A pose topic with orientations and intrinsics: the query can be placed by PnP."""
        path = self.camera_path
        return path is not None and path.orientations is not None and self.intrinsics is not None

    def verify_all(self, decisions: Iterable[SequenceDecision]) -> list[VerifiedDecision]:
        """Each decision in turn, each handed the one before's `hint` (as the threads of
        `verify_in_threads` do within a chain)."""
        verified: list[VerifiedDecision] = []
        for decision in decisions:
            verified.append(self.verify(decision, verified[-1].hint if verified else None))
        return verified

    def verify(self, decision: SequenceDecision, hint: Hint | None = None) -> VerifiedDecision:
        """The decision with one PairCheck per candidate when it is accepted, else none.

        At stride 1 every frame of the window is checked, not only the detector's match:
        keeping the detector's match whenever it passed (and searching only for the rejected
        ones) checks far fewer pairs but lets wrong matches through.
        """
        self.stats.decisions += 1
        if not decision.accepted:
            return VerifiedDecision(decision, ())
        stride = query_stride(decision, self.params.query_interval_s)
        features: dict[int, FrameFeatures] = {}
        if stride == 1:  # every query and window frame will be needed: read them in one go
            needed = {c.query_index for c in decision.candidates}
            for candidate in decision.candidates:
                needed.update(self._window(candidate.match_index, decision.database_size))
            features = self._features(sorted(needed))
        if stride == 1:
            checks = self._exhaustive(decision, features)
        else:
            checks = self._strided(decision, stride, hint)
        # Only reported pairs keep their inlier points (for drawing): a pair rejected after
        # its fit (bracketing, motion rule, second guess) drops them.
        checks = [c if c.accepted else _without_points(c) for c in checks]
        self.stats.candidates += len(checks)
        self.stats.accepted += sum(check.accepted for check in checks)
        self.stats.from_alternatives += sum(c.accepted and c.proposal > 0 for c in checks)
        self.stats.continued += sum(c.accepted and c.proposal == CONTINUED for c in checks)
        self.stats.skipped += sum(check.skipped for check in checks)
        self.stats.given_up += sum(check.verdict.reason == GIVEN_UP_REASON for check in checks)
        self.stats.stationary += sum(check.verdict.reason == STATIONARY for check in checks)
        self.stats.odometry_disagrees += sum(
            check.verdict.reason == ODOMETRY_DISAGREES for check in checks
        )
        return VerifiedDecision(decision, tuple(checks))

    def _exhaustive(
        self, decision: SequenceDecision, features: dict[int, FrameFeatures]
    ) -> list[PairCheck]:
        """Stride 1: every candidate's whole window, then the alternatives' when it fails."""
        checks: list[PairCheck] = []
        alternative_runs = [0] * len(decision.alternatives)  # hopeless in a row, per one
        for z, candidate in enumerate(decision.candidates):
            seen: dict[int, Verdict] = {}  # window frame -> verdict of this query
            check = self._check(candidate, decision.database_size, 1, None, features, seen)
            if not check.accepted:  # the query's features: read by `verify`
                query = features[candidate.query_index]
                check = self._try_alternatives(decision, z, check, query, seen, alternative_runs)
            checks.append(check)
        return checks

    def _strided(
        self, decision: SequenceDecision, stride: int, hint: Hint | None = None
    ) -> list[PairCheck]:
        """Stride s > 1: every s-th candidate, coarse to fine, on each proposal in turn.

        Proposal 0 is the detector's trajectory, k > 0 the k-th alternative, and with a `hint`
        one more, tried first: the previous sequence's place continued, its first check
        tracked from the hint as from a previous check (`_continued`). Each proposal is
        tracked on its own (the offset of its last check) and given up after GIVE_UP_AFTER
        hopeless checks in a row (an alternative after GIVE_UP_ALTERNATIVE_AFTER); the
        proposal accepted last is tried first, so a sequence
        whose revisit lies on an alternative checks that one alone while it keeps passing.
        The sequence is given up once every proposal is. A candidate costs at most one
        coarse-to-fine search per proposal, and each wrong proposal at most two hopeless ones
        per sequence: bounded by (1 + alternatives) x the cost without alternatives.
        """
        alternatives = len(decision.alternatives)
        proposals = 1 + alternatives + (hint is not None)
        runs = [0] * proposals  # hopeless checks in a row, per proposal
        limits = [GIVE_UP_AFTER] * proposals
        limits[1 : 1 + alternatives] = [GIVE_UP_ALTERNATIVE_AFTER] * alternatives
        last: list[PairCheck | None] = [None] * proposals  # each one's last check
        first = 0  # the proposal tried first: the last accepted
        if hint is not None:  # the last slot; tracked from the hint, tried first
            first = proposals - 1
            last[first] = self._continued(decision, hint)
        checks: list[PairCheck] = []
        for z, candidate in enumerate(decision.candidates):
            if z % stride:
                checks.append(PairCheck(candidate, candidate.match_index, self._skipped()))
                continue
            order = [first, *(k for k in range(proposals) if k != first)]
            live = [k for k in order if runs[k] < limits[k]]
            if not live:
                given_up = self._skipped(GIVEN_UP_REASON)
                checks.append(PairCheck(candidate, candidate.match_index, given_up))
                continue
            seen: dict[int, Verdict] = {}  # window frame -> verdict of this query
            kept: PairCheck | None = None
            for k in live:
                proposed = self._proposed(decision, z, k, hint)
                check = self._check(proposed, decision.database_size, stride, last[k], {}, seen)
                last[k] = check
                if k != 0:
                    check = self._second_guess(check)
                runs[k] = runs[k] + 1 if self._hopeless(check.verdict) else 0
                result = self._numbered(candidate, check, k, alternatives)
                if kept is None or check.accepted or k == 0:  # rejected: the own check
                    kept = result
                if check.accepted:
                    first = k
                    break
            assert kept is not None
            checks.append(kept)
        return checks

    @staticmethod
    def _proposed(
        decision: SequenceDecision, z: int, proposal: int, hint: Hint | None = None
    ) -> Candidate:
        """Candidate z at the match that proposal gives it (0: the detector's own; after the
        alternatives, the hint's place)."""
        candidate = decision.candidates[z]
        if proposal == 0:
            return candidate
        if proposal > len(decision.alternatives):
            assert hint is not None
            match = min(hint.match_for(candidate.query_index), decision.database_size - 1)
        else:
            match = decision.alternatives[proposal - 1].match_indices[z]
        return dataclasses.replace(candidate, match_index=max(match, 0))

    @staticmethod
    def _numbered(candidate: Candidate, check: PairCheck, k: int, alternatives: int) -> PairCheck:
        """The check of proposal slot k as recorded: the hint's slot is CONTINUED."""
        if k <= alternatives:
            return PairCheck(candidate, check.refined_match_index, check.verdict, k)
        match = check.candidate.match_index
        return PairCheck(candidate, check.refined_match_index, check.verdict, CONTINUED, match)

    def _continued(self, decision: SequenceDecision, hint: Hint) -> PairCheck:
        """A stand-in previous check for the hint's slot, at offset 0 from where the hint puts
        the first candidate, so that its first check is a tracked one (the frame
        there and the grid beside it) rather than a search of the whole window; hopeless
        there, the hint is not searched further."""
        first = self._proposed(decision, 0, 1 + len(decision.alternatives), hint)
        # Rejected with no inliers: a tracked check that is hopeless there too ends at once.
        return PairCheck(first, first.match_index, Verdict(False, 0, 0, "E", "hint"))

    def _skipped(self, reason: str = SKIPPED_REASON) -> Verdict:
        return Verdict(False, 0, 0, "F" if self.intrinsics is None else "E", reason)

    def _check(
        self,
        candidate: Candidate,
        database_size: int,
        stride: int,
        previous: PairCheck | None,
        features: dict[int, FrameFeatures],
        seen: dict[int, Verdict],
    ) -> PairCheck:
        """One candidate: its window searched exhaustively (stride 1), or tracked from the
        previous check of its sequence and, failing that, coarse to fine (module docstring).
        A tracked check's window is centred where the previous one's offset puts it, which a
        walk (`_walk`) may have moved past the candidate's own window. `seen` collects the
        query's verdict against each frame, so each pair is checked once."""
        match = candidate.match_index
        if previous is not None:
            offset = previous.refined_match_index - previous.candidate.match_index
            bounds = self._reach(match, database_size)
            match = min(max(match + offset, bounds.start), bounds.stop - 1)
        window = self._window(match, database_size)
        query = features.get(candidate.query_index)
        if query is None:  # stride > 1: loaded when checked (a given-up sequence needs fewer)
            query = self._features([candidate.query_index])[candidate.query_index]

        def best(frames: Iterable[int]) -> tuple[int, Verdict]:
            self._check_frames(query, [m for m in frames if m in window], seen)
            return best_verdict([(m, v) for m, v in seen.items() if m in window], match)

        def placed(refined: int, verdict: Verdict) -> PairCheck:
            refined, verdict = self._bracketed(
                query, window, seen, refined, verdict, stride, database_size
            )
            if verdict.reason == NOT_BRACKETED:
                bounds = self._reach(candidate.match_index, database_size)
                refined, verdict = self._walk(query, window, seen, refined, stride, bounds)
            refined, verdict = self._placed_by_odometry(
                query, window, seen, refined, verdict, database_size
            )
            return PairCheck(candidate, refined, self._moved(query, candidate, refined, verdict))

        if stride == 1:
            return placed(*best(window))
        if previous is not None:  # the frame at the previous offset, and the grid beside it
            tracked = [m for m in range(match - stride + 1, match + stride) if m % stride == 0]
            check = placed(*best([match, *tracked]))
            # Rejected but not hopeless (not bracketed, too few inliers, turned too far): the
            # place is where the tracking put it, and a search of the window seldom does better.
            if not self._hopeless(check.verdict) or self._hopeless(previous.verdict):
                return check
        # The grids are fixed in frame indices (not relative to the match), so the next checked
        # candidates, whose windows overlap this one, find most of their frames in the cache.
        coarse = COARSE_GRID * stride
        refined, verdict = best(m for m in window if m % coarse == 0 or m == match)
        if not self._hopeless(verdict):  # its near copies on either side will not pass either
            near = range(refined - coarse + 1, refined + coarse)
            refined, verdict = best(m for m in near if m % stride == 0)
        step = stride // 2  # then halving steps around the best, down to its neighbours
        while step and not self._hopeless(verdict):
            refined, verdict = best((refined - step, refined + step))
            step //= 2
        return placed(refined, verdict)

    def _walk(
        self,
        query: FrameFeatures,
        window: range,
        seen: dict[int, Verdict],
        refined: int,
        step: int,
        bounds: range,
    ) -> tuple[int, Verdict]:
        """A check that passed but was not bracketed: every verified frame saw the match camera
        on one side of the query, so the query's place lies beyond the window on the other
        (`side_of_query`). Steps that way from the refined match, `step` frames at a time,
        while the frames pass with a relative pose, until one lies on the other side and the
        frame a step further does not lie back on the first (one flipped direction estimate
        is not the place: the walk goes on past it); the frames between the last two are then
        checked and the match bracketed among them. Stops, not bracketed, at a frame that
        fails or outside `bounds` (`_reach`)."""
        direction = side_of_query(seen[refined])
        at = refined
        while direction and at + step * direction in bounds:
            ahead = at + step * direction
            self._check_frames(query, [ahead], seen)
            side = side_of_query(seen[ahead])
            if side == 0:
                break
            beyond = ahead + step * direction
            if side != direction and beyond in bounds:
                self._check_frames(query, [beyond], seen)
                if side_of_query(seen[beyond]) == direction:  # a lone flip
                    at = beyond
                    continue
            if side != direction:  # the place lies between `at` and `ahead`
                between = range(min(at, ahead), max(at, ahead) + 1)
                self._check_frames(query, between, seen)
                span = range(min(window.start, between.start), max(window.stop, between.stop))
                nearest = best_verdict([(m, seen[m]) for m in between], at)
                return self._bracketed(query, span, seen, *nearest, step, bounds.stop)
            at = ahead
        return refined, dataclasses.replace(seen[refined], accepted=False, reason=NOT_BRACKETED)

    def _try_alternatives(
        self,
        decision: SequenceDecision,
        z: int,
        rejected: PairCheck,
        query: FrameFeatures,
        seen: dict[int, Verdict],
        hopeless_runs: list[int],
    ) -> PairCheck:
        """Candidate z checked at each next-best trajectory's match (+- r) in turn: the first
        that passes, else the rejected check of the detector's own match. `hopeless_runs`
        counts each alternative's hopeless checks in a row; at GIVE_UP_AFTER it is skipped."""
        for number, alternative in enumerate(decision.alternatives, start=1):
            if hopeless_runs[number - 1] >= GIVE_UP_AFTER:
                continue
            match = alternative.match_indices[z]
            window = self._window(match, decision.database_size)
            self._check_frames(query, window, seen)
            refined, verdict = best_verdict([(m, seen[m]) for m in window], match)
            refined, verdict = self._bracketed(
                query, window, seen, refined, verdict, 1, decision.database_size
            )
            refined, verdict = self._placed_by_odometry(
                query, window, seen, refined, verdict, decision.database_size
            )
            verdict = self._moved(query, rejected.candidate, refined, verdict)
            hopeless = self._hopeless(verdict)
            hopeless_runs[number - 1] = hopeless_runs[number - 1] + 1 if hopeless else 0
            check = self._second_guess(PairCheck(rejected.candidate, refined, verdict, number))
            if check.accepted:
                return check
        return rejected

    def _second_guess(self, check: PairCheck) -> PairCheck:
        """An accepted check of a place other than the detector's own as it stands at the
        higher bar of a second guess (`second_guess_factor` x the pair's min_inliers), else
        rejected SECOND_GUESS_REASON. Its tracking is unchanged: the place it found stays where
        the proposal's next check looks first."""
        if not check.accepted or self.params.second_guess_factor == 1:
            return check
        query, match = check.candidate.query_index, check.refined_match_index
        pair = self._features([query, match])
        needed = pair_min_inliers(pair[query], pair[match], self.params)
        if check.verdict.inliers >= self.params.second_guess_factor * needed:
            return check
        verdict = dataclasses.replace(check.verdict, accepted=False, reason=SECOND_GUESS_REASON)
        return dataclasses.replace(check, verdict=verdict)

    def _moved(
        self, query: FrameFeatures, candidate: Candidate, refined: int, verdict: Verdict
    ) -> Verdict:
        """An accepted verdict as the motion rule leaves it: rejected STATIONARY when the
        camera did not leave the refined match's place before the query, ODOMETRY_DISAGREES
        when the pose topic turned far more than the fit (verification.motion). The inliers
        stay: the place is seen, it is only not a revisit."""
        if not verdict.accepted or not self.params.motion_rule:
            return verdict
        q = candidate.query_index
        left = None
        if self.camera_path is not None:
            left = self.camera_path.left(refined, q, self.params.leave_distance_m)
        if left is None:
            self.stats.motion_by_images += 1
            left = left_by_images(self._away(query, q, refined))
        if not left:
            return dataclasses.replace(verdict, accepted=False, reason=STATIONARY)
        if not self._agrees_with_odometry(refined, q, verdict):
            return dataclasses.replace(verdict, accepted=False, reason=ODOMETRY_DISAGREES)
        return verdict

    def _placed_by_odometry(
        self,
        query: FrameFeatures,
        window: range,
        seen: dict[int, Verdict],
        refined: int,
        verdict: Verdict,
        database_size: int,
    ) -> tuple[int, Verdict]:
        """A checked pair as the query's position by PnP with the odometry's baseline leaves
        it (verification.position). Accepted, where the visit's frames lie over
        relocate_spacing_m apart: moved to the visit's frame nearest the query camera when
        that frame is relocate_margin_m nearer and its own check passes. Accepted and turned
        past max_rotation_deg (up to confirmed_rotation_deg): rejected for its rotation
        unless placed within confirm_distance_m of its match. Not bracketed, its fit passed
        and not turned: accepted where the query is placed (`place_unbracketed`,
        `_placed_unbracketed`; one relaxation a pair: each lets a few look-alikes through).
        Unchanged without a pose topic or intrinsics."""
        path, params = self.camera_path, self.params
        if not self._can_place():
            return refined, verdict
        assert path is not None and self.intrinsics is not None
        unbracketed = (
            params.place_unbracketed and verdict.reason == NOT_BRACKETED and seen[refined].accepted
        )
        if not verdict.accepted and not unbracketed:
            return refined, verdict
        fitted = seen[refined] if unbracketed else verdict
        turned = self._is_turned(fitted)
        if unbracketed and turned:  # one relaxation a pair: a turned pair must be bracketed
            return refined, verdict
        spacing = spacing_m(path, refined)
        spaced = spacing is not None and spacing > params.relocate_spacing_m
        if not turned and not spaced and not unbracketed:
            return refined, verdict
        # The visit around the refined match (a walk may have taken it past the window).
        reach, stop = params.refine_radius, max(window.stop, refined + 1)
        around = range(max(0, refined - reach), min(refined + reach + 1, stop))
        position = self._position(query, refined, around, fitted)
        if position is None:
            return refined, self._turned(verdict) if turned and not unbracketed else verdict
        if unbracketed:
            return self._placed_unbracketed(query, refined, verdict, position, seen, database_size)
        nearest, distance, now = nearest_frame(path, refined, position, around)
        if spaced and nearest != refined and now - distance >= params.relocate_margin_m:
            self._check_frames(query, [nearest], seen)
            if seen[nearest].accepted:
                self.stats.relocated += 1
                refined, verdict, now = nearest, seen[nearest], distance
                turned = self._is_turned(verdict)
        if turned and now > params.confirm_distance_m:
            return refined, self._turned(verdict)
        return refined, verdict

    def _placed_unbracketed(
        self,
        query: FrameFeatures,
        refined: int,
        verdict: Verdict,
        position: npt.NDArray[np.float64],
        seen: dict[int, Verdict],
        database_size: int,
    ) -> tuple[int, Verdict]:
        """A pair not bracketed, accepted at the frame nearest the query's position among
        those its refined match may be (`_reach`) when: that frame is within
        confirm_distance_m of it and not at an end of them that the visit goes on past (the
        place may lie beyond), its own check passes unturned, and PnP from that frame places
        the query within confirm_distance_m too. A position is trusted where it was measured:
        the first may come from metres away, along a baseline on one side only. Else the
        pair stays rejected."""
        assert self.camera_path is not None
        visit = self._reach(refined, database_size)
        nearest, distance, _ = nearest_frame(self.camera_path, refined, position, visit)
        cut = {visit.start, visit.stop - 1} - {0, database_size - 1}  # the visit goes on
        if distance > self.params.confirm_distance_m or nearest in cut:
            return refined, verdict
        self._check_frames(query, [nearest], seen)
        if not seen[nearest].accepted or self._is_turned(seen[nearest]):
            return refined, verdict
        if nearest != refined and not self._placed_near(query, nearest, visit, seen):
            return refined, verdict
        self.stats.placed += 1
        return nearest, seen[nearest]

    def _position(
        self, query: FrameFeatures, frame: int, around: range, fitted: Verdict
    ) -> npt.NDArray[np.float64] | None:
        """The query camera in `frame`'s camera frame by PnP against its points triangulated
        with its neighbours of the visit within `around` (None: no baseline, or no pose)."""
        assert self.camera_path is not None and self.intrinsics is not None
        near = neighbours_of(self.camera_path, frame, around)
        if not near:  # no baseline: nothing to triangulate, no frame to load
            return None
        features = self._features([frame, *near])
        visit = [neighbour(self.camera_path, frame, n, features[n]) for n in near]
        return query_position(query, features[frame], visit, fitted, self.intrinsics, self.params)

    def _placed_near(
        self, query: FrameFeatures, frame: int, around: range, seen: dict[int, Verdict]
    ) -> bool:
        """Whether PnP from `frame` itself places the query within confirm_distance_m of it:
        a pair not bracketed may move metres from the frame it was placed from, along a
        baseline on one side only (a revisit of the first frames), and a position is trusted
        where it was measured."""
        distance = self._placed_distance(query, frame, around, seen)
        return distance is not None and distance <= self.params.confirm_distance_m

    def _placed_distance(
        self, query: FrameFeatures, frame: int, around: range, seen: dict[int, Verdict]
    ) -> float | None:
        """How far from `frame` PnP from it places the query camera (metres; None where it
        does not place it)."""
        position = self._position(query, frame, around, seen[frame])
        return None if position is None else float(np.linalg.norm(position))

    def _is_turned(self, verdict: Verdict) -> bool:
        """Turned past max_rotation_deg (accepted by the fit only up to confirmed_rotation_deg)."""
        return turned_past(verdict, self.params.max_rotation_deg)

    def _turned(self, verdict: Verdict) -> Verdict:
        """Rejected for its rotation, as the fit rejects it without a pose topic."""
        reason = turned_too_far(self.params.max_rotation_deg)
        return dataclasses.replace(verdict, accepted=False, reason=reason)

    def _agrees_with_odometry(self, match: int, query: int, verdict: Verdict) -> bool:
        """The fit's rotation agrees with the pose topic's turn (True without one, or without
        a rotation: a fundamental-matrix fit has none)."""
        path, params = self.camera_path, self.params
        turn = None if path is None else path.turn(match, query)
        if turn is None or verdict.rotation_deg is None:
            return True
        drift, per_m = params.heading_drift_deg, params.heading_drift_deg_per_m
        return agrees_with_odometry(verdict.rotation_deg, turn, drift, per_m)

    def _away(self, query: FrameFeatures, query_index: int, match: int) -> list[bool]:
        """For each frame sampled between the match and the query: whether it sees neither of
        them (hopeless against both). Against the query alone, a still camera's own frames
        fail whenever noise and light drift take a small frame's features below the bar; a
        frame that sees the match's place has not left it either."""
        between = frames_between(match, query_index, self.params.leave_samples)
        features = self._features(between)
        from_query = dict(self._verdicts(query, between, features))
        unseen = [m for m in between if self._hopeless(from_query[m])]
        from_match: dict[int, Verdict] = {}
        if unseen:
            at_match = self._features([match])[match]
            from_match = dict(self._verdicts(at_match, unseen, features))
        return [m in from_match and self._hopeless(from_match[m]) for m in between]

    def _bracketed(
        self,
        query: FrameFeatures,
        window: range,
        seen: dict[int, Verdict],
        refined: int,
        verdict: Verdict,
        step: int,
        database_size: int,
    ) -> tuple[int, Verdict]:
        """`bracketed_match` over the query's checked frames in the window and within
        BRACKET_RADII * refine_radius of the refined match, when `params.bracket` is on: a
        window that ends just past the true crossing would otherwise keep a noisy sign change
        further on (a figure eight's pair 3.3 m from its place). A run of frames ends at a gap
        of more than refine_radius unchecked frames. The frames a strided search skipped
        between the crossing's two are checked before the pair is bracketed: the place lies
        among them, and one turned past max_rotation_deg there rejects the pair
        (`bracketed_match`), where the two a stride apart may both be estimated under it (the
        rotation and a sideways translation are confused at the closest point).
        """
        if not self.params.bracket:
            return refined, verdict
        reach = BRACKET_RADII * self.params.refine_radius
        near = range(refined - reach, refined + reach + 1)

        def checked() -> list[tuple[int, Verdict]]:
            return [(m, v) for m, v in seen.items() if m in window or m in near]

        gap = self.params.refine_radius
        if not (verdict.accepted and verdict.translation_direction is not None):
            return bracketed_match(checked(), refined, verdict, gap)
        found = crossing(checked(), refined, gap)
        if found is not None and found.after - found.before > 1:
            self._check_frames(query, range(found.before + 1, found.after), seen)
        frame, result = bracketed_match(checked(), refined, verdict, gap)
        if not result.accepted:
            return frame, result
        found = crossing(checked(), refined, gap)
        assert found is not None  # an accepted bracketing has a crossing
        if not self._crossing_holds(query, found, seen, step, database_size):
            return frame, dataclasses.replace(result, accepted=False, reason=NOT_BRACKETED)
        return frame, result

    def _crossing_holds(
        self,
        query: FrameFeatures,
        found: Crossing,
        seen: dict[int, Verdict],
        step: int,
        database_size: int,
    ) -> bool:
        """Whether the crossing of an accepted bracketing stands two more tests. A side of one
        frame is checked against the frame a step beyond it (`lone_side_holds`): one flipped
        direction estimate at a run's end is not the place. With a pose topic, where the run
        has frames on the wrong side of its crossing, PnP from the crossing's two frames
        (`_position`) must not place the query over confirm_distance_m from both where it
        places it at all: signs can stay flipped over metres of a pass seen before far points
        from a metre aside, and the run's best split then lies metres past the place. A clean
        split is not placed: PnP costs several frame pairs' CPU, and clean splits are the
        common case."""
        for side, frames in ((-1, found.behind), (1, found.ahead)):
            if len(frames) != 1:
                continue
            beyond = frames[0] + side * step
            if beyond in range(database_size):
                self._check_frames(query, [beyond], seen)
            if not lone_side_holds(side, seen.get(beyond), confirmed=step > 1):
                return False
        if found.wrong and self._can_place():
            placed = [
                self._placed_distance(query, frame, self._window(frame, database_size), seen)
                for frame in (found.before, found.after)
            ]
            distances = [d for d in placed if d is not None]
            if distances and min(distances) > self.params.confirm_distance_m:
                return False
        return True

    def _hopeless(self, verdict: Verdict) -> bool:
        """Under half of min_inliers: no near copy of this frame is likely to pass."""
        return 2 * verdict.inliers < self.params.min_inliers

    def _check_frames(
        self, query: FrameFeatures, frames: Sequence[int], seen: dict[int, Verdict]
    ) -> None:
        """Verdicts of `query` against the frames not yet in `seen`, added to it."""
        new = [m for m in dict.fromkeys(frames) if m not in seen]  # each frame once
        if new:
            seen.update(self._verdicts(query, new, self._features(new)))

    def _reach(self, match: int, database_size: int) -> range:
        """The frames a candidate's refined match may be: its window widened by WALK_RADII *
        refine_radius on either side, for a walk (also over tracked checks, whose windows
        follow the previous offset), inside the sequence's database."""
        return _frames_around(match, (1 + WALK_RADII) * self.params.refine_radius, database_size)

    def _window(self, match: int, database_size: int) -> range:
        """Frames within +-refine_radius of `match` that belong to the sequence's database."""
        return _frames_around(match, self.params.refine_radius, database_size)

    def _verdicts(
        self, query: FrameFeatures, frames: Sequence[int], features: dict[int, FrameFeatures]
    ) -> list[tuple[int, Verdict]]:
        start = time.perf_counter()
        verdicts = []
        for m in frames:
            self._check_cancelled()
            verdict = verify_pair(query, features[m], self._fit_params, self.intrinsics)
            verdicts.append((m, verdict))
        self.stats.pairs_s += time.perf_counter() - start
        self.stats.pairs += len(verdicts)
        return verdicts

    def _check_cancelled(self) -> None:
        if self.cancel.is_set():
            raise Cancelled("verification stopped")

    def _features(self, indices: list[int]) -> dict[int, FrameFeatures]:
        """Features of these frames: from the cache, else the store, the rest loaded in one
        call."""
        found: dict[int, FrameFeatures] = {}
        missing = []
        for index in indices:
            cached = self._cache.get(index)
            if cached is None:
                cached = self._stored(index)
            if cached is None:
                missing.append(index)
            else:
                found[index] = cached
        if missing:
            found.update(self._load(missing))
        return found

    def _stored(self, index: int) -> FrameFeatures | None:
        if self.stored_features is None:
            return None
        start = time.perf_counter()
        features = self.stored_features(index)
        self.stats.load_s += time.perf_counter() - start
        if features is not None:
            self.stats.frames_stored += 1
            self._cache.put(index, features)
        return features

    def _load(self, indices: list[int]) -> dict[int, FrameFeatures]:
        loaded: dict[int, FrameFeatures] = {}
        start, extracting = time.perf_counter(), 0.0
        for index, gray in self.load_frames(indices):
            self._check_cancelled()
            extract_start = time.perf_counter()
            loaded[index] = extract_features(gray, self.params)
            extracting += time.perf_counter() - extract_start
            self._cache.put(index, loaded[index])
        self.stats.features_s += extracting
        self.stats.load_s += time.perf_counter() - start - extracting
        self.stats.frames_loaded += len(loaded)
        self.stats.peak_cache_bytes = max(self.stats.peak_cache_bytes, self._cache.bytes)
        absent = sorted(set(indices) - set(loaded))
        if absent:
            raise LookupError(f"the frame loader did not return frames {absent[:5]}")
        return loaded


def _without_points(check: PairCheck) -> PairCheck:
    if check.verdict.inlier_points is None:
        return check
    return dataclasses.replace(check, verdict=check.verdict.without_points())


def _frames_around(match: int, radius: int, database_size: int) -> range:
    """Frames within +-radius of `match` inside the database (`match` itself at least)."""
    return range(max(0, match - radius), min(max(database_size, match + 1), match + radius + 1))


def verify_in_threads(
    decisions: Sequence[SequenceDecision],
    open_loader: Callable[[], AbstractContextManager[FrameLoader]],
    params: VerificationParameters,
    intrinsics: Intrinsics | None = None,
    workers: int = 1,
    cache_bytes: int = DEFAULT_CACHE_BYTES,
    stored_features: StoredFeatures | None = None,
    camera_path: CameraPath | None = None,
    progress: Callable[[int], None] | None = None,
) -> tuple[list[VerifiedDecision], VerificationStats]:
    """`Verifier.verify` of each decision, on `workers` threads; results in decision order;
    `progress(decisions done)` as each is verified (from the verifying threads).

    Each thread opens its own frame loader and has its own Verifier, with an equal share of
    `cache_bytes`, and takes the next chain of CHAIN_DECISIONS decisions as it finishes one.
    OpenCV's matching and robust fits release the GIL, so the threads run on separate cores. A
    decision's checks depend on that decision and the one before it in its chain (`Hint`), and
    the chains are fixed, so the results are the same for any number of workers. Stats are
    summed over the threads.
    """
    workers = max(1, workers)
    results: list[VerifiedDecision | None] = [None] * len(decisions)
    stats = VerificationStats()
    lock, stop = threading.Lock(), threading.Event()
    chains = iter(range(0, len(decisions), CHAIN_DECISIONS))
    verified_count = [0]  # decisions verified, over the threads

    def work() -> None:
        with open_loader() as loader:
            verifier = Verifier(
                params,
                loader,
                intrinsics,
                cache_bytes // workers,
                cancel=stop,
                stored_features=stored_features,
                camera_path=camera_path,
            )
            try:
                while not stop.is_set():
                    with lock:
                        start = next(chains, None)
                    if start is None:
                        break
                    chain = decisions[start : start + CHAIN_DECISIONS]
                    for offset, verified in enumerate(verifier.verify_all(chain)):
                        results[start + offset] = verified
                        if progress is not None:
                            with lock:
                                verified_count[0] += 1
                                progress(verified_count[0])
            except Cancelled:
                pass  # stopped by another thread's error or the main thread's interrupt: that
                # is what gets raised, not this
            except BaseException:
                stop.set()  # the other threads stop at their next frame pair
                raise
            finally:
                with lock:
                    stats.add(verifier.stats)

    if workers == 1:
        work()
    else:
        with ThreadPoolExecutor(workers, thread_name_prefix="verify") as pool:
            try:
                futures = [pool.submit(work) for _ in range(workers)]
                for future in futures:
                    waiting.result(future)  # not a bare result(): it would not hear signals
            finally:
                # A KeyboardInterrupt (Ctrl-C, SIGTERM) lands here on the main thread: the
                # threads stop at their next frame pair, so neither the pool's shutdown nor
                # the interpreter's exit waits for the rest of the stage (minutes on a long
                # log). Also when it lands in submit(): a thread started there is not yet
                # one the pool's shutdown joins.
                stop.set()
    done = [result for result in results if result is not None]
    assert len(done) == len(decisions)
    return done, stats
