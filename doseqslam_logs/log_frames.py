"""Image messages of a log -> decoded frames in timestamp order, every skipped one counted."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt

from .errors import ImageDecodeError, SourceError
from .frames import Frame
from .sources.base import ImageMessage
from .sources.images import decode_gray

TimeSource = Literal["header", "log"]
OnError = Literal["skip", "fail"]
Decoder = Callable[[ImageMessage], npt.NDArray[np.uint8]]

SKIP_DECODE = "undecodable image"
SKIP_BACKWARDS = "timestamp earlier than the previous frame"


@dataclass
class FrameCounts:
    """What happened to the image messages of a run."""

    messages: int = 0
    used: int = 0
    skipped: Counter[str] = field(default_factory=Counter)
    # Frames whose header stamp was missing or zero and that used their log time instead.
    log_time_fallbacks: int = 0
    first_skip: dict[str, str] = field(default_factory=dict)  # reason -> first example

    @property
    def skipped_total(self) -> int:
        return sum(self.skipped.values())

    def skip(self, reason: str, detail: str) -> None:
        self.skipped[reason] += 1
        self.first_skip.setdefault(reason, detail)


def frame_time(msg: ImageMessage, time_source: TimeSource, counts: FrameCounts) -> int:
    """The header stamp (camera time) or the log time; a zero or missing header stamp falls
    back to the log time, counted, since a stamp of 0 would put every frame at one instant."""
    if time_source == "log":
        return msg.log_time_ns
    if msg.header_stamp_ns:
        return msg.header_stamp_ns
    counts.log_time_fallbacks += 1
    return msg.log_time_ns


def decoded_frames(
    messages: Iterable[ImageMessage],
    counts: FrameCounts,
    time_source: TimeSource = "header",
    on_error: OnError = "skip",
    decode: Decoder = decode_gray,
) -> Iterator[Frame]:
    """Decode each message into a Frame whose timestamps never decrease.

    With on_error="skip", undecodable images and frames stamped earlier than the previous
    frame are skipped and counted by reason; with "fail" the first one raises.

    Raises ImageDecodeError or SourceError (on_error="fail" only).
    """
    previous: int | None = None
    for msg in messages:
        counts.messages += 1
        stamp = frame_time(msg, time_source, counts)
        if previous is not None and stamp < previous:
            detail = f"{msg.topic} at log time {msg.log_time_ns}: {stamp} < {previous}"
            if on_error == "fail":
                raise SourceError(f"{SKIP_BACKWARDS}: {detail}")
            counts.skip(SKIP_BACKWARDS, detail)
            continue
        try:
            image = decode(msg)
        except ImageDecodeError as exc:
            if on_error == "fail":
                raise
            counts.skip(SKIP_DECODE, str(exc))
            continue
        yield Frame(counts.used, stamp, msg.log_time_ns, msg.header_stamp_ns, image)
        counts.used += 1
        previous = stamp
