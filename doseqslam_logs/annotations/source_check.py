"""A log given beside an annotated one (a sidecar's `--source`, `--poses-from`) must be the log
that was annotated: its images, poses and times are read as if it were. A different log would
give a wrong trajectory or wrong scores with exit 0, so it is refused unless the user says so.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import SourceError, UsageError
from ..sources import open_source
from ..sources.digest import source_sha256
from .reader import AnnotatedLog, read_annotations

OVERRIDE_FLAG = "--no-source-check"


def check_source_log(log: AnnotatedLog, given: Path, flag: str) -> None:
    """Raise UsageError unless `given` is the log `log` was annotated from.

    The recorded sha256 decides; a full annotated copy of that log passes too (its own record
    names the same source). A record without a sha256 (an early version) leaves the recorded
    image topic, which `given` must hold.
    """
    if given.resolve() == log.path.resolve():
        return
    recorded = log.metadata.source_sha256
    if not recorded:
        _check_topic(log, given, flag)
        return
    try:
        actual = source_sha256(given)
    except OSError as exc:
        raise SourceError(f"{flag} {given}: cannot read it ({exc.strerror or exc})") from exc
    if actual == recorded or _annotated_from(given) == recorded:
        return
    raise UsageError(
        f"{flag} {given}: not the log {log.path} was annotated from "
        f"({log.metadata.source_file or 'recorded'}: sha256 {recorded[:12]}..., this file: "
        f"{actual[:12]}...); give that log, or {OVERRIDE_FLAG} to use this one anyway"
    )


def _check_topic(log: AnnotatedLog, given: Path, flag: str) -> None:
    topic = log.metadata.image_topic
    with open_source(given) as source:
        topics = {channel.topic for channel in source.channels()}
    if topic and topic not in topics:
        raise UsageError(
            f"{flag} {given}: has no topic {topic}, which {log.path} was annotated from; give "
            f"that log, or {OVERRIDE_FLAG} to use this one anyway"
        )


def _annotated_from(path: Path) -> str:
    """The source sha256 recorded in `path` when it is itself an annotated log, else ""."""
    try:
        return read_annotations(path).metadata.source_sha256
    except SourceError:
        return ""
