"""The difference matrix of an annotated run, rebuilt from the log's images for pictures.

The detector never keeps the whole N x N matrix; for a picture (paper Fig. 1) the frames are
read again from the log, every `stride`-th one so that the side stays at most `max_side`,
turned into the detector's frame vectors (`detector.preprocess`), compared by SAD
(`detector.difference`) and optionally contrast-enhanced along each row (`detector.enhance`,
over the run's epsilon kept frames: with a stride it spans stride x epsilon frames of the run;
a window shrunk to a few samples would leave only noise to see).
"""

from __future__ import annotations

import math
from collections import defaultdict, deque
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ..annotations.reader import AnnotatedLog
from ..annotations.records import NO_STAMP
from ..detector.difference import FrameStore, sad_rows
from ..detector.enhance import enhance
from ..detector.params import Parameters
from ..detector.preprocess import frame_vector
from ..errors import ImageDecodeError, SourceError, UsageError
from ..pipeline.decode import FrameCounts, TimeSource, decoded_frames
from ..sources import decode_gray, open_source
from .recorded_run import frame_count

MAX_SIDE = 1500
# Query rows compared per SAD call: bounds the temporaries for large sides.
ROW_BLOCK = 256

Gray = npt.NDArray[np.uint8]


@dataclass(frozen=True)
class DifferenceMatrix:
    """values[a, b]: difference between frames frame_indices[a] and frame_indices[b]."""

    values: npt.NDArray[np.float32]
    frame_indices: npt.NDArray[np.int64]  # frame k * stride of the run for row and column k
    stride: int
    frames: int  # frames of the run the matrix samples
    enhanced: bool
    window: int  # enhancement window in kept frames (0 when not enhanced)


def _wanted_frames(log: AnnotatedLog, max_side: int) -> tuple[npt.NDArray[np.int64], int]:
    frames = frame_count(log)
    if frames == 0:
        raise UsageError(f"{log.path}: the run used no frame: no difference matrix to draw")
    stride = max(1, math.ceil(frames / max_side))
    return np.arange(0, frames, stride, dtype=np.int64), stride


def _frames_by_times(
    content: Path, log: AnnotatedLog, wanted: npt.NDArray[np.int64]
) -> Iterator[tuple[int, Gray]]:
    """The wanted frames, found by their recorded log time and header stamp: only those
    messages are decoded. A message that does not decode was skipped by the run too."""
    assert log.frame_times is not None
    by_key: dict[tuple[int, int], deque[int]] = defaultdict(deque)
    for index in wanted.tolist():
        key = (log.frame_times.log_time(index), int(log.frame_times.header_stamps_ns[index]))
        by_key[key].append(index)
    topic, start, end = _run_range(log)
    with open_source(content) as source:
        for msg in source.image_messages(topic, start, end):
            stamp = NO_STAMP if msg.header_stamp_ns is None else msg.header_stamp_ns
            waiting = by_key.get((msg.log_time_ns, stamp))
            if not waiting:
                continue
            try:
                image = decode_gray(msg)
            except ImageDecodeError:
                continue
            yield waiting.popleft(), image


def _frames_by_decoding(
    content: Path, log: AnnotatedLog, wanted: npt.NDArray[np.int64]
) -> Iterator[tuple[int, Gray]]:
    """Logs without frame times: decode every frame as the run did and keep the wanted ones."""
    keep = set(wanted.tolist())
    topic, start, end = _run_range(log)
    time_source: TimeSource = "log" if log.metadata.time_source == "log" else "header"
    with open_source(content) as source:
        messages = source.image_messages(topic, start, end)
        for frame in decoded_frames(messages, FrameCounts(), time_source, "skip"):
            if frame.index in keep:
                yield frame.index, frame.image


def _run_range(log: AnnotatedLog) -> tuple[str, int | None, int | None]:
    topic = log.metadata.image_topic
    if not topic:
        raise SourceError(f"{log.path}: the metadata names no image topic")
    return topic, log.metadata.start_ns, log.metadata.end_ns


def _parameters(log: AnnotatedLog) -> Parameters:
    """The preprocessing parameters of the run (defaults for any the log lacks)."""
    recorded = log.parameters
    defaults = Parameters()
    names = ("image_width", "image_height", "patch_size", "difference_precision")
    values = {name: recorded.get(name, getattr(defaults, name)) for name in names}
    window = recorded.get("enhancement_window", defaults.enhancement_window)
    return defaults.replace(**values, enhancement_window=window)


def difference_matrix(
    content: str | Path, log: AnnotatedLog, max_side: int = MAX_SIDE, enhanced: bool = True
) -> DifferenceMatrix:
    """The (enhanced) difference matrix of the run in `log`, from the images in `content`
    (the annotated log itself when it is a full copy, else the original log).

    Raises:
        SourceError / NoCameraError: `content` cannot be read or lacks the image topic.
        UsageError: the run used no frame.
    """
    params = _parameters(log)
    wanted, stride = _wanted_frames(log, max_side)
    reader = _frames_by_times if log.frame_times is not None else _frames_by_decoding
    shape = (params.image_width, params.image_height, params.patch_size)
    vectors = {
        index: frame_vector(image, *shape) for index, image in reader(Path(content), log, wanted)
    }
    found = sorted(vectors)
    if len(found) != wanted.size:
        raise SourceError(
            f"{content}: found {len(found)} of the {wanted.size} frames to draw on "
            f"{log.metadata.image_topic}: not the log this run was annotated from?"
        )
    store = FrameStore(params.image_width * params.image_height, params.difference_precision)
    for index in found:
        store.append(vectors[index])
    n = len(store)
    values = np.empty((n, n), np.float32)
    for first in range(0, n, ROW_BLOCK):
        last = min(first + ROW_BLOCK, n) - 1
        values[first : last + 1] = sad_rows(store.rows(first, last), store, n)
    window = params.enhancement_window if enhanced else 0
    if enhanced:
        values = enhance(values, window)
    indices = np.asarray(found, np.int64)
    return DifferenceMatrix(values, indices, stride, frame_count(log), enhanced, window)
