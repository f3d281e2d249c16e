"""Frames again, by index: the verification stage re-reads the frames it needs from the log.

The detector keeps no images (memory linear in frames, small per frame), so after it has
decided, the frames a decision needs are read again from the log. A frame is identified by its
image message's log time and header stamp (recorded in `FrameTimes` on the first pass);
neighbouring frames are read in one ranged read, which an indexed MCAP or a bag answers by
seeking to the chunks that hold them.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import TracebackType

import cv2
import numpy as np

from .sinks.messages import NO_STAMP, FrameTimes
from .sources import open_source
from .sources.images import decode_gray
from .verification.geometry import GrayImage

# Wanted frames closer than this are read in one range (reading a few unwanted messages is
# cheaper than a new seek and chunk decompression).
MAX_GAP_FRAMES = 32


def runs(indices: Sequence[int], max_gap: int = MAX_GAP_FRAMES) -> list[list[int]]:
    """Sorted indices grouped into runs whose neighbours are at most `max_gap` apart."""
    grouped: list[list[int]] = []
    for index in sorted(set(indices)):
        if grouped and index - grouped[-1][-1] <= max_gap:
            grouped[-1].append(index)
        else:
            grouped.append([index])
    return grouped


class LogFrameReader:
    """Decoded gray frames of one camera topic of a log, by frame index (a `FrameLoader`).

    Use as a context manager: it keeps its own reader of the log open.
    """

    def __init__(self, path: str | Path, topic: str, frame_times: FrameTimes) -> None:
        self.path, self.topic, self.times = Path(path), topic, frame_times
        self._source = open_source(self.path)
        self._by_key: dict[tuple[int, int], list[int]] = defaultdict(list)
        log_times, stamps = frame_times.log_times_ns.tolist(), frame_times.header_stamps_ns.tolist()
        for index, key in enumerate(zip(log_times, stamps, strict=True)):
            self._by_key[key].append(index)

    def __call__(self, indices: Sequence[int]) -> Iterator[tuple[int, GrayImage]]:
        """(index, gray) for each wanted frame, in index order within each run.

        Raises LookupError when a frame is not found again (the log changed under us).
        """
        for run in runs(indices):
            yield from self._read_run(run)

    def _read_run(self, run: list[int]) -> Iterator[tuple[int, GrayImage]]:
        wanted = set(run)
        start = self.times.log_time(run[0])
        end = self.times.log_time(run[-1]) + 1
        for message in self._source.image_messages(self.topic, start, end):
            stamp = NO_STAMP if message.header_stamp_ns is None else message.header_stamp_ns
            hits = [i for i in self._by_key.get((message.log_time_ns, stamp), ()) if i in wanted]
            if not hits:
                continue
            gray = decode_gray(message)
            for index in hits:
                wanted.discard(index)
                yield index, gray
        if wanted:
            raise LookupError(
                f"{self.path}: frames {sorted(wanted)[:5]} of {self.topic} not found again"
            )

    def close(self) -> None:
        self._source.close()

    def __enter__(self) -> LogFrameReader:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()


class FolderFrameReader:
    """Gray frames of an image folder by index (the `evaluate --images` case)."""

    def __init__(self, images: Sequence[Path]) -> None:
        self.images = list(images)

    def __call__(self, indices: Sequence[int]) -> Iterator[tuple[int, GrayImage]]:
        for index in sorted(set(indices)):
            gray = cv2.imread(str(self.images[index]), cv2.IMREAD_GRAYSCALE)
            if gray is None:
                raise LookupError(f"{self.images[index]}: cannot decode image")
            yield index, np.ascontiguousarray(gray, dtype=np.uint8)
