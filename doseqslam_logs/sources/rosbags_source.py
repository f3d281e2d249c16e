"""ROS 1 .bag files and rosbag2 bags (directory, bare .db3, .mcap storage) through rosbags.

rosbags reads ROS 1 bags with none, bz2 or lz4 chunks, rosbag2 directories with their
metadata.yaml (sqlite3 or MCAP storage), and a bare .db3 file without metadata.yaml. Message types
come from the definitions stored in the bag; bags without any (old rosbag2 sqlite3 files) fall back
to the standard ROS 2 Humble types.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from doseqslam_logs.errors import DoseqslamError, NoCameraError, SourceError
from doseqslam_logs.sources.base import (
    ROS1_MAGIC,
    ChannelInfo,
    DecodedMessage,
    ImageMessage,
    Promise,
    SideMessage,
)
from doseqslam_logs.sources.handles import HandlePool
from doseqslam_logs.sources.images import RecordInfo, image_from_payload, is_image_type

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import Connection

REINDEX_HINT = (
    "a bag whose recording never finished (or was cut short) has no index: "
    "`rosbag reindex` it (ROS 1 tools) and try again"
)


def _one_line(exc: BaseException) -> str:
    """`Type: message` on one line, cut at 200 characters."""
    text = " ".join(str(exc).split())
    if len(text) > 200:
        text = text[:200] + "..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _is_ros1_file(path: Path) -> bool:
    """Whether `path` is a file that starts with the ROS 1 bag magic (formats are told by
    content: a ROS 1 bag may be named anything)."""
    if not path.is_file():
        return False
    with path.open("rb") as file:
        return file.read(len(ROS1_MAGIC)) == ROS1_MAGIC


def _check_layout(path: Path) -> None:
    """Fail early, with a message saying what is needed, where rosbags would fail obscurely."""
    if not path.exists():
        raise SourceError(f"{path}: no such file or directory")
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            raise SourceError(
                f"{path}: a rosbag2 directory needs its metadata.yaml (or pass the .db3/.mcap "
                "file inside it)"
            )
        return
    if path.suffix in (".bag", ".db3", ".mcap") or _is_ros1_file(path):
        return
    raise SourceError(f"{path}: not a ROS bag (expected .bag, .db3, .mcap or a rosbag2 directory)")


class _NamedAsBag(type(Path())):  # type: ignore[misc]
    """`path` as rosbags must see it to read a ROS 1 bag: rosbags tells ROS 1 from ROS 2 by
    the .bag suffix alone, we by content (the reader opens the real file)."""

    @property
    def suffix(self) -> str:
        return ".bag"


def _open_reader(path: Path) -> AnyReader:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    _check_layout(path)
    is_ros1 = _is_ros1_file(path)
    fallback = get_typestore(Stores.ROS1_NOETIC if is_ros1 else Stores.ROS2_HUMBLE)
    kind = "ROS 1 bag" if is_ros1 else "rosbag2 bag"
    as_read = _NamedAsBag(path) if is_ros1 and path.suffix != ".bag" else path
    try:
        reader = AnyReader([as_read], default_typestore=fallback)
        reader.open()
    except Exception as exc:  # rosbags, sqlite (apsw), YAML, OS and decompression errors
        hint = f"; {REINDEX_HINT}" if is_ros1 and "index" in str(exc).lower() else ""
        raise SourceError(f"{path}: cannot open as a {kind} ({_one_line(exc)}){hint}") from exc
    return reader


def _close_reader(reader: AnyReader) -> None:
    if reader.stack is not None:
        reader.close()


def _same_connections(reader: AnyReader, connections: list[Connection]) -> list[Connection]:
    """`connections` (of the bag's first reader) as `reader`'s own: rosbags reads a
    connection through the reader that owns it. Two readers of one bag list the same
    connections in the same order."""
    ids = {c.id for c in connections}
    return [c for c in reader.connections if c.id in ids]


def _time_range(connections: list[Connection]) -> tuple[int | None, int | None]:
    """First and last log time from the ROS 1 reader's in-memory index (IndexData.time, sorted);
    rosbag2 readers keep no per-topic index, so (None, None) for them."""
    firsts, lasts = [], []
    for connection in connections:
        index = getattr(connection.owner, "indexes", {}).get(connection.id)
        if index:
            firsts.append(int(index[0].time))
            lasts.append(int(index[-1].time))
    return (min(firsts) if firsts else None, max(lasts) if lasts else None)


def _topic_info(topic: str, connections: list[Connection]) -> ChannelInfo:
    first, last = _time_range(connections)
    return ChannelInfo(
        topic=topic,
        message_type=", ".join(dict.fromkeys(c.msgtype for c in connections)),
        # ROS 1 connections have no serialization format field: they are always "ros1".
        message_encoding=", ".join(
            dict.fromkeys(getattr(c.ext, "serialization_format", "ros1") for c in connections)
        ),
        message_count=sum(c.msgcount for c in connections),
        first_log_time_ns=first,
        last_log_time_ns=last,
        is_image=any(is_image_type(c.msgtype) for c in connections),
    )


class RosbagsSource:
    """A ROS 1 bag or a rosbag2 bag, opened read-only.

    Type names are the ROS 2 style names rosbags uses for both generations
    ("sensor_msgs/msg/CompressedImage"). One `image_messages` iteration at a time: the readers
    keep one current chunk.

    Raises (constructor):
        SourceError: the path is missing, has a layout rosbags cannot read (directory without
            metadata.yaml, ROS 1 bag not named .bag), or the bag is corrupt.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._reader = _open_reader(self.path)  # its connections describe the bag
        # A rosbags reader seeks one file: each iteration borrows its own (sources.handles).
        self._readers = HandlePool(lambda: _open_reader(self.path), _close_reader, self._reader)

    @property
    def handles_opened(self) -> int:
        """How many times this source opened the bag (for tests and benchmarks)."""
        return self._readers.opened

    def channels(self) -> list[ChannelInfo]:
        """Every topic (several connections of one topic are merged), with message counts;
        first/last log times for ROS 1 bags only."""
        by_topic: dict[str, list[Connection]] = {}
        for connection in self._reader.connections:
            by_topic.setdefault(connection.topic, []).append(connection)
        return [_topic_info(topic, group) for topic, group in by_topic.items()]

    def promised_messages(self, topic: str) -> Promise | None:
        """The count of the ROS 1 bag's index or of the rosbag2 folder's metadata.yaml; None for
        a bare .db3, whose counts rosbags takes from the rows themselves."""
        if self.path.is_file() and self.path.suffix != ".bag":
            return None
        origin = "the bag's index" if self.path.suffix == ".bag" else "metadata.yaml"
        counts = [c.msgcount for c in self._reader.connections if c.topic == topic]
        return Promise(sum(counts), origin)

    def unattributed_messages(self) -> int:
        """Rows of a .db3 whose topic id names no topic: rosbags reads messages by topic, so
        they are never read; the file's row count minus the topics' counts."""
        declared = sum(c.msgcount for c in self._reader.connections)
        return max(0, self._reader.message_count - declared)

    def image_messages(
        self, topic: str, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[ImageMessage]:
        """The image messages of `topic` with log time in [start_ns, end_ns), in log-time order.

        A message that does not deserialize is yielded with `decode_error` set.

        Raises:
            NoCameraError: `topic` (exact name) is not an image topic of this bag (at call time).
            SourceError: while iterating, the bag turns out corrupt.
        """
        messages = self._images(self._image_connections(topic), [], start_ns, end_ns)
        return (m for m in messages if isinstance(m, ImageMessage))  # no side topic: all are

    def image_and_side_messages(
        self,
        topic: str,
        side_topics: Sequence[str],
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[ImageMessage | SideMessage]:
        """`image_messages` of `topic` and the messages of `side_topics`, in one pass of
        rosbags' reader over their connections."""
        images = self._image_connections(topic)
        side = [c for c in self._reader.connections if c.topic in side_topics and c.topic != topic]
        return self._images(images, side, start_ns, end_ns)

    def _image_connections(self, topic: str) -> list[Connection]:
        connections = [
            c for c in self._reader.connections if c.topic == topic and is_image_type(c.msgtype)
        ]
        # Never call messages() with an empty list: rosbags then yields every message of the bag.
        if not connections:
            image_topics = dict.fromkeys(c.topic for c in self.channels() if c.is_image)
            raise NoCameraError(
                f"{self.path}: {topic!r} is not an image topic (image topics: "
                f"{', '.join(image_topics) or 'none'})"
            )
        return connections

    def _images(
        self,
        connections: list[Connection],
        side: list[Connection],
        start_ns: int | None,
        end_ns: int | None,
    ) -> Iterator[ImageMessage | SideMessage]:
        if start_ns is not None and end_ns is not None and start_ns >= end_ns:
            return
        topic = connections[0].topic  # the side topics are others
        try:
            deserializers = {c.msgtype: self._deserializer(c.msgtype) for c in connections}
            every = connections + side
            for connection, log_time, payload in self._messages(every, start_ns, end_ns):
                if connection.topic != topic:
                    decode = functools.partial(self._decode, connection, log_time, payload)
                    yield SideMessage(connection.topic, log_time, decode)
                    continue
                record = RecordInfo(connection.topic, log_time)
                deserialize = deserializers[connection.msgtype]
                yield image_from_payload(connection.msgtype, payload, deserialize, record)
        except DoseqslamError:
            raise
        except Exception as exc:
            raise SourceError(
                f"{self.path}: cannot read the messages of {topic} ({_one_line(exc)})"
            ) from exc

    def raw_messages(
        self, topic: str, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[tuple[int, bytes]]:
        """(log time, message bytes) of `topic` in [start_ns, end_ns), in log-time order.

        Raises SourceError (while iterating) when the bag turns out corrupt.
        """
        connections = [c for c in self._reader.connections if c.topic == topic]
        if not connections:  # rosbags would yield every message of the bag
            return
        with self._reading(topic):
            for _, log_time, payload in self._messages(connections, start_ns, end_ns):
                yield log_time, bytes(payload)

    def messages(self, topic: str) -> Iterator[DecodedMessage]:
        """Every message of `topic` in log-time order, decoded (none for a missing topic).

        Raises SourceError (while iterating) when the bag turns out corrupt.
        """
        connections = [c for c in self._reader.connections if c.topic == topic]
        if not connections:  # rosbags would yield every message of the bag
            return
        with self._reading(topic):
            for connection, log_time, payload in self._messages(connections, None, None):
                yield self._decode(connection, log_time, payload)

    def _decode(self, connection: Connection, log_time: int, payload: bytes) -> DecodedMessage:
        try:
            decoded = self._reader.deserialize(payload, connection.msgtype)
        except Exception as exc:  # this message only: the bag itself reads on
            problem = f"{type(exc).__name__}: {exc}"
            return DecodedMessage(log_time, connection.msgtype, None, problem)
        return DecodedMessage(log_time, connection.msgtype, decoded)

    def _messages(
        self, connections: list[Connection], start_ns: int | None, end_ns: int | None
    ) -> Iterator[tuple[Connection, int, bytes]]:
        """rosbags' messages of `connections` in [start_ns, end_ns), through a reader of their
        own, lent by the pool and given back when they end (or are dropped)."""
        with self._readers.borrowed() as reader:
            own = _same_connections(reader, connections)
            yield from reader.messages(connections=own, start=start_ns, stop=end_ns)

    @contextlib.contextmanager
    def _reading(self, topic: str) -> Iterator[None]:
        """A bag found corrupt while reading `topic`'s messages, as one SourceError."""
        try:
            yield
        except DoseqslamError:
            raise
        except Exception as exc:
            raise SourceError(
                f"{self.path}: cannot read the messages of {topic} ({_one_line(exc)})"
            ) from exc

    def _deserializer(self, msgtype: str) -> Callable[[bytes], Any]:
        reader = self._reader
        return lambda payload: reader.deserialize(payload, msgtype)

    def close(self) -> None:
        """Close the bag; iterations already started keep their reader until they end."""
        self._readers.close()

    def __enter__(self) -> RosbagsSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
