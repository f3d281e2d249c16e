"""Opening a log, and choosing its camera topic.

The reader is chosen by what the path is (a directory, or the file's magic bytes), not by its
name alone. `FORMATS` lists (probe, constructor) pairs, first match wins: supporting a new format
is one new module plus one entry.
"""

from __future__ import annotations

import contextlib
import os
import stat
from collections.abc import Callable, Iterator
from pathlib import Path

from doseqslam_logs.errors import NoCameraError, SourceError
from doseqslam_logs.sources.base import (
    MCAP_MAGIC,
    ROS1_MAGIC,
    SQLITE_MAGIC,
    ChannelInfo,
    DecodedMessage,
    ImageMessage,
    Source,
)
from doseqslam_logs.sources.images import IMAGE_TYPES, decode_gray
from doseqslam_logs.sources.mcap_source import McapSource
from doseqslam_logs.sources.rosbags_source import RosbagsSource

__all__ = [
    "FORMATS",
    "ChannelInfo",
    "DecodedMessage",
    "ImageMessage",
    "Source",
    "decode_gray",
    "image_channels",
    "is_mcap_file",
    "open_source",
    "opened",
    "pick_image_topic",
]

# What a reading helper takes: the run's open log, or a path it opens for itself.
Log = Source | str | os.PathLike[str]


# A probe sees the path and the first 16 bytes of the file (empty for a directory).
Probe = Callable[[Path, bytes], bool]


def _is_directory(path: Path, head: bytes) -> bool:
    return path.is_dir()  # a rosbag2 bag; RosbagsSource says so if metadata.yaml is missing


def _is_mcap(path: Path, head: bytes) -> bool:
    return head.startswith(MCAP_MAGIC)


def _is_ros1_bag(path: Path, head: bytes) -> bool:
    return head.startswith(ROS1_MAGIC)


def _is_rosbag2_sqlite(path: Path, head: bytes) -> bool:
    # rosbags picks its sqlite3 reader by the .db3 suffix, so other sqlite files cannot be read.
    return path.suffix == ".db3" and head.startswith(SQLITE_MAGIC)


FORMATS: list[tuple[Probe, Callable[[Path], Source]]] = [
    (_is_directory, RosbagsSource),
    (_is_mcap, McapSource),
    (_is_ros1_bag, RosbagsSource),
    (_is_rosbag2_sqlite, RosbagsSource),
]


def refuse_stream(path: Path) -> None:
    """Raises SourceError when `path` is a pipe, socket or device: logs are read by seeking
    (an index, a second reader), and opening a FIFO with no writer would block for ever."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return  # missing or unreadable: the caller says which
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return
    kinds = {stat.S_IFIFO: "a pipe (FIFO)", stat.S_IFSOCK: "a socket", stat.S_IFCHR: "a device"}
    kind = kinds.get(stat.S_IFMT(mode), "a device")
    raise SourceError(
        f"{path}: the log is {kind}, not a file: logs are read by seeking; save it to a file"
    )


def _head(path: Path) -> bytes:
    refuse_stream(path)
    if path.is_dir():
        return b""
    try:
        with path.open("rb") as file:
            return file.read(16)
    except OSError as exc:
        raise SourceError(f"{path}: cannot read ({exc.strerror or exc})") from exc


def is_mcap_file(path: str | Path) -> bool:
    """Whether `path` is a file that starts with the MCAP magic (False when unreadable:
    `open_source` says what is wrong with it)."""
    path = Path(path)
    try:
        return path.is_file() and _head(path).startswith(MCAP_MAGIC)
    except SourceError:
        return False


def open_source(path: str | Path) -> Source:
    """Open a log read-only with the reader its content calls for.

    Raises:
        SourceError: the path is missing or unreadable, is not a log file (MCAP, ROS 1 bag,
            rosbag2 .db3 or rosbag2 directory), or the reader cannot open it.
    """
    path = Path(path)
    if not path.exists():
        raise SourceError(f"{path}: no such file or directory")
    head = _head(path)
    if not head and path.is_file():
        raise SourceError(f"{path}: not a log file: it is empty (0 bytes)")
    for probe, open_format in FORMATS:
        if probe(path, head):
            return open_format(path)
    raise SourceError(
        f"{path}: not a log file (not MCAP, ROS 1 .bag, rosbag2 .db3 or rosbag2 directory; "
        f"it starts with {head!r})"
    )


@contextlib.contextmanager
def opened(log: Log) -> Iterator[Source]:
    """`log` itself when it is an open Source (left open: whoever opened it closes it), else
    the log at that path, opened for the block. A run opens its log once and hands the open
    Source to every stage; a helper called on its own takes a path."""
    if isinstance(log, (str, os.PathLike)):
        with open_source(Path(log)) as source:
            yield source
    else:
        yield log


def image_channels(source: Source) -> list[ChannelInfo]:
    """The channels of `source` that carry camera images."""
    return [channel for channel in source.channels() if channel.is_image]


def _same_topic(a: str, b: str) -> bool:
    # ROS 1 allows relative topic names; users write them with or without the leading slash.
    return a.lstrip("/") == b.lstrip("/")


def _without_depth(source: Source, channels: list[ChannelInfo], names: list[str]) -> list[str]:
    """`names` less the topics that hold depth images (all of them when every one does)."""
    from .depth import is_depth_topic  # depth reads through this package's sources

    types = {c.topic: c.message_type for c in channels}
    return [n for n in names if not is_depth_topic(source, n, types[n])] or names


def pick_image_topic(source: Source, topic: str | None = None) -> str:
    """The log's image topic: the only one, or `topic` (with or without a leading slash).

    Returns the topic name exactly as the log spells it.

    Raises:
        NoCameraError: the log has no image topic; several and `topic` is None; or `topic` is
            not among them. The message lists the image topics.
    """
    channels = source.channels()
    names = [c.topic for c in channels if c.is_image]
    listing = ", ".join(names)
    if topic is None:
        # An annotated log's match images (/doseqslam/match/...) are never its camera.
        names = [n for n in names if not n.startswith("/doseqslam/")] or names
        if len(names) > 1:  # an RGB-D camera's depth topic is not a camera to read
            names = _without_depth(source, channels, names)
        if len(names) == 1:
            return names[0]
        if not names:
            types = ", ".join(sorted(IMAGE_TYPES))
            raise NoCameraError(
                f"{source.path}: no image topic among {len(channels)} topics (image types: {types})"
            )
        raise NoCameraError(f"{source.path}: {len(names)} image topics, choose one: {listing}")
    matches = [n for n in names if n == topic] or [n for n in names if _same_topic(n, topic)]
    if len(matches) == 1:
        return matches[0]
    if matches:
        raise NoCameraError(f"{source.path}: topic {topic!r} matches {', '.join(matches)}")
    others = [c for c in channels if _same_topic(c.topic, topic) and not c.is_image]
    problem = f"is a {others[0].message_type}, not an image" if others else "is not in the log"
    raise NoCameraError(
        f"{source.path}: topic {topic!r} {problem} (image topics: {listing or 'none'})"
    )
