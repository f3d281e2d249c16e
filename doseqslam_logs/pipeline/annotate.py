"""Annotate one log: source -> frames -> detector -> decisions -> annotated MCAP.

`annotate_log` is the library entry point; the `annotate` and `batch` commands call it.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import json
import os
import threading
import time
from array import array
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .. import __version__, waiting
from ..annotations.records import NO_STAMP, FrameTimes, RunMetadata
from ..detector import Parameters, make_detector
from ..errors import (
    DoseqslamError,
    ImageDecodeError,
    OutputError,
    SourceError,
    TimestampError,
    UsageError,
)
from ..sinks.atomic import check_output_path, scratch_file
from ..sinks.mcap_writer import (
    Annotations,
    WriteSummary,
    refuse_same_file,
    write_annotated_mcap,
)
from ..sinks.output_format import OutputFormat
from ..sinks.ros1_bag import mcap_to_bag
from ..sinks.visualization import FrameClock, Visualization, read_trajectory, visual_loops
from ..sources import Log, is_mcap_file, pick_image_topic
from ..sources.base import Promise, Source
from ..sources.camera_info import find_camera_info
from ..sources.digest import source_sha256
from ..sources.formats import LogFormat, format_of
from ..sources.frame import Frame
from ..sources.image_header import DEFAULT_MAX_PIXELS
from ..sources.images import decode_gray
from ..sources.mcap_source import McapSource
from ..sources.poses import PoseTrack, run_pose_topic
from ..sources.salvage import SalvageReport, salvage_mcap
from ..verification import (
    DEFAULT_VERIFICATION,
    InlierPoints,
    Intrinsics,
    VerificationParameters,
    VerificationStats,
    command_detector_parameters,
)
from ..verification.stage import DEFAULT_CACHE_BYTES, VerifiedDecision, verify_in_threads
from .decode import (
    SKIP_CORRUPT_CHUNK,
    SKIP_MISSING,
    FrameCounts,
    OnError,
    TimeSource,
    decoded_frames,
)
from .feature_health import FeatureHealth, check_feasibility, run_feature_health
from .feature_spill import FeatureSpill, feature_spill_for
from .frame_spill import spilled_frame_store
from .metric_edges import (
    NO_INTRINSICS,
    MetricEdges,
    Odometry,
    OdometryFrames,
    metric_edges,
    read_odometry,
)
from .replay import ReplayResult, replay
from .reread import LogFrameReader
from .side_topics import SideTopics
from .stages import StageCallback, StageObserver, observer_of

# Verification.intrinsics_source of a camera assumed where the CameraInfo's K is unusable.
ASSUMED = "assumed"


@dataclass(frozen=True)
class AnnotateOptions:
    """Everything about a run except the detector parameters."""

    topic: str | None = None
    time_source: TimeSource = "header"
    start_ns: int | None = None
    end_ns: int | None = None
    on_error: OnError = "skip"
    sidecar: bool = False
    # MCAP input: first copy every readable record into a clean temporary MCAP beside the
    # output (see sources.salvage) and annotate that: a truncated or corrupt file then gives
    # what it still holds instead of an error. Other inputs: no effect.
    recover: bool = False
    # Threads that prepare frames (frame vectors, features) ahead of the detector, and that
    # verify the candidates after it; the output does not depend on it.
    workers: int = 2
    # Geometric verification of the candidate pairs, on by default as in the `annotate`
    # command (None: off, the paper's decision, `annotate --no-verify`).
    verification: VerificationParameters | None = DEFAULT_VERIFICATION
    # Intrinsics for the essential matrix; None: the log's CameraInfo when it has one.
    intrinsics: Intrinsics | None = None
    # Memory for cached per-frame verification features (evicted frames are re-read), shared
    # by the verification threads.
    verification_cache_bytes: int = DEFAULT_CACHE_BYTES
    # An image whose header claims more pixels is skipped ("too large") before it is decoded,
    # so that a decompression bomb cannot take the machine's memory.
    max_pixels: int = DEFAULT_MAX_PIXELS
    # The visualization channels (match images, image texts, 3-D lines; sinks.visualization),
    # False: `--no-visualization`, the output without them. Never in a sidecar.
    visualization: bool = True
    # The output's chunks: compression and size (`--compression`, `--chunk-size`).
    output_format: OutputFormat = field(default_factory=OutputFormat)
    # With verification: the pose topic whose odometry gives the motion rule its evidence and
    # accepted pairs a metric pose (pipeline.metric_edges); None the log's default pose topic
    # (sources.poses.default_pose_topic: its first nav_msgs/Odometry topic, else its first
    # topic of another pose type), "" none (`--odometry-topic none`).
    odometry_topic: str | None = None


@dataclass(frozen=True)
class AnnotateResult:
    input_path: Path
    output_path: Path
    topic: str
    replay: ReplayResult
    counts: FrameCounts
    written: WriteSummary
    source_sha256: str
    recovery: SalvageReport | None = None  # what --recover found (MCAP inputs only)
    # What the log's index or statistics promised for the topic (None: nothing to compare).
    promise: Promise | None = None
    unattributed: int = 0  # messages of undeclared topics (a .db3's rows of unknown topic ids)
    verification: Verification | None = None  # None when it was off
    # Whether the frames held enough features to segment and verify (None: not measured).
    health: FeatureHealth | None = None

    @property
    def loop_closures(self) -> int:
        """Reported loop closures: the accepted pairs with verification, else every pair."""
        if self.verification is None:
            return self.replay.loop_closures
        return sum(v.accepted_pairs for v in self.verification.decisions.values())


@dataclass
class Verification:
    """What the verification stage decided for a run, and what it cost."""

    params: VerificationParameters
    intrinsics: Intrinsics | None
    # "--intrinsics", the CameraInfo topic, "assumed" (`Intrinsics.assumed`), or "" (none)
    intrinsics_source: str
    decisions: dict[int, VerifiedDecision]  # by sequence id
    stats: VerificationStats  # seconds summed over the verification threads
    wall_s: float = 0.0  # wall time of the whole stage
    metric: MetricEdges | None = None  # the accepted pairs' metric poses (the metric stage)
    # The motion rule's evidence: "odometry TOPIC", or "images" without a pose topic.
    motion_evidence: str = "images"
    # The CameraInfo messages whose K cannot be a camera, described ("" none).
    unusable_camera_info: str = ""

    @property
    def intrinsics_assumed(self) -> bool:
        """Whether the check used `Intrinsics.assumed` (the CameraInfo's K unusable)."""
        return self.intrinsics_source == ASSUMED

    @property
    def metric_intrinsics(self) -> Intrinsics | None:
        """The intrinsics metric poses may use: not an assumed camera's."""
        return None if self.intrinsics_assumed else self.intrinsics

    @property
    def no_intrinsics_reason(self) -> str:
        """A pair's metric reason when there are no intrinsics to fit with."""
        if not self.unusable_camera_info:
            return NO_INTRINSICS
        return f"no intrinsics ({self.unusable_camera_info}; no --intrinsics)"

    @property
    def motion_summary(self) -> str:
        """The evidence as the summary names it ("odometry /odom", "images", or both when
        the poses did not cover every pair)."""
        if self.motion_evidence == "images" or not self.stats.motion_by_images:
            return self.motion_evidence
        return f"{self.motion_evidence}; images where it has no pose"

    def recorded_in(self, metadata: RunMetadata) -> RunMetadata:
        """The run's metadata with the stage's parameters and outcome; the run reports the
        accepted pairs. Nothing that varies between runs."""
        k = self.intrinsics
        return replace(
            metadata,
            verification="on",
            verification_parameters_json=self.params.canonical_json(),
            verification_hash=self.params.hash,
            intrinsics_json="" if k is None else json.dumps([k.fx, k.fy, k.cx, k.cy]),
            intrinsics_source=self.intrinsics_source,
            verified_pairs=self.stats.candidates,
            accepted_pairs=self.stats.accepted,
            loop_closures=self.stats.accepted,
        )


def verify_decisions(
    log: Log,
    topic: str,
    result: ReplayResult,
    frame_times: FrameTimes,
    options: AnnotateOptions,
    features: FeatureSpill | None = None,
    odometry: OdometryFrames | None = None,
    frame_size: tuple[int, int] | None = None,
    progress: Callable[[int], None] | None = None,
    side: SideTopics | None = None,
) -> Verification | None:
    """The verification stage over a finished replay (None when it is off); `features`: the
    frames' features the replay extracted, if it did; `odometry`: the camera's poses at the
    frames, for the motion rule (None: it looks at the images); `frame_size`: (width, height)
    of the frames, for an assumed camera where the CameraInfo's K is unusable; `progress(
    decisions verified)`; `side`: the CameraInfo the replay's pass collected, if it did. `log`:
    the run's open Source (or a path)."""
    if options.verification is None:
        return None
    intrinsics, origin, unusable = options.intrinsics, "--intrinsics", ""
    if intrinsics is None:
        search = None if side is None else side.camera_info_search()
        if search is None:
            search = find_camera_info(log, topic)
        info, unusable = search.info, search.describe_unusable()
        if info is not None:
            intrinsics, origin = Intrinsics(info.fx, info.fy, info.cx, info.cy), info.topic
        elif unusable and frame_size is not None:
            # A K that is not a camera says the camera is a pinhole one of unknown focal
            # length: the fundamental matrix's extra freedom passes look-alikes.
            intrinsics, origin = Intrinsics.assumed(*frame_size), ASSUMED
        else:
            origin = ""
    start = time.perf_counter()
    checked, stats = verify_in_threads(
        result.decisions,
        lambda: LogFrameReader(log, topic, frame_times, max_pixels=options.max_pixels),
        options.verification,
        intrinsics,
        options.workers,
        options.verification_cache_bytes,
        None if features is None else features.get,
        None if odometry is None else odometry.camera_path(),
        progress,
    )
    verified = {item.decision.sequence_id: item for item in checked}
    wall_s = time.perf_counter() - start
    evidence = "images" if odometry is None else f"odometry {odometry.topic}"
    return Verification(
        options.verification,
        intrinsics,
        origin,
        verified,
        stats,
        wall_s,
        motion_evidence=evidence,
        unusable_camera_info=unusable,
    )


def visualization_of(
    annotations: Annotations,
    log: Log,
    topic: str,
    track: PoseTrack | None = None,
    pose_topic: str | None = None,
    time_source: str = "header",
    verification: Verification | None = None,
) -> Visualization:
    """What the visualization channels draw for these annotations of the log: the trajectory
    of `pose_topic`, else of its default pose topic (`track` when the run read it already),
    its pose at each frame, timed as the run timed its frames (`time_source`), and the inlier
    points of the pairs `verification` accepted."""
    loops = visual_loops(annotations.messages, inlier_points(verification))
    trajectory = read_trajectory(log, pose_topic, track)
    times = annotations.frame_times
    frames = None if times is None else FrameClock.of(times, time_source)
    return Visualization(topic, loops, trajectory, frames, verified=verification is not None)


def inlier_points(verification: Verification | None) -> dict[tuple[int, int], InlierPoints]:
    """The accepted pairs' inlier points (the verification keeps none for the others) by
    (query, refined match) frame index: at most MAX_INLIER_POINTS a reported pair."""
    if verification is None:
        return {}
    return {
        (check.candidate.query_index, check.refined_match_index): check.verdict.inlier_points
        for verified in verification.decisions.values()
        for check in verified.checks
        if check.accepted and check.verdict.inlier_points is not None
    }


def _hash_in_background(path: Path) -> Future[str]:
    """`source_sha256` on its own thread, beside the replay (seconds on an hour-long log)."""
    future: Future[str] = Future()

    def run() -> None:
        try:
            future.set_result(source_sha256(path))
        except BaseException as exc:  # handed to whoever asks for the result
            future.set_exception(exc)

    threading.Thread(target=run, name="sha256", daemon=True).start()
    return future


class _TimesRecorder:
    """Passes frames through and keeps each one's log time and header stamp by index."""

    def __init__(self) -> None:
        # Two int64 arrays, 16 B a frame (a list of tuples took about 130).
        self.log_times = array("q")
        self.stamps = array("q")  # NO_STAMP: no header
        self.first_shape: tuple[int, int] | None = None  # (width, height) of the first frame

    def __call__(self, frames: Iterable[Frame]) -> Iterator[Frame]:
        for frame in frames:
            if not self.log_times:
                self.first_shape = (frame.image.shape[1], frame.image.shape[0])
            self.log_times.append(frame.log_time_ns)
            stamp = frame.header_stamp_ns
            self.stamps.append(NO_STAMP if stamp is None else stamp)
            yield frame

    @property
    def first_size(self) -> str:
        """The first frame's size as WxH ("" before one), for the feature-poor warning."""
        return "" if self.first_shape is None else "{}x{}".format(*self.first_shape)

    def frame_times(self) -> FrameTimes:
        return FrameTimes(
            np.frombuffer(self.log_times, np.int64).copy(),
            np.frombuffer(self.stamps, np.int64).copy(),
        )


def printable_name(path: Path) -> str:
    """`path`'s name as UTF-8 text: bytes that are not UTF-8 (a name from another locale)
    are written as \\xNN, since MCAP strings must be UTF-8."""
    return os.fsencode(path.name).decode("utf-8", "backslashreplace")


def run_metadata(
    params: Parameters,
    result: ReplayResult,
    counts: FrameCounts,
    log: Path,
    sha256: str,
    topic: str,
    options: AnnotateOptions,
    recovery: SalvageReport | None = None,
    promise: Promise | None = None,
    unattributed: int = 0,
    odometry_topic: str = "",
) -> RunMetadata:
    """The `doseqslam` metadata record of a run without verification; `odometry_topic`: the
    run's pose topic (`run_pose_topic`)."""
    return RunMetadata(
        tool_version=__version__,
        method=params.method,
        parameters_json=params.canonical_json(),
        parameters_hash=params.hash,
        feature_detector=result.feature_detector,
        source_file=printable_name(log),
        source_sha256=sha256,
        image_topic=topic,
        odometry_topic=odometry_topic,
        time_source=options.time_source,
        start_ns=options.start_ns,
        end_ns=options.end_ns,
        on_error=options.on_error,
        image_messages=counts.messages,
        image_messages_promised=None if promise is None else promise.count,
        image_messages_promised_by="" if promise is None else promise.origin,
        unattributed_messages=unattributed,
        frames_used=counts.used,
        frames_skipped=counts.skipped_total,
        frames_skipped_by_reason_json=json.dumps(counts.skipped_by_reason()),
        first_skipped_by_reason_json=json.dumps(dict(sorted(counts.first_skip.items()))),
        log_time_fallbacks=counts.log_time_fallbacks,
        clock_jumps=counts.clock_jumps,
        first_clock_jump=counts.first_clock_jump,
        recovered_json="" if recovery is None else json.dumps(recovery.as_metadata()),
        verification="off",
        sequences=len(result.decisions),
        loop_closures=result.loop_closures,
    )


def promised(
    source: Source, log: Path, topic: str, options: AnnotateOptions, recovered: bool
) -> Promise | None:
    """What the log promises for the whole topic (None with a time range: the records count
    the whole log). After --recover, the damaged file's own summary, when it still has one:
    the copy's statistics count only what was copied."""
    if options.start_ns is not None or options.end_ns is not None:
        return None
    if not recovered:
        return source.promised_messages(topic)
    try:
        with McapSource(log) as original:
            return original.promised_messages(topic)
    except SourceError:
        return None


def count_missing(counts: FrameCounts, promise: Promise | None, log: Path, topic: str) -> None:
    """Messages promised but not in the data: counted as skipped, so that nothing is lost
    silently (found + missing = promised)."""
    if promise is None or promise.count <= counts.messages:
        return
    missing = promise.count - counts.messages
    counts.messages += missing
    detail = (
        f"{promise.origin} of {log.name} promises {promise.count} messages of {topic}; "
        f"the data holds {promise.count - missing}"
    )
    counts.skip(SKIP_MISSING, detail, missing)


def refuse_no_frame(
    counts: FrameCounts, recovery: SalvageReport | None, log: Path, topic: str, window: str
) -> None:
    """Raises when not one frame was used: SourceError when --recover found no complete image
    message, else ImageDecodeError (no image message in the `window` asked for, or what every
    skipped one was)."""
    lost = sum(counts.skipped[reason] for reason in (SKIP_CORRUPT_CHUNK, SKIP_MISSING))
    if recovery is not None and counts.used == 0 and counts.messages == lost:
        raise SourceError(
            f"{log}: nothing to recover on {topic}: no complete image message "
            f"({recovery.describe()})"
        )
    if counts.messages == 0:
        raise ImageDecodeError(
            f"{log}: no image message of {topic}{window}: nothing to annotate", "no image"
        )
    if counts.used == 0:
        reasons = ", ".join(f"{n} {why}" for why, n in counts.skipped_by_reason().items())
        first = next(iter(counts.first_skip.values()), "")
        raise ImageDecodeError(
            f"{log}: none of the {counts.messages} image messages of {topic} could be used "
            f"({reasons}); first: {first}"
        )


def annotate_log(
    log: str | Path,
    output: str | Path,
    params: Parameters | None = None,
    options: AnnotateOptions | None = None,
    progress: Callable[[int], None] | None = None,
    expected: Callable[[int | None], None] | None = None,
    stage: StageCallback | None = None,
    observer: StageObserver | None = None,
) -> AnnotateResult:
    """Replay the detector over the log's camera topic and write the annotated MCAP.

    The defaults are the `annotate` command's: `annotate_log(log, out)` writes the bytes that
    `doseqslam-logs annotate LOG -o OUT` writes (verification on, the detector's verified
    defaults); `annotate_log(log, out, Parameters(), AnnotateOptions(verification=None))` is
    `annotate --no-verify`. Parameters given are used as they are.

    `progress(frames done)` is called after each frame, `expected(image messages or None)`
    once the topic is known, `stage(name)` as each of STAGES begins ("verify" and "metric"
    only with verification on); `observer` hears the stages and their products. The input is
    only read; the output appears whole or not at all.

    Raises SourceError / NoCameraError (input), ImageDecodeError / TimestampError (a frame
    with on_error="fail"; ImageDecodeError also when not one image could be decoded),
    OutputError (output), ParameterError.
    """
    log, output = Path(log), Path(output)
    options = options or AnnotateOptions()
    if params is None:
        params = command_detector_parameters(options.verification)
    check_output_path(output)  # before the detector runs, not after
    if log.exists():
        refuse_same_file(log, output)
    if output.suffix == ".bag" and not options.sidecar:
        return _annotate_to_bag(log, output, params, options, progress, expected, stage, observer)
    callbacks = _Callbacks(progress, expected, observer_of(stage, observer))
    if not (options.recover and is_mcap_file(log)):
        return _annotate(log, log, output, params, options, callbacks, None)
    with scratch_file(output) as repaired:
        try:
            with repaired.open("wb") as stream:
                report = salvage_mcap(log, stream)
        except OSError as exc:
            raise OutputError(
                f"{output}: cannot write the recovered copy of {log} beside it: "
                f"{exc.strerror or exc}"
            ) from exc
        if report.messages == 0 and not report.lost_by_topic:
            raise SourceError(
                f"{log}: nothing to recover: not one complete message ({report.describe()})"
            )
        try:
            return _annotate(repaired, log, output, params, options, callbacks, report)
        except DoseqslamError as exc:
            # Messages about the recovered copy are about the log, for whoever reads them.
            exc.args = (str(exc).replace(str(repaired), str(log)), *exc.args[1:])
            raise


def _annotate_to_bag(
    log: Path,
    output: Path,
    params: Parameters,
    options: AnnotateOptions,
    progress: Callable[[int], None] | None,
    expected: Callable[[int | None], None] | None,
    stage: StageCallback | None,
    observer: StageObserver | None,
) -> AnnotateResult:
    """annotate_log into a ROS 1 .bag: the annotated MCAP beside it, then that as the .bag
    (`sinks.ros1_bag`), for a ROS 1 .bag input only (refused before the run otherwise)."""
    kind = format_of(log)
    if kind.name != "ros1-bag":
        raise UsageError(
            f"{output}: a .bag output needs a ROS 1 .bag input, and {log} is {kind.described}: "
            "write OUT.mcap (rosbags-convert turns a ROS 2 MCAP into a .bag)"
        )
    with scratch_file(output) as annotated:
        result = annotate_log(log, annotated, params, options, progress, expected, stage, observer)
        mcap_to_bag(annotated, output)
    return replace(result, output_path=output)


def _window(options: AnnotateOptions) -> str:
    """' in the log-time window ...' of -S/-E, or '' without them."""
    if options.start_ns is None and options.end_ns is None:
        return ""
    start = "its start" if options.start_ns is None else str(options.start_ns)
    end = "its end" if options.end_ns is None else str(options.end_ns)
    return f" with log time in [{start}, {end}) (-S/-E)"


@dataclass(frozen=True)
class _Callbacks:
    """What annotate_log's caller hears: frames done, image messages expected, stages."""

    progress: Callable[[int], None] | None
    expected: Callable[[int | None], None] | None
    observer: StageObserver


@dataclass(frozen=True)
class OpenLog:
    """A run's input: the log opened once, through which every stage reads."""

    source: Source  # reads the log, or the copy --recover made of it
    log_format: LogFormat | None  # None: not a log file (an image folder), never written
    path: Path  # the log as given, for messages and the metadata
    recovery: SalvageReport | None  # what --recover found (None: not recovered)


@dataclass
class Replayed:
    """What the replay stage leaves for the later ones."""

    topic: str
    result: ReplayResult
    promise: Promise | None
    unattributed: int
    counts: FrameCounts
    frame_times: FrameTimes
    first_shape: tuple[int, int] | None
    first_size: str
    side: SideTopics  # the pose topic and CameraInfo read in the replay's pass


@dataclass(frozen=True)
class Decided:
    """What a run decided before anything is written (`decide_log`)."""

    replayed: Replayed
    verification: Verification | None  # None when it was off
    odometry: Odometry  # the poses the motion rule used (none: it looked at the images)

    def feature_health(self, params: Parameters) -> FeatureHealth:
        """Whether the frames held enough features to segment and verify."""
        verification, result = self.verification, self.replayed.result
        decisions = None if verification is None else verification.decisions.values()
        checks = None if decisions is None else check_feasibility(decisions)
        accepted = result.loop_closures if verification is None else verification.stats.accepted
        return run_feature_health(params, result, checks, accepted, self.replayed.first_size)


class _Run:
    """One run's stages over its open log, in order: replay, verify, metric, write."""

    def __init__(
        self,
        log: OpenLog,
        output: Path,
        params: Parameters,
        options: AnnotateOptions,
        callbacks: _Callbacks,
    ) -> None:
        self.log, self.output, self.params, self.options = log, output, params, options
        self.callbacks = callbacks
        self.observer = callbacks.observer

    def decide(self) -> Decided:
        """The replay and the verification of its candidates: what the run decides."""
        options = self.options
        # verification's features, extracted as the replay decodes the frames
        with feature_spill_for(options.verification, self.params) as features:
            replayed = self.replay(features)
            odometry = Odometry(None)
            if options.verification is not None:
                self.observer.started("verify")
                odometry = read_odometry(
                    self.log.source,
                    replayed.frame_times,
                    options.time_source,
                    options.odometry_topic,
                    replayed.side.poses,
                )
            verification = self.verify(replayed, features, odometry)
        return Decided(replayed, verification, odometry)

    def annotate(self, digest: Future[str]) -> AnnotateResult:
        """Every stage: the decisions, their metric poses, and the annotated output."""
        decided = self.decide()
        replayed, verification, odometry = decided.replayed, decided.verification, decided.odometry
        if verification is not None:
            self.observer.started("metric")
            verification.metric = self.metric(replayed, verification, odometry)
            self.observer.finished("metric", verification.metric)
        sha256 = waiting.result(digest)
        annotations, health = self.annotations(decided, sha256)
        frames = odometry.frames
        track = replayed.side.pose_track() if frames is None else frames.track
        try:
            written = self.write(annotations, replayed.topic, track, verification)
        finally:
            annotations.close()
        log = self.log
        return AnnotateResult(
            log.path,
            self.output,
            replayed.topic,
            replayed.result,
            replayed.counts,
            written,
            sha256,
            log.recovery,
            replayed.promise,
            replayed.unattributed,
            verification,
            health,
        )

    def replay(self, features: FeatureSpill | None) -> Replayed:
        """The replay stage: the camera topic's frames through the detector (which also fills
        `features`, when given)."""
        log, options = self.log, self.options
        source, counts, recorder = log.source, FrameCounts(), _TimesRecorder()
        topic = pick_image_topic(source, options.topic)
        recovery = log.recovery
        if recovery is not None and recovery.lost_by_topic.get(topic):
            lost = recovery.lost_by_topic[topic]
            counts.messages += lost
            counts.skip(SKIP_CORRUPT_CHUNK, f"{lost} messages of {topic} in corrupt chunks", lost)
        promise = promised(source, log.path, topic, options, recovery is not None)
        unattributed = source.unattributed_messages()
        expected = self.callbacks.expected
        if expected is not None:
            expected(next((c.message_count for c in source.channels() if c.topic == topic), None))
        side = self._side_topics(topic)
        start_ns, end_ns = options.start_ns, options.end_ns
        if side.topics:
            messages = side.split(source.image_and_side_messages(topic, side.topics))
        else:
            messages = source.image_messages(topic, start_ns, end_ns)
        decode = functools.partial(decode_gray, max_pixels=options.max_pixels)
        frames = decoded_frames(messages, counts, options.time_source, options.on_error, decode)
        try:
            result = self._detect(recorder(frames), features)
        except (ImageDecodeError, TimestampError) as exc:  # on_error="fail": name the log
            exc.args = (f"{log.path}: {exc}", *exc.args[1:])
            raise
        self.observer.finished("replay", result)
        release_freed_memory()
        count_missing(counts, promise, log.path, topic)
        refuse_no_frame(counts, recovery, log.path, topic, _window(options))
        frame_times = recorder.frame_times()
        return Replayed(
            topic,
            result,
            promise,
            unattributed,
            counts,
            frame_times,
            recorder.first_shape,
            recorder.first_size,
            side,
        )

    def _side_topics(self, image_topic: str) -> SideTopics:
        """What the replay's pass reads besides the frames: the pose topic (for the motion
        rule, the metric poses and the trajectory drawn) and the CameraInfo (for the
        verification). A run over a time window reads them later, whole."""
        options = self.options
        if options.start_ns is not None or options.end_ns is not None:
            return SideTopics()
        verifies = options.verification is not None
        if verifies:
            pose_topic = options.odometry_topic
        else:  # the topic drawn: the one asked for, else (also for "none") the log's default
            draws = options.visualization and not options.sidecar
            pose_topic = (options.odometry_topic or None) if draws else ""
        camera_info = verifies and options.intrinsics is None
        return SideTopics.for_run(self.log.source, image_topic, pose_topic, camera_info)

    def _detect(self, frames: Iterable[Frame], features: FeatureSpill | None) -> ReplayResult:
        """The detector over the frames. The detector, whose place index and frame vectors
        grow with the log (hundreds of MB on a 4-hour log), is freed when this returns,
        before the later stages."""
        with spilled_frame_store(self.params) as store:
            detector = make_detector(self.params, store)
            self.observer.detector_made(detector)
            self.observer.started("replay")
            workers = self.options.workers
            return replay(frames, detector, self.callbacks.progress, workers, features)

    def verify(
        self, replayed: Replayed, features: FeatureSpill | None, odometry: Odometry
    ) -> Verification | None:
        """The verification stage (None when it is off)."""
        total = len(replayed.result.decisions)
        verification = verify_decisions(
            self.log.source,
            replayed.topic,
            replayed.result,
            replayed.frame_times,
            self.options,
            features,
            odometry.frames,
            replayed.first_shape,
            lambda done: self.observer.advanced("verify", done, total),
            replayed.side,
        )
        if verification is not None:
            self.observer.finished("verify", verification)
        return verification

    def metric(
        self, replayed: Replayed, verification: Verification, odometry: Odometry
    ) -> MetricEdges:
        """The metric stage: the accepted pairs' metric poses."""
        options = self.options
        return metric_edges(
            self.log.source,
            replayed.topic,
            replayed.frame_times,
            verification.decisions,
            verification.metric_intrinsics,
            verification.params,
            time_source=options.time_source,
            odometry_topic=options.odometry_topic,
            max_pixels=options.max_pixels,
            workers=options.workers,
            odometry=odometry,
            no_intrinsics=verification.no_intrinsics_reason,
            progress=lambda done, total: self.observer.advanced("metric", done, total),
        )

    def annotations(self, decided: Decided, sha256: str) -> tuple[Annotations, FeatureHealth]:
        """Our messages and metadata for the decisions (spooled: `close` when written)."""
        replayed, verification = decided.replayed, decided.verification
        params, options, log, result = self.params, self.options, self.log, replayed.result
        metadata = run_metadata(
            params,
            result,
            replayed.counts,
            log.path,
            sha256,
            replayed.topic,
            options,
            log.recovery,
            replayed.promise,
            replayed.unattributed,
            run_pose_topic(log.source, options.odometry_topic),
        )
        if verification is not None:
            metadata = verification.recorded_in(metadata)
        health = decided.feature_health(params)
        metadata = replace(metadata, feature_poor_json=health.metadata_json())
        metric = None if verification is None else verification.metric
        annotations = Annotations.from_decisions(
            result.decisions,
            replayed.frame_times,
            params.method,
            params.hash,
            metadata.to_entries(),
            None if verification is None else verification.decisions,
            None if metric is None else metric.poses,
            spool=True,
        )
        self.observer.finished("annotations", annotations)
        return annotations, health

    def write(
        self,
        annotations: Annotations,
        topic: str,
        track: PoseTrack | None,
        verification: Verification | None = None,
    ) -> WriteSummary:
        """The write stage: the visualization channels drawn, then the output written."""
        options, source = self.options, self.log.source
        if options.visualization and not options.sidecar:
            # The odometry asked for, if any (not "none": the log's default is still drawn).
            drawn = visualization_of(
                annotations,
                source,
                topic,
                track,
                options.odometry_topic or None,
                options.time_source,
                verification,
            )
            annotations = replace(annotations, visualization=drawn)
        self.observer.started("write")
        total = sum(c.message_count for c in source.channels())
        written = write_annotated_mcap(
            source.path,
            self.output,
            annotations,
            sidecar=options.sidecar,
            output_format=options.output_format,
            source=source,
            log_format=self.log.log_format,
            progress=lambda done: self.observer.advanced("write", done, total),
        )
        self.observer.finished("write", written)
        return written


def decide_log(
    log: OpenLog,
    params: Parameters | None = None,
    options: AnnotateOptions | None = None,
    progress: Callable[[int], None] | None = None,
    expected: Callable[[int | None], None] | None = None,
    stage: StageCallback | None = None,
    observer: StageObserver | None = None,
) -> Decided:
    """The replay and verify stages of `annotate_log` over an open log, nothing written: what
    `evaluate --images` scores. Defaults and callbacks as annotate_log's."""
    options = options or AnnotateOptions()
    if params is None:
        params = command_detector_parameters(options.verification)
    callbacks = _Callbacks(progress, expected, observer_of(stage, observer))
    return _Run(log, Path(), params, options, callbacks).decide()


def release_freed_memory() -> None:
    """Hand the heap pages freed so far back to the system: glibc keeps them resident
    otherwise, so the later stages' peak would stand on the replay's (freeing the detector
    alone does not lower resident memory). A no-op where the C library has no malloc_trim."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


def _annotate(
    read_path: Path,
    log: Path,
    output: Path,
    params: Parameters,
    options: AnnotateOptions,
    callbacks: _Callbacks,
    recovery: SalvageReport | None,
) -> AnnotateResult:
    """annotate_log on `read_path`: the log itself, or the copy that --recover made of it,
    opened once for the whole run: every stage reads through the one Source."""
    digest = _hash_in_background(log)
    log_format = format_of(read_path)
    with log_format.open(read_path) as source:
        run = _Run(OpenLog(source, log_format, log, recovery), output, params, options, callbacks)
        return run.annotate(digest)
