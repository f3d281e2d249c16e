"""What every log source provides: channel listings and image messages in timestamp order."""

from __future__ import annotations

import heapq
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol, TypeVar, cast

from ..errors import SourceError

ImageKind = Literal["raw", "compressed"]

# The first bytes of each container, the one definition that readers and writers share.
MCAP_MAGIC = b"\x89MCAP0\r\n"
ROS1_MAGIC = b"#ROSBAG V2.0\n"
SQLITE_MAGIC = b"SQLite format 3\x00"
# The latest time our annotation messages can carry: builtin_interfaces/Time has int32 seconds
# (2038-01-19T03:14:07.999999999Z). Later stamps and log times are invalid (docs/robustness.md).
MAX_TIME_NS = (2**31 - 1) * 1_000_000_000 + 999_999_999


@dataclass(frozen=True)
class Promise:
    """How many messages of a topic the log's own bookkeeping (MCAP Statistics record, ROS 1
    bag index, rosbag2 metadata.yaml) says it holds, written when the recording ended: a run
    that finds fewer has lost some, and says so."""

    count: int
    origin: str  # e.g. "the Statistics record"


@dataclass(frozen=True)
class ChannelInfo:
    """One topic of a log, as `info` lists it."""

    topic: str
    message_type: str  # e.g. "sensor_msgs/msg/Image", "foxglove.CompressedImage"
    message_encoding: str  # "cdr", "ros1", "protobuf", "json"
    message_count: int
    first_log_time_ns: int | None = None
    last_log_time_ns: int | None = None
    is_image: bool = False


@dataclass(frozen=True)
class ImageMessage:
    """One camera message, still encoded; `sources.images.decode_gray` turns it into pixels.

    Decoding is kept apart from reading so that it can run in a worker pool.
    """

    topic: str
    log_time_ns: int
    header_stamp_ns: int | None  # None when the message type has no header stamp
    kind: ImageKind
    encoding: str  # raw: the ROS encoding ("mono8", "rgb8", ...); compressed: the format string
    width: int  # raw only (0 for compressed)
    height: int  # raw only (0 for compressed)
    step: int  # raw only: bytes per row including padding (0 for compressed)
    is_bigendian: bool
    data: bytes
    publish_time_ns: int | None = None
    sequence: int | None = None
    # Set when the message itself could not be deserialized. The source still yields it (a
    # generator that raised could not go on) and `decode_gray` raises ImageDecodeError with it,
    # so `--on-error skip` can skip one corrupt message and keep reading.
    decode_error: str | None = None


@dataclass(frozen=True)
class DecodedMessage:
    """One message of any topic, decoded with the log's own definition of its type (a ROS
    message object, a protobuf message, or a namespace of a JSON object)."""

    log_time_ns: int
    message_type: str
    message: Any  # None when it could not be deserialized (decode_error says why)
    # As ImageMessage's: one corrupt message is yielded, not raised, so that a reader can skip
    # and count it and go on with the rest of the topic.
    decode_error: str | None = None


@dataclass(frozen=True)
class SideMessage:
    """A message of another topic met in the pass that reads the camera's (odometry, camera
    info): decoded only when its reader wants it, so a topic read for its first messages costs
    no more than the pass.

    `decode()` returns the DecodedMessage (`decode_error` set for a damaged message) and raises
    SourceError when the topic itself cannot be decoded (no schema, an unsupported encoding).
    """

    topic: str
    log_time_ns: int
    decode: Callable[[], DecodedMessage]


class SideTopicReader:
    """A reader of one side topic fed message by message (a pose topic, the CameraInfo): the
    messages of another topic's pass are decoded only while it wants more, and a topic that
    cannot be decoded at all is kept as `error`, raised when the result is asked for."""

    error: SourceError | None = None

    @property
    def wants_more(self) -> bool:
        """Whether a later message could still change the result."""
        return self.error is None

    def add(self, message: DecodedMessage) -> None:
        """The topic's next message."""
        raise NotImplementedError

    def add_side(self, message: SideMessage) -> None:
        """`add` for a message met in another topic's pass, decoded here."""
        if not self.wants_more:
            return
        try:
            self.add(message.decode())
        except SourceError as exc:
            self.error = exc


class Source(Protocol):
    """A readable log. Sources are context managers; the input file is opened read-only."""

    path: Path

    def channels(self) -> list[ChannelInfo]:
        """Every channel of the log, image or not."""
        ...

    def image_messages(
        self, topic: str, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[ImageMessage]:
        """The messages of one image topic in log-time order, within [start_ns, end_ns)."""
        ...

    def messages(self, topic: str) -> Iterator[DecodedMessage]:
        """Every message of `topic` (poses, camera info: the other channels a run reads),
        decoded. SourceError while iterating when the log or a message cannot be read."""
        ...

    def image_and_side_messages(
        self,
        topic: str,
        side_topics: Sequence[str],
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[ImageMessage | SideMessage]:
        """In one pass over the log, in log-time order within [start_ns, end_ns): the image
        messages of `topic` (as `image_messages` yields them) and the messages of
        `side_topics` (as SideMessage). Raises as `image_messages` does."""
        ...

    def raw_messages(
        self, topic: str, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[tuple[int, bytes]]:
        """(log time, message bytes as stored) of `topic` within [start_ns, end_ns), in
        log-time order: what the writer copies, for republishing a message unchanged."""
        ...

    def promised_messages(self, topic: str) -> Promise | None:
        """The messages of `topic` the log's index or statistics promise (None: no such
        record, or one that counts the data it was read from)."""
        ...

    def unattributed_messages(self) -> int:
        """Messages that belong to no topic the log declares (they cannot be read)."""
        ...

    def close(self) -> None: ...

    def __enter__(self) -> Source: ...

    def __exit__(self, *exc: object) -> None: ...


_Defaults = TypeVar("_Defaults", bound="SourceDefaults")


class SourceDefaults:
    """What a `Source` with nothing of its own to release, and no index or statistics that
    promise a count, inherits (an image folder, a toy format): no promise, no unattributed
    message, and the context manager around `close`."""

    def promised_messages(self, topic: str) -> Promise | None:
        return None

    def unattributed_messages(self) -> int:
        return 0

    def image_and_side_messages(
        self,
        topic: str,
        side_topics: Sequence[str],
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[ImageMessage | SideMessage]:
        return merged_passes(cast(Source, self), topic, side_topics, start_ns, end_ns)

    def close(self) -> None:
        """Nothing to release."""

    def __enter__(self: _Defaults) -> _Defaults:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def merged_passes(
    source: Source,
    topic: str,
    side_topics: Sequence[str],
    start_ns: int | None = None,
    end_ns: int | None = None,
) -> Iterator[ImageMessage | SideMessage]:
    """`image_and_side_messages` for a source that reads one topic at a time (an image folder
    has no side topic; a toy format): a pass per topic, merged by log time."""
    images = source.image_messages(topic, start_ns, end_ns)
    passes: list[Iterator[ImageMessage | SideMessage]] = [images]
    passes += [_side_pass(source, side, start_ns, end_ns) for side in side_topics]
    return heapq.merge(*passes, key=lambda message: message.log_time_ns)


def _side_pass(
    source: Source, topic: str, start_ns: int | None, end_ns: int | None
) -> Iterator[SideMessage]:
    for message in source.messages(topic):
        time_ns = message.log_time_ns
        if (start_ns is None or time_ns >= start_ns) and (end_ns is None or time_ns < end_ns):
            yield SideMessage(topic, time_ns, _decoded_already(message))


def _decoded_already(message: DecodedMessage) -> Callable[[], DecodedMessage]:
    return lambda: message
