"""`OUTDIR/manifest.jsonl`: one JSON line per finished attempt, the memory of a batch.

Each line is appended with a single write to a file opened O_APPEND, then fsynced, so a
line is either whole or (after a crash mid-write) a torn last line, which readers skip. The
last entry of a log decides whether a re-run may skip it (`is_up_to_date`).
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from ..errors import OutputError

MANIFEST_NAME = "manifest.jsonl"


@dataclass(frozen=True)
class Counts:
    frames: int = 0
    sequences: int = 0
    loop_closures: int = 0
    skipped: int = 0


@dataclass(frozen=True)
class FileStamp:
    """Size and modification time of a log (summed / latest over a rosbag2 folder's files):
    when both are unchanged, the recorded sha256 is trusted instead of reading the log again."""

    size: int
    mtime_ns: int

    @classmethod
    def of(cls, path: Path) -> FileStamp:
        files = [p for p in path.rglob("*") if p.is_file()] if path.is_dir() else [path]
        stats = [f.stat() for f in files]
        return cls(sum(s.st_size for s in stats), max((s.st_mtime_ns for s in stats), default=0))


@dataclass(frozen=True)
class Entry:
    """One finished attempt at one log."""

    input: str  # absolute path of the log
    output: str  # absolute path of the annotated MCAP
    status: str  # "ok" or "failed"
    sha256: str  # of the log ("" when it could not be read)
    stamp: FileStamp | None
    parameters_hash: str  # the detector parameters' hash, as in the output's metadata
    options_hash: str  # every other option that changes the output (topic, times, ...)
    tool_version: str
    engine: str
    counts: Counts = field(default_factory=Counts)
    timings: dict[str, float] = field(default_factory=dict)  # seconds
    error: str = ""
    exit_code: int = 0
    finished_at: str = ""  # UTC, ISO 8601
    warning: str = ""  # frames too poor in features to segment or verify: what and what to do

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True, separators=(",", ":"))

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> Entry:
        stamp = values.get("stamp")
        return cls(
            **{
                **values,
                "stamp": FileStamp(**stamp) if stamp else None,
                "counts": Counts(**values.get("counts", {})),
            }
        )


def append_entry(manifest: Path, entry: Entry) -> None:
    """Append one line and make it durable before returning."""
    line = (entry.to_json() + "\n").encode()
    try:
        fd = os.open(manifest, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        try:
            os.write(fd, line)  # one write: O_APPEND keeps concurrent lines apart
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as exc:
        raise OutputError(f"{manifest}: cannot append to the manifest: {exc.strerror}") from exc


def read_entries(manifest: Path) -> Iterator[Entry]:
    """Every readable entry in file order; torn or foreign lines are skipped."""
    with contextlib.suppress(FileNotFoundError), manifest.open("rb") as stream:
        for raw in stream:
            try:
                values = json.loads(raw)
                yield Entry.from_dict(values)
            except (ValueError, TypeError):
                continue


def last_entries(manifest: Path) -> dict[str, Entry]:
    """The last entry of each input path."""
    return {entry.input: entry for entry in read_entries(manifest)}


def is_up_to_date(
    last: Entry | None,
    output: Path,
    parameters_hash: str,
    options_hash: str,
    tool_version: str,
    current_sha256: str,
) -> bool:
    """A log may be skipped when its last attempt succeeded with the same content, options
    and tool version, and wrote the output we expect, which still exists."""
    return (
        last is not None
        and last.status == "ok"
        and last.sha256 == current_sha256
        and last.parameters_hash == parameters_hash
        and last.options_hash == options_hash
        and last.tool_version == tool_version
        and last.output == str(output)
        and output.is_file()
    )
