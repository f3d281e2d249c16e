"""Image messages of a log -> decoded frames in timestamp order, every skipped one counted.

Rules (docs/robustness.md has them per case):

* an image whose header claims more than the pixel cap is skipped under SKIP_TOO_LARGE, before
  it is decoded (or raises with on_error="fail");
* an undecodable image is skipped under SKIP_DECODE and counted by its problem ("empty image",
  "corrupt compressed image", "raw size mismatch", ...), or raises with on_error="fail";
* a message identical to the previous frame's (same log time, stamp and bytes: recorded twice)
  is skipped under SKIP_DUPLICATE; equal stamps with other pixels are kept;
* a frame stamped before the previous frame is skipped under SKIP_BACKWARDS, or raises
  TimestampError with on_error="fail";
* a log time later than sources.base.MAX_TIME_NS (2038: our messages could not carry it; such
  clocks are broken) is skipped under SKIP_LOG_TIME, or raises TimestampError with
  on_error="fail"; an invalid header stamp reaches here as a missing one (sources.images);
* with header time, a frame without a header stamp (missing, zero or invalid) is timed by the
  log time elapsed since the frame with the latest log time, on the camera clock: its own log
  time is off that clock by the recorder's latency, which would put it ahead of the next
  frames (then skipped as earlier) or behind the previous one (itself skipped). Before the
  first stamped frame there is no camera clock yet: such frames use their log time, and the
  first stamped frame is bridged to them as across a jump (not counted as one);
* with header time, a jump of the camera clock (the header stamps move more than
  CLOCK_JUMP_NS further or less than the log times do between two frames, e.g. an NTP step of
  hours) is bridged: from there on the stamps are shifted so that the detector's time moves as
  the log time did across the jump (from the frame with the latest log time), and the jump is
  counted. Skipping every later frame of a
  backward jump, or letting a forward jump make every earlier frame "old", would both defeat
  the detector; the log time is the one clock left to measure the gap with. Frame.timestamp_ns
  is the shifted time; Frame.header_stamp_ns stays what the message says.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt

from ..errors import ImageDecodeError, TimestampError
from ..sources.base import MAX_TIME_NS, ImageMessage
from ..sources.frame import Frame
from ..sources.images import TOO_LARGE, decode_gray

TimeSource = Literal["header", "log"]
OnError = Literal["skip", "fail"]
Decoder = Callable[[ImageMessage], npt.NDArray[np.uint8]]

SKIP_DECODE = "undecodable image"
SKIP_BACKWARDS = "timestamp earlier than the previous frame"
SKIP_DUPLICATE = "duplicate message"
SKIP_LOG_TIME = "log time out of range"
SKIP_CORRUPT_CHUNK = "lost in a corrupt chunk"  # annotate --recover: see annotate.py
# The log's Statistics record / bag index / metadata.yaml promises more messages of the topic
# than its data holds (a record lost without a trace in the data section).
SKIP_MISSING = "missing from the data"
SKIP_TOO_LARGE = TOO_LARGE  # the header claims more than --max-pixels: refused undecoded

# Header stamps that move this much more (or less) than the log times between two frames mean
# the camera clock jumped. Transport latency varies by milliseconds, a stalled recorder by
# seconds; a clock step (NTP, RTC reset, GPS time) by minutes to years.
CLOCK_JUMP_NS = 10 * 1_000_000_000


@dataclass
class FrameCounts:
    """What happened to the image messages of a run."""

    messages: int = 0
    used: int = 0
    skipped: Counter[str] = field(default_factory=Counter)
    # Undecodable images (skipped[SKIP_DECODE]) by problem: "empty image", "corrupt compressed
    # image", ... (`ImageDecodeError.problem`).
    undecodable: Counter[str] = field(default_factory=Counter)
    # Frames whose header stamp was missing or zero and that used their log time instead.
    log_time_fallbacks: int = 0
    clock_jumps: int = 0  # camera clock jumps bridged with the log time (header time only)
    first_skip: dict[str, str] = field(default_factory=dict)  # reason -> first example
    first_clock_jump: str = ""

    @property
    def skipped_total(self) -> int:
        return sum(self.skipped.values())

    def skip(self, reason: str, detail: str, count: int = 1) -> None:
        self.skipped[reason] += count
        self.first_skip.setdefault(reason, detail)

    def clock_jump(self, detail: str) -> None:
        self.clock_jumps += 1
        self.first_clock_jump = self.first_clock_jump or detail

    def skipped_by_reason(self) -> dict[str, int]:
        """Skipped frames by reason, undecodable ones by problem ("undecodable image: empty
        image"): the breakdown that summaries and the output's metadata show."""
        out: dict[str, int] = {}
        for reason, count in self.skipped.items():
            if reason == SKIP_DECODE and self.undecodable:
                for problem, n in self.undecodable.items():
                    out[f"{SKIP_DECODE}: {problem}"] = n
                rest = count - sum(self.undecodable.values())
                if rest > 0:
                    out[SKIP_DECODE] = rest
            else:
                out[reason] = count
        return dict(sorted(out.items()))


def frame_time(msg: ImageMessage, time_source: TimeSource, counts: FrameCounts) -> int:
    """The header stamp (camera time) or the log time; a zero or missing header stamp falls
    back to the log time, counted, since a stamp of 0 would put every frame at one instant."""
    if time_source == "log":
        return msg.log_time_ns
    if msg.header_stamp_ns:
        return msg.header_stamp_ns
    counts.log_time_fallbacks += 1
    return msg.log_time_ns


@dataclass
class _Previous:
    """The last frame handed on: its detector time, log time and identity."""

    time: int
    log_time: int
    header_stamp: int | None
    data: bytes


def _hours(ns: int) -> str:
    return f"{ns / 3.6e12:+.2f} h" if abs(ns) >= 360 * 10**9 else f"{ns / 1e9:+.1f} s"


def decoded_frames(
    messages: Iterable[ImageMessage],
    counts: FrameCounts,
    time_source: TimeSource = "header",
    on_error: OnError = "skip",
    decode: Decoder = decode_gray,
) -> Iterator[Frame]:
    """Decode each message into a Frame whose timestamps never decrease (module docstring).

    Raises ImageDecodeError or TimestampError (on_error="fail" only).
    """
    previous: _Previous | None = None
    anchor = (0, 0)  # (detector time, log time) of the used frame with the latest log time
    shift = 0  # added to the header stamps since the last camera clock jump
    stamped = False  # a frame with a header stamp was used: the camera clock is known
    for msg in messages:
        counts.messages += 1
        where = f"{msg.topic} at log time {msg.log_time_ns}"
        if msg.log_time_ns > MAX_TIME_NS:
            detail = f"{where}: later than {MAX_TIME_NS} (2038-01-19T03:14:07.999999999Z)"
            if on_error == "fail":
                raise TimestampError(f"{SKIP_LOG_TIME}: {detail}")
            counts.skip(SKIP_LOG_TIME, detail)
            continue
        stamp = frame_time(msg, time_source, counts) + shift
        if previous is not None:
            if (
                msg.log_time_ns == previous.log_time
                and msg.header_stamp_ns == previous.header_stamp
                and msg.data == previous.data
            ):
                counts.skip(SKIP_DUPLICATE, f"{where}: same stamp and bytes as the previous one")
                continue
            # Measured from the frame with the latest log time so far: a log time out of order
            # (an unindexed file beyond the reorder window) measures nothing.
            log_step = msg.log_time_ns - anchor[1]
            if time_source == "header" and not msg.header_stamp_ns and stamped:
                stamp = anchor[0] + log_step  # on the camera clock (module docstring)
            elif time_source == "header" and msg.header_stamp_ns and log_step >= 0:
                jump = (stamp - anchor[0]) - log_step
                if abs(jump) > CLOCK_JUMP_NS:
                    counts.clock_jump(
                        f"{where}: header stamps jump {_hours(jump)} against the log time"
                    )
                # The first stamped frame after frames timed by their log time alone: it
                # continues from them as across a jump, uncounted (the clock changes, not
                # the camera's).
                if abs(jump) > CLOCK_JUMP_NS or not stamped:
                    bridged = max(anchor[0] + log_step, previous.time)
                    shift, stamp = shift + bridged - stamp, bridged
            if stamp < previous.time:
                detail = f"{where}: {stamp} < {previous.time}"
                if on_error == "fail":
                    raise TimestampError(f"{SKIP_BACKWARDS}: {detail}")
                counts.skip(SKIP_BACKWARDS, detail)
                continue
        try:
            image = decode(msg)
        except ImageDecodeError as exc:
            if on_error == "fail":
                raise
            if exc.problem == TOO_LARGE:  # not damage: a size the run refuses to decode
                counts.skip(SKIP_TOO_LARGE, str(exc))
                continue
            counts.skip(SKIP_DECODE, str(exc))
            counts.undecodable[exc.problem] += 1
            continue
        yield Frame(counts.used, stamp, msg.log_time_ns, msg.header_stamp_ns, image)
        counts.used += 1
        previous = _Previous(stamp, msg.log_time_ns, msg.header_stamp_ns, msg.data)
        stamped = stamped or bool(msg.header_stamp_ns)
        if msg.log_time_ns >= anchor[1]:
            anchor = (stamp, msg.log_time_ns)
