"""Frames again, by index: the verification stage re-reads the frames it needs from the log.

The detector keeps no images (memory linear in frames, small per frame), so after it has
decided, the frames a decision needs are read again from the log. A frame is identified by its
image message's log time and header stamp (recorded in `FrameTimes` on the first pass);
neighbouring frames are read in one ranged read, which an indexed MCAP or a bag answers by
seeking to the chunks that hold them.

Each ranged read costs a seek and the decompression of whole chunks, whatever few frames it is
for, and the stage asks for a few frames at a time (about three per checked candidate). So a
read takes `READ_AROUND` frames on each side too and keeps their still-encoded messages in a
cache bounded in bytes: the next requests, for nearby frames, are answered from it and only
decoded.
"""

from __future__ import annotations

import contextlib
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from ..annotations.records import NO_STAMP, FrameTimes
from ..closing import Closing
from ..sources import Log, opened
from ..sources.base import ImageMessage
from ..sources.image_folder import read_gray_file
from ..sources.image_header import DEFAULT_MAX_PIXELS
from ..sources.images import decode_gray
from ..verification.geometry import GrayImage

# Wanted frames closer than this are read in one range (reading a few unwanted messages is
# cheaper than a new seek and chunk decompression).
MAX_GAP_FRAMES = 32
# Frames read on each side of a wanted run, kept encoded for the requests that follow.
READ_AROUND = 32
# Bytes of encoded messages kept (JPEG 640x480: ~25 kB a frame, so ~1,300 frames).
MESSAGE_CACHE_BYTES = 32 * 2**20


def runs(indices: Sequence[int], max_gap: int = MAX_GAP_FRAMES) -> list[list[int]]:
    """Sorted indices grouped into runs whose neighbours are at most `max_gap` apart."""
    grouped: list[list[int]] = []
    for index in sorted(set(indices)):
        if grouped and index - grouped[-1][-1] <= max_gap:
            grouped[-1].append(index)
        else:
            grouped.append([index])
    return grouped


class LogFrameReader(Closing):
    """Decoded gray frames of one camera topic of a log, by frame index (a `FrameLoader`).

    Use as a context manager: given a path it keeps its own reader of the log open; given
    the run's open Source it reads through it (each read borrows a handle of its own, so
    threads may each have a LogFrameReader over one Source) and leaves it open.
    """

    def __init__(
        self,
        log: Log,
        topic: str,
        frame_times: FrameTimes,
        cache_bytes: int = MESSAGE_CACHE_BYTES,
        max_pixels: int = DEFAULT_MAX_PIXELS,
    ) -> None:
        self.topic, self.times = topic, frame_times
        self.max_pixels = max_pixels  # the run's cap: the frames it accepted decode again
        self.cache_bytes = cache_bytes
        self.reads = 0  # ranged reads of the log (for benchmarks)
        self._opened = contextlib.ExitStack()
        self._source = self._opened.enter_context(opened(log))
        self.path = self._source.path
        self._messages: OrderedDict[int, ImageMessage] = OrderedDict()
        self._bytes = 0

    def __call__(self, indices: Sequence[int]) -> Iterator[tuple[int, GrayImage]]:
        """(index, gray) for each wanted frame, in index order within each run.

        Raises LookupError when a frame is not found again (the log changed under us).
        """
        for run in runs(indices):
            missing = [index for index in run if index not in self._messages]
            cached = run if not missing else [i for i in run if i < missing[0]]
            for index in cached:
                self._messages.move_to_end(index)
                yield index, decode_gray(self._messages[index], self.max_pixels)
            if missing:
                yield from self._read(run[len(cached) :], missing[0])

    def _read(self, wanted: list[int], first_missing: int) -> Iterator[tuple[int, GrayImage]]:
        """The wanted frames, from one read of first_missing - READ_AROUND to
        wanted[-1] + READ_AROUND; every frame read is kept (the wanted ones are served from
        the read itself, so even a cache too small for them is correct)."""
        self.reads += 1
        first = max(0, first_missing - READ_AROUND)
        last = min(len(self.times) - 1, wanted[-1] + READ_AROUND)
        missing = set(wanted)
        start, end = self.times.log_time(first), self.times.log_time(last) + 1
        for message in self._source.image_messages(self.topic, start, end):
            for index in self._frames_of(message, first, last):
                self._keep(index, message)
                if index in missing:  # the read is in index (log-time) order
                    missing.discard(index)
                    yield index, decode_gray(message, self.max_pixels)
        if missing:
            raise LookupError(
                f"{self.path}: frames {sorted(missing)[:5]} of {self.topic} not found again"
            )

    def _frames_of(self, message: ImageMessage, first: int, last: int) -> list[int]:
        """The frames first..last recorded with this message's log time and header stamp, in
        order (found in the read's window of `FrameTimes`: no per-frame table is built, which
        on a long log would cost hundreds of bytes a frame in each reader)."""
        stamp = NO_STAMP if message.header_stamp_ns is None else message.header_stamp_ns
        window = slice(first, last + 1)
        same = (self.times.log_times_ns[window] == message.log_time_ns) & (
            self.times.header_stamps_ns[window] == stamp
        )
        return [first + int(offset) for offset in np.flatnonzero(same)]

    def _keep(self, index: int, message: ImageMessage) -> None:
        old = self._messages.pop(index, None)
        if old is not None:
            self._bytes -= len(old.data)
        self._messages[index] = message
        self._bytes += len(message.data)
        while self._bytes > self.cache_bytes and len(self._messages) > 1:
            _, evicted = self._messages.popitem(last=False)
            self._bytes -= len(evicted.data)

    def close(self) -> None:
        self._opened.close()


class FolderFrameReader:
    """Gray frames of an image folder by index: a Verifier's frame loader over a folder with
    no run around it (`evaluate --images` reads through its ImageFolderSource instead)."""

    def __init__(self, images: Sequence[Path], max_pixels: int = DEFAULT_MAX_PIXELS) -> None:
        self.images = list(images)
        self.max_pixels = max_pixels

    def __call__(self, indices: Sequence[int]) -> Iterator[tuple[int, GrayImage]]:
        for index in sorted(set(indices)):
            yield index, read_gray_file(self.images[index], self.max_pixels)
