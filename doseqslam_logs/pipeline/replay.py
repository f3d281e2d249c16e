"""The replay pipeline: frames -> detector -> decisions, with progress and counts.

Three kinds of work run at once on a log: reading and decoding its images (`frames`), the
per-frame `detector.prepare` (frame vector, features), and the sequential detector. The
detector runs on the calling thread; with workers > 1 a reader thread iterates `frames` and a
thread pool runs `prepare`, so the calling thread does nothing but the detector's own work.
OpenCV releases the GIL, so both cores work. The decisions do not depend on `workers`.

A later stage that needs something of every decoded frame (verification's features:
pipeline.feature_spill) hands the replay a `FrameSideWork`: its `compute` runs beside
`prepare` on the pool, its `keep` on the calling thread in frame order, so the frames are
decoded once; where its features are the detector's too, `prepare` takes them
(`detector_features`), so they are also extracted once.
"""

from __future__ import annotations

import queue
import threading
import time
from array import array
from collections.abc import Callable, Generator, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeVar

from .. import waiting
from ..detector import Detector, PreparedFrame, SequenceDecision
from ..sources.frame import Frame
from ..verification.geometry import GrayImage

if TYPE_CHECKING:
    from ..detector.segmentation import OrbFeatures

ProgressCallback = Callable[[int], None]

# Seconds a blocked queue operation waits before it checks whether the other side gave up.
_POLL_S = 0.1
# Prepared frames that may wait for the detector: a frame vector and up to max_features
# descriptors each (about 64 KB with SIFT), so 256 frames take about 16 MB. Enough for the
# pool to keep working through a long query (hundreds of frames at the end of an hour).
LOOKAHEAD_FRAMES = 256


@dataclass
class ReplayResult:
    """Every decision of a run, in the order the detector made them, and what it cost."""

    decisions: list[SequenceDecision] = field(default_factory=list)
    frames: int = 0
    wall_time_s: float = 0.0
    feature_detector: str = ""
    peak_detector_bytes: int = 0
    # Seconds per detector stage (`StageTimes`: preprocess and features summed over the
    # prepare threads, the rest on the detector's thread), plus "wait": the detector's thread
    # waiting for the next prepared frame (reading, decoding and preparing lag behind).
    stage_seconds: dict[str, float] = field(default_factory=dict)
    # Segmentation features of each frame, in order (-1: not counted; pipeline.feature_health).
    feature_counts: array[int] = field(default_factory=lambda: array("i"))

    @property
    def loop_closures(self) -> int:
        return sum(len(d.loop_closures) for d in self.decisions)

    @property
    def frames_per_second(self) -> float:
        return self.frames / self.wall_time_s if self.wall_time_s > 0 else 0.0


T = TypeVar("T")


class FrameSideWork(Protocol, Generic[T]):
    """Work on each decoded frame beside the detector's `prepare`."""

    def compute(self, gray: GrayImage) -> T:
        """On a prepare thread; a pure function of the frame."""
        ...

    def keep(self, index: int, result: T) -> None:
        """On the detector's thread, for frame 0, 1, ... in order."""
        ...

    def detector_features(self, result: T) -> OrbFeatures | None:
        """ORB features of `compute`'s result for `detector.prepare` to use instead of
        extracting its own (one extraction a frame), or None."""
        ...


class _NoSideWork:
    def compute(self, gray: GrayImage) -> None:
        return None

    def keep(self, index: int, result: None) -> None:
        pass

    def detector_features(self, result: None) -> None:
        return None


_Prepared = tuple[PreparedFrame, Any]  # detector.prepare, side.compute


class _End:
    """Queue marker: the frames ran out, or iterating them raised `error`."""

    def __init__(self, error: BaseException | None = None) -> None:
        self.error = error


_Item = tuple[int, "Future[_Prepared]"]  # (detector timestamp, prepare results)


class _Reader:
    """A thread that iterates the frames and submits `prepare` for each, in order.

    Two bounds keep memory flat: at most `in_flight` frames wait for or run `prepare` (they
    hold a whole decoded image), and at most `lookahead` prepared frames wait for the detector
    (they hold only a frame vector and features). The lookahead lets the prepare pool run
    through the long queries of the sequential detector instead of idling. An exception
    raised while iterating the frames is handed over and re-raised on the consumer's side
    where the frame would have come.
    """

    def __init__(
        self,
        frames: Iterable[Frame],
        prepare: Callable[[GrayImage], _Prepared],
        pool: ThreadPoolExecutor,
        in_flight: int,
        lookahead: int,
    ) -> None:
        self._frames = frames
        self._prepare = prepare
        self._pool = pool
        self._slots = threading.BoundedSemaphore(in_flight)
        self._queue: queue.Queue[_Item | _End] = queue.Queue(lookahead)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="frame-reader", daemon=True)
        self._thread.start()

    def _wait(self, attempt: Callable[[], bool]) -> bool:
        """Retries a timed-out blocking step; False when the consumer gave up meanwhile."""
        while not self._stop.is_set():
            if attempt():
                return True
        return False

    def _put(self, item: _Item | _End) -> bool:
        def attempt() -> bool:
            try:
                self._queue.put(item, timeout=_POLL_S)
            except queue.Full:
                return False
            return True

        return self._wait(attempt)

    def _submit(self, frame: Frame) -> Future[_Prepared] | None:
        if not self._wait(lambda: self._slots.acquire(timeout=_POLL_S)):
            return None
        future = self._pool.submit(self._prepare, frame.image)
        future.add_done_callback(lambda _: self._slots.release())
        return future

    def _run(self) -> None:
        iterator = iter(self._frames)
        try:
            for frame in iterator:
                future = self._submit(frame)
                if future is None or not self._put((frame.timestamp_ns, future)):
                    break
            else:
                self._put(_End())
        except BaseException as exc:  # handed to the consumer, which raises it
            self._put(_End(exc))
        finally:
            close = getattr(iterator, "close", None)
            if close is not None:
                close()  # a generator stopped early releases its files here, on its thread

    def items(self) -> Generator[_Item, None, None]:
        """The (timestamp, prepare future) pairs in order; raises what iterating raised."""
        try:
            while True:
                item = waiting.get(self._queue)  # hears Ctrl-C and SIGTERM while it waits
                if isinstance(item, _End):
                    if item.error is not None:
                        raise item.error
                    return
                yield item
        finally:
            self._stop.set()
            self._thread.join()


def prepared_frames(
    frames: Iterable[Frame],
    detector: Detector,
    workers: int,
    lookahead: int = LOOKAHEAD_FRAMES,
    side: FrameSideWork[Any] | None = None,
) -> Generator[tuple[int, _Prepared], None, None]:
    """(timestamp, (`detector.prepare`, `side.compute`) of the image) of each frame, in order.

    With workers > 1, a reader thread iterates (reads and decodes) the frames and a pool of
    `workers` threads prepares up to `lookahead` of them ahead of the consumer (see `_Reader`).
    """
    work: FrameSideWork[Any] = _NoSideWork() if side is None else side

    def prepare(gray: GrayImage) -> _Prepared:
        computed = work.compute(gray)
        return detector.prepare(gray, work.detector_features(computed)), computed

    if workers <= 1:
        for frame in frames:
            yield frame.timestamp_ns, prepare(frame.image)
        return
    with ThreadPoolExecutor(workers, thread_name_prefix="prepare") as pool:
        items = _Reader(frames, prepare, pool, 2 * workers, lookahead).items()
        try:
            for timestamp_ns, future in items:
                yield timestamp_ns, waiting.result(future)
        finally:
            items.close()  # stops the reader thread before the pool shuts down


def replay(
    frames: Iterable[Frame],
    detector: Detector,
    progress: ProgressCallback | None = None,
    workers: int = 1,
    side: FrameSideWork[Any] | None = None,
) -> ReplayResult:
    """Push every frame in order, then flush; `progress(frames_done)` after each frame;
    `side.keep(index, side.compute(frame))` for each frame, in order, when given.

    The decisions do not depend on `workers` (prepare is a pure function of the frame).
    """
    result = ReplayResult(feature_detector=detector.feature_detector)
    start = time.perf_counter()
    waited = 0.0
    stream = prepared_frames(frames, detector, workers, side=side)
    try:
        while True:
            asked = time.perf_counter()
            item = next(stream, None)
            waited += time.perf_counter() - asked
            if item is None:
                break
            timestamp_ns, (prepared, computed) = item
            if side is not None:
                side.keep(result.frames, computed)
            result.decisions += detector.push_prepared(timestamp_ns, prepared)
            result.feature_counts.append(prepared.feature_count)
            result.frames += 1
            if progress is not None:
                progress(result.frames)
    finally:
        stream.close()  # on an exception: stops the reader thread and the pool
    result.decisions += detector.finish()
    result.wall_time_s = time.perf_counter() - start
    result.peak_detector_bytes = detector.memory_bytes
    timings = getattr(detector, "timings", None)
    result.stage_seconds = {**getattr(timings, "seconds", {}), "wait": waited}
    return result
