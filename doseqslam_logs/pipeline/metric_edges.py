"""The metric stage of a run: a metric relative pose for each accepted pair.

After verification, each accepted pair (query, refined match) gets the best rung of
`verification.metric_pose` the log allows: the match's aligned depth image when the log has a
depth topic (`sources.depth.find_depth_topic`), else neighbours of the match with their
relative pose from an odometry topic (the first nav_msgs/Odometry, or `--odometry-topic`),
else the essential fit's rotation (none without intrinsics). The pose and, when a better rung
failed, why, go on the pair's LoopClosure message (`annotations.writer`).

Odometry poses are body poses of the camera (x forward, y left, z up) turned into optical
axes with `OPTICAL_TO_BODY`: the camera is assumed to look along the body's x axis at the
pose's origin (no tf is read). Neighbours of a match are chosen as `tools/reproduce/metric_edges.py`
found best: on each side, the nearest frame whose odometry is at least 1 m, and 2 m, away,
within NEIGHBOUR_REACH_S of the match. A pair left with the rotation only also gets the query's
neighbours, chosen the same way, for that rotation's consensus (read only for those pairs).

Features of the fit: SIFT on frames shrunk to the verification's working size
(`image_max_side`), a feature-poor one looked at again at twice that size as verification does
(`detail_below`; without it a 640x480 drive's fits lost a third of their PnP edges): the run's
ORB features miss the accuracy a loop edge needs, SIFT's meet it. A fit is costly (SIFT on up
to six frames: query, match, neighbours), so at high frame rates (the pairs of a sequence with
more than one frame per the verification's `query_interval_s`, as its query stride) at most one
pair per `METRIC_INTERVAL_S` of query time gets a metric fit: near-copy pairs add edges, not
information, to a pose graph, and a pose graph needs a loop edge every few tens of metres. The
others record no metric pose and say why (their essential-fit rotation stays on the message, as
for every accepted pair). At 2 Hz every accepted pair is fitted.

Memory is bounded whatever the log's length: the depth topic is read once, each image used
and dropped as it arrives (`stream_depth`); frames are re-read through `LogFrameReader` and
their features kept in a `FeatureCache` bounded in bytes. Pairs are fitted on `workers`
threads (SIFT and the fits release the GIL), at most a few ahead of the one the calling thread
waits for, and their poses come back in pair order: the same on any number of threads, each
fit seeding its own thread's generator. Ctrl-C and SIGTERM stop it within the fits running.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Final, Literal

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from .. import waiting
from ..annotations.records import FrameTimes
from ..errors import SourceError
from ..sources import Log, opened
from ..sources.base import Source
from ..sources.depth import DepthFrames, find_depth_topic, stream_depth
from ..sources.image_header import DEFAULT_MAX_PIXELS
from ..sources.poses import (
    PoseReader,
    PoseTrack,
    describe_skipped,
    read_poses,
    run_pose_topic,
)
from ..verification.geometry import FrameFeatures, Intrinsics, Verdict, extract_features
from ..verification.metric_pose import (
    OPTICAL_TO_BODY,
    MetricPose,
    MetricPoseParameters,
    OdometryNeighbour,
    metric_pose,
)
from ..verification.motion import CameraPath
from ..verification.params import VerificationParameters
from ..verification.position import BASELINES_M
from ..verification.stage import FeatureCache, VerifiedDecision, query_stride
from .reread import LogFrameReader

F64 = npt.NDArray[np.float64]
PairKey = tuple[int, int]  # (sequence id, pair number in its decision)

# The features of the metric fit (module docstring).
METRIC_FEATURES: Final = "sift"
# At a high frame rate, at most one metric fit per this much query time (module docstring).
METRIC_INTERVAL_S: Final = 20.0
# Neighbours of a match: the nearest frame on each side at least each baseline away by the
# odometry (the verification's position check picks the same), within this much time of the
# match (tools/reproduce/metric_edges.py: 8 frames at 2 Hz).
NEIGHBOUR_BASELINES_M: Final = BASELINES_M
NEIGHBOUR_REACH_S: Final = 4.0
# The odometry's error per metre of baseline (metres, degrees), on every axis: what the
# samples' and drifting drives' odometry showed against their ground truth.
ODOMETRY_SIGMA_PER_M: Final = (0.03, 0.15)
FEATURE_CACHE_BYTES: Final = 64 * 2**20

NO_INTRINSICS = "no intrinsics (no CameraInfo and no --intrinsics)"
NO_ROTATION = "no rotation from the essential fit"


@dataclass(frozen=True)
class AcceptedPair:
    key: PairKey
    query: int
    match: int  # the refined match
    query_time_ns: int
    verdict: Verdict
    high_rate: bool  # its sequence has more than one frame per query_interval_s


@dataclass
class MetricStats:
    """What the stage did and what it cost."""

    pairs: int = 0  # accepted pairs
    fitted: int = 0  # pairs given a metric fit (the others: not fitted at a high frame rate)
    methods: Counter[str] = field(default_factory=Counter)  # "" for none
    depth_topic: str = ""
    odometry_topic: str = ""
    odometry_skipped: dict[str, int] = field(default_factory=dict)  # by reason (read_poses)
    odometry_problem: str = ""  # the default pose topic could not be used (Odometry.problem)
    depth_messages: int = 0
    depth_skipped: dict[str, int] = field(default_factory=dict)
    frames_loaded: int = 0
    wall_s: float = 0.0

    def summary(self) -> str:
        """e.g. '50 pairs: 46 odometry_pnp, 4 rotation_only (odometry /odom)'."""
        counts = ", ".join(f"{n} {m or 'none'}" for m, n in sorted(self.methods.items()))
        sources = [f"depth {self.depth_topic}"] if self.depth_topic else []
        if self.odometry_topic:
            skipped = describe_skipped(self.odometry_skipped)
            sources.append(f"odometry {self.odometry_topic}{f', {skipped}' if skipped else ''}")
        sources += [self.odometry_problem] if self.odometry_problem else []
        where = f" ({', '.join(sources)})" if sources else ""
        return f"{self.pairs} pairs: {counts or 'none'}{where}"


@dataclass
class MetricEdges:
    """The stage's outcome: each accepted pair's pose, or why it has none, by PairKey."""

    poses: dict[PairKey, MetricPose | str]
    stats: MetricStats


@dataclass(frozen=True)
class OdometryFrames:
    """Camera poses (optical axes) from the odometry at every frame's time: X_world = R X + p;
    `valid` False for a frame outside the odometry's time range."""

    topic: str
    rotations: Rotation
    positions: F64
    valid: npt.NDArray[np.bool_]
    times_ns: npt.NDArray[np.int64]
    track: PoseTrack | None = None  # the poses as read (the trajectory drawn reuses them)

    def camera_path(self) -> CameraPath:
        """The positions and orientations at the frames, for verification's motion rule."""
        return CameraPath(self.topic, self.positions, self.valid, self.rotations.as_quat())

    def pose(self, frame: int) -> tuple[Rotation, F64]:
        """The camera pose (R, p) at the frame: X_world = R X + p."""
        return self.rotations[frame], self.positions[frame]

    def neighbours(self, match: int) -> list[int]:
        """On each side of `match`, the nearest frame at least each of NEIGHBOUR_BASELINES_M
        away, within NEIGHBOUR_REACH_S; none when the match has no odometry."""
        if not self.valid[match]:
            return []
        chosen: list[int] = []
        for side in (1, -1):
            frames = list(self._side(match, side))
            distance = np.linalg.norm(self.positions[frames] - self.positions[match], axis=1)
            for baseline in NEIGHBOUR_BASELINES_M:
                far = next((f for f, d in zip(frames, distance, strict=True) if d >= baseline), -1)
                if far >= 0 and far not in chosen:
                    chosen.append(far)
        return chosen

    def _side(self, match: int, side: int) -> Iterator[int]:
        reach_ns = round(NEIGHBOUR_REACH_S * 1e9)
        frame = match + side
        while 0 <= frame < len(self.valid) and self.valid[frame]:
            if abs(int(self.times_ns[frame]) - int(self.times_ns[match])) > reach_ns:
                return
            yield frame
            frame += side


def odometry_frames(track: PoseTrack, times_ns: npt.NDArray[np.int64]) -> OdometryFrames:
    """The odometry at each frame time, as camera poses in optical axes."""
    first, last = int(track.times_ns[0]), int(track.times_ns[-1])
    valid = (times_ns >= first) & (times_ns <= last)
    at = track.interpolate(np.clip(times_ns, first, last))
    optical = Rotation.from_matrix(OPTICAL_TO_BODY)
    rotations = Rotation.from_quat(at.quaternions_xyzw) * optical
    return OdometryFrames(track.topic, rotations, at.positions, valid, times_ns, track)


def odometry_covariance(translation: F64) -> F64:
    """ODOMETRY_SIGMA_PER_M over a baseline: the error grows with the distance."""
    distance = float(np.linalg.norm(translation))
    metres, degrees = ODOMETRY_SIGMA_PER_M
    sigmas = [metres * distance] * 3 + [math.radians(degrees) * distance] * 3
    return np.diag(np.square(np.maximum(sigmas, 1e-6)))


def accepted_pairs(
    decisions: Mapping[int, VerifiedDecision],
    frame_times: FrameTimes,
    time_source: str,
    query_interval_s: float,
) -> list[AcceptedPair]:
    """The run's accepted pairs, in sequence and pair order."""
    times = frame_times.detector_times_ns(time_source)
    pairs = []
    for sequence_id, verified in sorted(decisions.items()):
        high_rate = query_stride(verified.decision, query_interval_s) > 1
        for z, check in enumerate(verified.checks):
            if check.accepted:
                query, match = check.candidate.query_index, check.refined_match_index
                at = int(times[query])
                pair = AcceptedPair((sequence_id, z), query, match, at, check.verdict, high_rate)
                pairs.append(pair)
    return pairs


def thinned(pairs: Sequence[AcceptedPair], interval_s: float) -> tuple[list[AcceptedPair], str]:
    """The pairs to fit: every pair of a sequence at a low frame rate; of the high-rate ones,
    the first and then each at least `interval_s` of query time after the last fitted one
    (over the whole run: the cost is then bounded by the log's duration); and the reason the
    others record."""
    interval_ns = round(interval_s * 1e9)
    last: int | None = None
    chosen = []
    for pair in pairs:
        if not pair.high_rate:
            chosen.append(pair)
        elif last is None or pair.query_time_ns - last >= interval_ns:
            last = pair.query_time_ns
            chosen.append(pair)
    reason = f"not fitted: at a high frame rate, one metric fit per {interval_s:g} s of query time"
    return chosen, reason


class _Features:
    """Metric-fit features of frames by index, re-read from the log and cached in bytes.

    Called from several threads: the reader and the cache are used under a lock, the
    extraction (most of the cost) outside it. Two threads wanting the same new frame may both
    extract it: the same features, a little work twice.
    """

    def __init__(self, reader: LogFrameReader, params: VerificationParameters) -> None:
        self.reader, self.params = reader, params
        self.cache = FeatureCache(FEATURE_CACHE_BYTES)
        self.loaded = 0
        self.shape: tuple[int, ...] | None = None  # (height, width) of the frames decoded
        self.lock = threading.Lock()

    def __call__(self, indices: Sequence[int]) -> list[FrameFeatures]:
        with self.lock:  # what is cached now is held here: another thread's puts may evict it
            found = {i: f for i in set(indices) if (f := self.cache.get(i)) is not None}
            decoded = list(self.reader(sorted(set(indices) - found.keys())))
            if decoded:
                self.shape = decoded[-1][1].shape
        extracted = {index: extract_features(gray, self.params) for index, gray in decoded}
        with self.lock:
            for index, features in extracted.items():
                self.cache.put(index, features)
            self.loaded += len(extracted)
        found.update(extracted)
        return [found[i] for i in indices]


@dataclass
class _Fitter:
    """Fits one pair at a time (the rungs its inputs allow)."""

    features: _Features
    intrinsics: Intrinsics
    odometry: OdometryFrames | None
    # A pair's reason when there is no odometry (Odometry.missing_reason).
    no_odometry: str = "odometry_pnp: no odometry topic"
    params: MetricPoseParameters = field(default_factory=MetricPoseParameters)

    def fit(
        self, pair: AcceptedPair, depth: npt.NDArray[np.float32] | None, no_depth: str
    ) -> MetricPose | str:
        near = [] if self.odometry is None else self.odometry.neighbours(pair.match)
        query, match, *others = self.features([pair.query, pair.match, *near])
        if depth is not None and depth.shape != self.features.shape:
            # Not registered to the camera's pixels (REP 118 aligns them): no depth rung.
            sizes = f"{_size(depth.shape)}, the camera's {_size(self.features.shape)}"
            no_depth = f"depth_pnp: depth image {sizes}"
            depth = None
        neighbours = [self._neighbour(pair.match, n, f) for n, f in zip(near, others, strict=True)]
        verification = self.features.params
        pose = metric_pose(
            query,
            match,
            pair.verdict,
            self.intrinsics,
            verification,
            self.params,
            depth=depth,
            neighbours=neighbours,
            query_neighbours=lambda: self._neighbours(pair.query),
        )
        if pose is None:
            return NO_ROTATION
        # Say why the better rungs were not even tried (the core names those that failed).
        missing = [no_depth] if depth is None and pose.method != "depth_pnp" else []
        if not neighbours and pose.method == "rotation_only":
            missing.append(self._no_odometry())
        reasons = [r for r in [*missing, *pose.reason.split("; ")] if r]
        return dataclasses.replace(pose, reason="; ".join(sorted(reasons, key=_rung)))

    def _neighbours(self, frame: int) -> list[OdometryNeighbour]:
        """Frames near `frame` with their odometry relative to it (none without odometry)."""
        near = [] if self.odometry is None else self.odometry.neighbours(frame)
        features = self.features(near)
        return [self._neighbour(frame, n, f) for n, f in zip(near, features, strict=True)]

    def _neighbour(self, match: int, neighbour: int, features: FrameFeatures) -> OdometryNeighbour:
        assert self.odometry is not None
        poses = self.odometry.pose(match), self.odometry.pose(neighbour)
        return OdometryNeighbour.between(features, *poses, odometry_covariance)

    def _no_odometry(self) -> str:
        if self.odometry is None:
            return self.no_odometry
        return "odometry_pnp: no odometry at the match"


def metric_edges(
    log: Log,
    image_topic: str,
    frame_times: FrameTimes,
    decisions: Mapping[int, VerifiedDecision],
    intrinsics: Intrinsics | None,
    verification: VerificationParameters,
    *,
    time_source: str = "header",
    odometry_topic: str | None = None,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    interval_s: float = METRIC_INTERVAL_S,
    progress: Callable[[int, int], None] | None = None,
    workers: int = 2,
    odometry: Odometry | Literal["read"] = "read",
    no_intrinsics: str = NO_INTRINSICS,
) -> MetricEdges:
    """The metric pose of every accepted pair (module docstring), fitted on `workers` threads.
    `log`: the run's open Source (or a path, opened here); `odometry_topic`: None the log's
    default pose topic (`default_pose_topic`), "" none; `odometry`: the odometry at the
    frames when the run has read it already (`read_odometry`), else "read" here;
    `no_intrinsics`: each pair's reason when `intrinsics` is None; `progress(fits done, fits)`
    after each fit.

    Raises SourceError when the log cannot be read again.
    """
    start = time.perf_counter()
    pairs = accepted_pairs(decisions, frame_times, time_source, verification.query_interval_s)
    stats = MetricStats(pairs=len(pairs))
    if intrinsics is None or not pairs:
        poses: dict[PairKey, MetricPose | str] = {p.key: no_intrinsics for p in pairs}
        return _finished(MetricEdges(poses, stats), start)
    chosen, not_fitted = thinned(pairs, interval_s)
    poses = {p.key: not_fitted for p in pairs}
    stats.fitted = len(chosen)
    with opened(log) as source:
        if odometry == "read":
            odometry = read_odometry(source, frame_times, time_source, odometry_topic)
        frames, stats.odometry_problem = odometry.frames, odometry.problem
        stats.odometry_topic = "" if frames is None else frames.topic
        if frames is not None and frames.track is not None:
            stats.odometry_skipped = dict(frames.track.skipped)
        params = dataclasses.replace(verification, feature_detector=METRIC_FEATURES)
        with LogFrameReader(source, image_topic, frame_times, max_pixels=max_pixels) as reader:
            fitter = _Fitter(_Features(reader, params), intrinsics, frames, odometry.missing_reason)
            fits = _fit_all(source, image_topic, chosen, fitter, stats)
            for done, (key, pose) in enumerate(_in_threads(fits, workers)):
                poses[key] = pose
                if progress is not None:
                    progress(done + 1, len(chosen))
            stats.frames_loaded = fitter.features.loaded
    return _finished(MetricEdges(poses, stats), start)


def _finished(edges: MetricEdges, start: float) -> MetricEdges:
    edges.stats.methods = Counter(
        p.method if isinstance(p, MetricPose) else "" for p in edges.poses.values()
    )
    edges.stats.wall_s = time.perf_counter() - start
    return edges


@dataclass(frozen=True)
class Odometry:
    """What a run found for its odometry: the frames' poses, or why there are none."""

    frames: OdometryFrames | None
    problem: str = ""  # the default pose topic that could not be used, and why

    @property
    def missing_reason(self) -> str:
        """A pair's reason for fitting without odometry."""
        return f"odometry_pnp: {self.problem or 'no odometry topic'}"


def read_odometry(
    log: Log,
    frame_times: FrameTimes,
    time_source: str,
    asked: str | None,
    collected: PoseReader | None = None,
) -> Odometry:
    """The odometry at the frames: `asked` (raises SourceError when it cannot be read), else the
    log's default pose topic (`default_pose_topic`; when there is none or it cannot be read,
    the run goes on with the other rungs and `problem` says why), "" none. `collected`: that
    topic as the replay's pass read it (None: read here). Its PoseTrack is kept (`track`) for
    the trajectory the visualization draws."""
    with opened(log) as source:
        topic = run_pose_topic(source, asked)
        if not topic:
            return Odometry(None)
        try:
            if collected is not None and collected.topic == topic:
                track = collected.track()
            else:
                track = read_poses(source, topic)
        except SourceError as exc:
            if asked is not None:
                raise
            return Odometry(None, f"odometry {topic} unusable ({_after_path(str(exc), source)})")
    return Odometry(odometry_frames(track, frame_times.detector_times_ns(time_source)))


def _after_path(message: str, source: Source) -> str:
    """A SourceError's text without its leading "PATH: " (the pair is in that log already)."""
    prefix = f"{source.path}: "
    return message[len(prefix) :] if message.startswith(prefix) else message


_Fit = Callable[[], "MetricPose | str"]


def _in_threads(
    fits: Iterator[tuple[PairKey, _Fit]], workers: int
) -> Iterator[tuple[PairKey, MetricPose | str]]:
    """Each fit's result, in the order of `fits`, run on `workers` threads at most 2 *
    `workers` ahead of the one yielded (bounded memory: a fit holds its frames' features)."""
    if workers <= 1:
        yield from ((key, fit()) for key, fit in fits)
        return
    with ThreadPoolExecutor(workers, thread_name_prefix="metric") as pool:
        pending: deque[tuple[PairKey, Future[MetricPose | str]]] = deque()
        try:
            for key, fit in fits:
                pending.append((key, pool.submit(fit)))
                if len(pending) > 2 * workers:
                    done_key, future = pending.popleft()
                    yield done_key, waiting.result(future)  # hears Ctrl-C while it waits
            while pending:
                done_key, future = pending.popleft()
                yield done_key, waiting.result(future)
        finally:  # interrupted or failed: the fits not started are dropped, not run
            for _, future in pending:
                future.cancel()


def _fit_all(
    source: Source,
    image_topic: str,
    pairs: Sequence[AcceptedPair],
    fitter: _Fitter,
    stats: MetricStats,
) -> Iterator[tuple[PairKey, _Fit]]:
    """Each pair's fit, to run: with depth, as the match's depth image arrives (one pass over
    the depth topic), then the pairs whose match had none; else in pair order."""
    depth_topic = find_depth_topic(source, image_topic)
    if depth_topic is None:
        for pair in pairs:
            yield (
                pair.key,
                functools.partial(fitter.fit, pair, None, "depth_pnp: no depth topic"),
            )
        return
    stats.depth_topic = depth_topic
    by_stamp: dict[int, list[AcceptedPair]] = {}
    stamps = fitter.features.reader.times
    for pair in pairs:
        by_stamp.setdefault(_stamp(stamps, pair.match), []).append(pair)
    found = DepthFrames(depth_topic)
    try:
        for stamp, image in stream_depth(source, depth_topic, by_stamp, found):
            for pair in by_stamp.pop(stamp):
                yield pair.key, functools.partial(fitter.fit, pair, image.metres, "")
    finally:
        stats.depth_messages, stats.depth_skipped = found.messages, found.skipped
    no_depth = "depth_pnp: no depth image at the match"
    for left in by_stamp.values():
        for pair in left:
            yield pair.key, functools.partial(fitter.fit, pair, None, no_depth)


def _rung(reason: str) -> int:
    """A reason's place in the ladder ("depth_pnp: ..." first), for their order."""
    return 0 if reason.startswith("depth_pnp") else 1


def _size(shape: tuple[int, ...] | None) -> str:
    return "?" if shape is None else f"{shape[1]}x{shape[0]}"


def _stamp(times: FrameTimes, index: int) -> int:
    """The frame's header stamp (its log time without one), as depth images are stamped."""
    stamp = times.stamp(index)
    return stamp if stamp else times.log_time(index)
