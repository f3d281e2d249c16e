"""The log formats, each known in one place: how to tell it (a probe of the path and its first
bytes), how to read it (a `Source`), how to copy it into an output, and which names a batch
searches for.

`open_source`, the annotated MCAP writer and batch discovery all go through `FORMATS`, first
match wins: supporting a new format is one module (its `Source` and its copier) plus one entry.
A format is told by its content, not by its name.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from rosbags.rosbag2 import Reader as Ros2Reader
from rosbags.rosbag2.reader import DirectoryReader
from rosbags.rosbag2.storage_mcap import McapReader as Ros2McapStorage

from ..errors import SourceError
from .bag_copy import copy_ros1_bag, copy_rosbag2, open_bag
from .base import MCAP_MAGIC, ROS1_MAGIC, SQLITE_MAGIC, Source
from .copying import Copier
from .mcap_copy import copy_mcap, read_mcap_profile
from .mcap_source import McapSource
from .rosbags_source import RosbagsSource

HEAD_BYTES = 16  # what a probe sees of a file
ROSBAG2_METADATA = "metadata.yaml"

# A probe sees the path and the first HEAD_BYTES of the file (empty for a directory).
Probe = Callable[[Path, bytes], bool]


@dataclass(frozen=True)
class CopyPlan:
    """What the writer copies for a log, and the MCAP profile of the output."""

    kind: str  # the name of the format copied
    path: Path  # what is copied: a rosbag2 folder of one plain MCAP file copies that file
    profile: str  # the output's MCAP profile
    copy: Copier


@dataclass(frozen=True)
class LogFormat:
    """One log format."""

    name: str  # "mcap", "ros1-bag", "rosbag2"
    described: str  # as an error message lists it: "MCAP", "ROS 1 .bag"
    probe: Probe
    open: Callable[[Path], Source]
    plan_copy: Callable[[Path], CopyPlan]
    suffixes: tuple[str, ...] = ()  # file names a batch takes as logs of this format
    folder_marker: str = ""  # a directory holding this file is one log of this format


def _is_mcap(path: Path, head: bytes) -> bool:
    return head.startswith(MCAP_MAGIC)


def _is_ros1_bag(path: Path, head: bytes) -> bool:
    return head.startswith(ROS1_MAGIC)


def _is_rosbag2_sqlite(path: Path, head: bytes) -> bool:
    # rosbags picks its sqlite3 reader by the .db3 suffix, so other sqlite files cannot be read.
    return path.suffix == ".db3" and head.startswith(SQLITE_MAGIC)


def _is_directory(path: Path, head: bytes) -> bool:
    return path.is_dir()  # a rosbag2 bag; RosbagsSource says so if metadata.yaml is missing


def _mcap_plan(path: Path) -> CopyPlan:
    return CopyPlan("mcap", path, read_mcap_profile(path), copy_mcap)


def _ros1_plan(path: Path) -> CopyPlan:
    return CopyPlan("ros1-bag", path, "ros1", copy_ros1_bag)


def _rosbag2_file_plan(path: Path) -> CopyPlan:
    # A storage file of a bag folder is copied as the whole bag (its metadata, its splits).
    has_metadata = (path.parent / ROSBAG2_METADATA).is_file()
    return CopyPlan("rosbag2", path.parent if has_metadata else path, "ros2", copy_rosbag2)


def _rosbag2_folder_plan(path: Path) -> CopyPlan:
    if not (path / ROSBAG2_METADATA).is_file():
        raise SourceError(f"{path}: a folder without {ROSBAG2_METADATA} is not a rosbag2 bag")
    with open_bag(path, Ros2Reader) as reader:
        storage = reader.storage
        if (
            isinstance(storage, DirectoryReader)
            and not reader.compression_mode
            and len(storage.storages) == 1
            and isinstance(storage.storages[0], Ros2McapStorage)
        ):
            # One plain MCAP file: copy it at the MCAP level, which keeps every record.
            return _mcap_plan(Path(str(storage.storages[0].path)))
    return CopyPlan("rosbag2", path, "ros2", copy_rosbag2)


FORMATS: list[LogFormat] = [
    LogFormat("mcap", "MCAP", _is_mcap, McapSource, _mcap_plan, (".mcap",)),
    LogFormat("ros1-bag", "ROS 1 .bag", _is_ros1_bag, RosbagsSource, _ros1_plan, (".bag",)),
    LogFormat(
        "rosbag2", "rosbag2 .db3", _is_rosbag2_sqlite, RosbagsSource, _rosbag2_file_plan, (".db3",)
    ),
    LogFormat(
        "rosbag2",
        "rosbag2 directory",
        _is_directory,
        RosbagsSource,
        _rosbag2_folder_plan,
        folder_marker=ROSBAG2_METADATA,
    ),
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


def read_head(path: Path) -> bytes:
    """What a probe sees of `path`: its first HEAD_BYTES, b"" for a directory."""
    refuse_stream(path)
    if path.is_dir():
        return b""
    try:
        with path.open("rb") as file:
            return file.read(HEAD_BYTES)
    except OSError as exc:
        raise SourceError(f"{path}: cannot read ({exc.strerror or exc})") from exc


def _listed(names: list[str]) -> str:
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} or {names[-1]}"


def format_of(path: str | Path) -> LogFormat:
    """The format of the log at `path`, told by its content.

    Raises SourceError: the path is missing, unreadable, empty, or no format's probe takes it.
    """
    path = Path(path)
    if not path.exists():
        raise SourceError(f"{path}: no such file or directory")
    head = read_head(path)
    if not head and path.is_file():
        raise SourceError(f"{path}: not a log file: it is empty (0 bytes)")
    for log_format in FORMATS:
        if log_format.probe(path, head):
            return log_format
    formats = _listed([f.described for f in FORMATS])
    raise SourceError(f"{path}: not a log file (not {formats}; it starts with {head!r})")


def plan_copy(path: str | Path) -> CopyPlan:
    """What the writer copies for the log at `path` (`format_of`'s errors)."""
    path = Path(path)
    return format_of(path).plan_copy(path)


def log_file_suffixes() -> tuple[str, ...]:
    """The file names a batch takes as logs, of every format."""
    return tuple(dict.fromkeys(s for f in FORMATS for s in f.suffixes))


def is_log_folder(path: Path) -> bool:
    """Whether `path` is a directory that is one log (a rosbag2 bag), not a folder of logs."""
    markers = [f.folder_marker for f in FORMATS if f.folder_marker]
    return path.is_dir() and any((path / marker).is_file() for marker in markers)


__all__ = [
    "FORMATS",
    "CopyPlan",
    "LogFormat",
    "Probe",
    "format_of",
    "is_log_folder",
    "log_file_suffixes",
    "plan_copy",
    "read_head",
    "refuse_stream",
]
