"""Opening a log, and choosing its camera topic.

The reader is chosen by what the path is (a directory, or the file's magic bytes), not by its
name alone: `formats.FORMATS` knows each format, its reader, its copier and its file names.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from doseqslam_logs.errors import NoCameraError, SourceError
from doseqslam_logs.sources.base import (
    MCAP_MAGIC,
    ChannelInfo,
    DecodedMessage,
    ImageMessage,
    Source,
)
from doseqslam_logs.sources.formats import FORMATS, format_of, read_head, refuse_stream
from doseqslam_logs.sources.images import IMAGE_TYPES, decode_gray

__all__ = [
    "FORMATS",
    "ChannelInfo",
    "DecodedMessage",
    "ImageMessage",
    "Source",
    "decode_gray",
    "format_of",
    "image_channels",
    "is_mcap_file",
    "open_source",
    "opened",
    "pick_image_topic",
    "refuse_stream",
]

# What a reading helper takes: the run's open log, or a path it opens for itself.
Log = Source | str | os.PathLike[str]


def is_mcap_file(path: str | Path) -> bool:
    """Whether `path` is a file that starts with the MCAP magic (False when unreadable:
    `open_source` says what is wrong with it)."""
    path = Path(path)
    try:
        return path.is_file() and read_head(path).startswith(MCAP_MAGIC)
    except SourceError:
        return False


def open_source(path: str | Path) -> Source:
    """Open a log read-only with the reader its content calls for (`formats.FORMATS`).

    Raises:
        SourceError: the path is missing or unreadable, is not a log file of a known format
            (MCAP, ROS 1 bag, rosbag2 .db3 or rosbag2 directory), or the reader cannot open it.
    """
    path = Path(path)
    return format_of(path).open(path)


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
