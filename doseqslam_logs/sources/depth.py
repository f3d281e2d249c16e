"""Aligned depth images (REP 118): which topic holds a camera's depth, and the depth at its frames.

An RGB-D camera's ROS driver publishes, beside the colour image, a depth image registered to it
(same stamp, same size, same pinhole model): sensor_msgs/Image (Foxglove: RawImage) with
encoding 32FC1 (metres along the optical axis, NaN where there is no depth) or 16UC1
(millimetres, 0 where there is none). A metric loop constraint needs the 3-D point behind a
matched pixel; this module finds and reads those images, through `Source.messages` whatever
the container.

`find_depth_topic` picks, among the raw-image topics whose first message has a depth encoding,
the one sharing the longest topic prefix with the image topic (/camera/image/compressed ->
/camera/depth/image), as the camera's CameraInfo is picked (`camera_info`). `read_depth` reads
the depth nearest each wanted stamp in one pass, keeping at most one image per wanted stamp;
`stream_depth` hands each one on as soon as no later message can be nearer, so that a caller
that uses and drops them (annotate's metric stage) holds a few images at a time, whatever the
log's length.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Final

import numpy as np
import numpy.typing as npt

from ..errors import DepthTopicError, ImageDecodeError, SourceError
from .base import DecodedMessage, ImageMessage, Source
from .camera_info import shared_prefix
from .image_header import DEFAULT_MAX_PIXELS
from .images import (
    IMAGE_TYPES,
    UNDESERIALIZABLE,
    RecordInfo,
    check_pixel_cap,
    pixel_rows,
)

Metres = npt.NDArray[np.float32]

# Bytes per pixel of the depth encodings REP 118 names.
DEPTH_ENCODINGS: Final = {"32FC1": 4, "16UC1": 2}
RAW_IMAGE_TYPES: Final = frozenset(name for name, t in IMAGE_TYPES.items() if t.kind == "raw")
# RGB-D drivers stamp the depth with its colour frame's stamp; 10 ms also covers drivers that
# stamp the two a few milliseconds apart, and is far below any camera's frame interval.
DEFAULT_TOLERANCE_NS: Final = 10_000_000
# A depth topic must share at least the first name with the image topic ("", "camera").
_MIN_SHARED_PARTS: Final = 2

# Why a depth message near a wanted stamp was not used (`DepthFrames.skipped`); the pixel cap
# and the layout checks use the image decoder's words (TOO_LARGE, RAW_SIZE_MISMATCH, ...).
NOT_DEPTH = "not a depth encoding"
SIZE_MISMATCH = "size differs from the camera's"


@dataclass(frozen=True)
class DepthImage:
    """One depth image: metres along the optical axis, NaN where the sensor has no depth."""

    stamp_ns: int  # the message's header stamp (its log time when the stamp is unset)
    metres: Metres  # (height, width) float32, C-contiguous, writable


@dataclass
class DepthFrames:
    """What `read_depth` found: the depth nearest each wanted stamp, and what it skipped."""

    topic: str
    images: dict[int, DepthImage] = field(default_factory=dict)  # by wanted stamp
    messages: int = 0  # messages read
    skipped: dict[str, int] = field(default_factory=dict)  # problem -> messages
    first_problem: dict[str, str] = field(default_factory=dict)  # problem -> its first message

    def skip(self, error: ImageDecodeError) -> None:
        self.skipped[error.problem] = self.skipped.get(error.problem, 0) + 1
        self.first_problem.setdefault(error.problem, str(error))


def find_depth_topic(source: Source, image_topic: str, asked: str | None = None) -> str | None:
    """The depth topic of the camera of `image_topic`: `asked` when given (checked), else the
    raw-image topic with a depth encoding that shares the longest topic prefix with the image
    topic (at least its first name); None when the log has none.

    Raises:
        DepthTopicError: `asked` is not in the log, is not a raw image type, or its first
            message is not 32FC1 or 16UC1.
        SourceError: the log cannot be read (while checking `asked`).
    """
    channels = {c.topic: c.message_type for c in source.channels()}
    if asked is not None:
        _check_asked(source, asked, channels)
        return asked
    candidates = [
        topic
        for topic, message_type in channels.items()
        if topic != image_topic and is_depth_topic(source, topic, message_type)
    ]
    best = max(sorted(candidates), key=lambda t: shared_prefix(t, image_topic), default=None)
    if best is None or shared_prefix(best, image_topic) < _MIN_SHARED_PARTS:
        return None
    return best


def is_depth_topic(source: Source, topic: str, message_type: str) -> bool:
    """Whether a channel holds depth images (a raw image type whose first message has a depth
    encoding): such a topic is an RGB-D camera's range, never the camera the detector reads."""
    return _is_raw_image(message_type) and _first_is_depth(source, topic)


def _is_raw_image(message_type: str) -> bool:
    """A channel's type names (a topic may list several, comma-separated)."""
    return any(name in RAW_IMAGE_TYPES for name in message_type.split(", "))


def _check_asked(source: Source, topic: str, channels: dict[str, str]) -> None:
    if topic not in channels:
        raise DepthTopicError(f"{source.path}: no topic {topic!r} in the log")
    if not _is_raw_image(channels[topic]):
        raise DepthTopicError(
            f"{source.path}: {topic} carries {channels[topic]}, not depth images "
            "(sensor_msgs/Image or foxglove.RawImage with encoding 32FC1 or 16UC1)"
        )
    first = _first_message(source, topic)
    encoding = None if first is None else _encoding(first)
    if first is not None and encoding not in DEPTH_ENCODINGS:
        raise DepthTopicError(
            f"{source.path}: {topic} has images of encoding {encoding!r}, not depth "
            "(32FC1 metres or 16UC1 millimetres)"
        )


def _first_is_depth(source: Source, topic: str) -> bool:
    """Whether the topic's first message has a depth encoding; a topic that cannot be read is
    not taken (the search is best effort: another topic's damage must not stop a run)."""
    try:
        first = _first_message(source, topic)
    except SourceError:
        return False
    return first is not None and _encoding(first) in DEPTH_ENCODINGS


def _first_message(source: Source, topic: str) -> DecodedMessage | None:
    messages = source.messages(topic)
    try:
        return next(iter(messages), None)
    finally:
        close = getattr(messages, "close", None)
        if close is not None:
            close()  # a generator holds the file open until it is closed


def _encoding(decoded: DecodedMessage) -> str | None:
    encoding = getattr(decoded.message, "encoding", None)
    return None if encoding is None else str(encoding)


def read_depth(
    source: Source,
    topic: str,
    wanted_stamps_ns: Iterable[int],
    *,
    tolerance_ns: int = DEFAULT_TOLERANCE_NS,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    size: tuple[int, int] | None = None,
) -> DepthFrames:
    """The depth image nearest each wanted stamp, within `tolerance_ns`, in one pass over the
    topic. At most one image per wanted stamp is kept, so memory is bounded by the number of
    wanted stamps. A message near a wanted stamp that cannot be used is skipped and counted by
    its problem: not a depth encoding, more pixels claimed than `max_pixels` (refused before
    anything is allocated), width/height/step/data that do not fit together, a size other
    than `size` (width, height) when given.

    Raises SourceError when the log cannot be read (a message that does not deserialize ends
    the read, as for any topic).
    """
    wanted = np.unique(np.fromiter(wanted_stamps_ns, dtype=np.int64))
    found = DepthFrames(topic)
    for rec, decoded in _records(source, topic):
        found.messages += 1
        image = _image_message(decoded, rec)
        stamp = image.header_stamp_ns or rec.log_time_ns
        target = _nearest(wanted, stamp, tolerance_ns)
        if target is None:
            continue
        nearer = _nearer(found, found.images.get(target), target, image, stamp, max_pixels, size)
        if nearer is not None:
            found.images[target] = nearer
    return found


def stream_depth(
    source: Source,
    topic: str,
    wanted_stamps_ns: Iterable[int],
    found: DepthFrames,
    *,
    tolerance_ns: int = DEFAULT_TOLERANCE_NS,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    size: tuple[int, int] | None = None,
) -> Iterator[tuple[int, DepthImage]]:
    """(wanted stamp, its nearest depth image) in one pass over the topic, as `read_depth`
    chooses them, each yielded once a message stamped more than `tolerance_ns` after the wanted
    stamp has been read (or at the end): only the images still within the tolerance of a
    message are held. Messages are counted and skipped ones recorded in `found`, whose
    `images` stays empty. Assumes stamps ascend with log time within the tolerance (an image
    stamped further out of order than that is not a candidate any more).

    Raises SourceError as `read_depth`.
    """
    wanted = np.unique(np.fromiter(wanted_stamps_ns, dtype=np.int64))
    pending: dict[int, DepthImage] = {}
    done: set[int] = set()
    for rec, decoded in _records(source, topic):
        found.messages += 1
        image = _image_message(decoded, rec)
        stamp = image.header_stamp_ns or rec.log_time_ns
        for passed in sorted(t for t in pending if t + tolerance_ns < stamp):
            done.add(passed)
            yield passed, pending.pop(passed)
        target = _nearest(wanted, stamp, tolerance_ns)
        if target is None or target in done:
            continue
        nearer = _nearer(found, pending.get(target), target, image, stamp, max_pixels, size)
        if nearer is not None:
            pending[target] = nearer
    for target in sorted(pending):
        yield target, pending[target]


def _nearer(
    found: DepthFrames,
    kept: DepthImage | None,
    target: int,
    image: ImageMessage,
    stamp: int,
    max_pixels: int,
    size: tuple[int, int] | None,
) -> DepthImage | None:
    """`image` decoded, when it is nearer `target` than the image `kept` for it so far (ties
    keep the first); None when it is not, or when it cannot be used (skipped in `found`)."""
    if kept is not None and abs(kept.stamp_ns - target) <= abs(stamp - target):
        return None
    try:
        metres = depth_metres(image, max_pixels)
        _check_size(image, size)
    except ImageDecodeError as error:
        found.skip(error)
        return None
    return DepthImage(stamp, metres)


def _records(source: Source, topic: str) -> Iterator[tuple[RecordInfo, DecodedMessage]]:
    for decoded in source.messages(topic):
        yield RecordInfo(topic, decoded.log_time_ns), decoded


def _image_message(decoded: DecodedMessage, rec: RecordInfo) -> ImageMessage:
    """The message's image fields; one without them becomes an ImageMessage whose
    `decode_error` says so (skipped and counted when it would have been used)."""
    image_type = IMAGE_TYPES.get(decoded.message_type)
    problem = f"a {decoded.message_type} message, not an image"
    if image_type is not None and image_type.kind == "raw":
        try:
            return image_type.build(decoded.message, rec)
        except Exception as exc:  # any field may be missing or of the wrong type
            problem = f"cannot read the {decoded.message_type} fields ({exc})"
    return ImageMessage(
        topic=rec.topic,
        log_time_ns=rec.log_time_ns,
        header_stamp_ns=None,
        kind="raw",
        encoding="",
        width=0,
        height=0,
        step=0,
        is_bigendian=False,
        data=b"",
        decode_error=f"depth on {rec.topic} at log time {rec.log_time_ns}: {problem}",
    )


def _nearest(wanted: npt.NDArray[np.int64], stamp: int, tolerance_ns: int) -> int | None:
    """The wanted stamp nearest `stamp` (the earlier on a tie), if within the tolerance."""
    i = int(np.searchsorted(wanted, stamp))
    near = [int(wanted[j]) for j in (i - 1, i) if 0 <= j < len(wanted)]
    best = min(near, key=lambda w: abs(w - stamp), default=None)
    return best if best is not None and abs(best - stamp) <= tolerance_ns else None


def _check_size(image: ImageMessage, size: tuple[int, int] | None) -> None:
    if size is not None and (image.width, image.height) != size:
        raise ImageDecodeError(
            f"depth on {image.topic} at log time {image.log_time_ns}: "
            f"{image.width}x{image.height}, the camera's images are {size[0]}x{size[1]}",
            SIZE_MISMATCH,
        )


def depth_metres(image: ImageMessage, max_pixels: int = DEFAULT_MAX_PIXELS) -> Metres:
    """A depth message's pixels in metres (float32, NaN where invalid): 32FC1 as it is, with
    NaN, infinities and values <= 0 made NaN; 16UC1 millimetres / 1000, 0 made NaN. Byte order
    from `is_bigendian`, row padding (`step`) dropped.

    Raises ImageDecodeError: the message did not deserialize, its encoding is not a depth one
    (NOT_DEPTH), it claims more than `max_pixels` (TOO_LARGE, checked before anything is
    allocated), or width/height/step/data do not fit together.
    """
    where = f"depth on {image.topic} at log time {image.log_time_ns}"
    if image.decode_error is not None:
        raise ImageDecodeError(image.decode_error, UNDESERIALIZABLE)
    pixel_bytes = DEPTH_ENCODINGS.get(image.encoding)
    if pixel_bytes is None:
        raise ImageDecodeError(
            f"{where}: encoding {image.encoding!r} is not 32FC1 or 16UC1", NOT_DEPTH
        )
    check_pixel_cap((max(image.width, 0), max(image.height, 0)), max_pixels, where)
    rows = np.ascontiguousarray(pixel_rows(image, pixel_bytes))
    order = ">" if image.is_bigendian else "<"
    if image.encoding == "32FC1":
        metres = rows.view(order + "f4").astype(np.float32)
        with np.errstate(invalid="ignore"):
            metres[~(metres > 0) | ~np.isfinite(metres)] = np.nan
        return metres
    millimetres = rows.view(order + "u2")
    from_mm: Metres = millimetres.astype(np.float32) / np.float32(1000.0)
    from_mm[millimetres == 0] = np.nan
    return from_mm
