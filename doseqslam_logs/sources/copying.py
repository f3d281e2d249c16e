"""What a log format's copier needs: where the records go, what to leave out, and read errors
turned into one line.

A copier streams every record of its input into an MCAP `Writer` unchanged, so that an output
holds the whole log. The sink that drives it (the annotated MCAP writer) says through
`CopyHooks` which of the input's records it replaces and interleaves its own messages by log
time before each copied message.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TypeVar

from mcap.writer import Writer

from ..errors import DoseqslamError, SourceError

T = TypeVar("T")


class CopyHooks(Protocol):
    """The sink's side of a copy."""

    def keeps_topic(self, topic: str) -> bool:
        """False for a channel the sink replaces (its messages are left out)."""
        ...

    def keeps_attachment(self, name: str) -> bool: ...

    def keeps_metadata(self, name: str) -> bool: ...

    def before_message(self, log_time_ns: int) -> None:
        """Called before each copied message: the sink writes its own messages up to then."""
        ...

    def channel_copied(
        self, topic: str, encoding: str, schema_id: int, metadata: dict[str, str]
    ) -> None:
        """Called for each input channel copied, with its id in the output."""
        ...

    def message_copied(self, topic: str, log_time_ns: int, data: bytes) -> None:
        """Called after each copied message, with its bytes as written: the sink keeps what
        it republishes later (the match images) instead of reading the input again."""
        ...


@dataclass(frozen=True)
class Copied:
    """What a copy did: messages copied, and the topics of the channels left out."""

    messages: int
    dropped_topics: list[str]


# copy(path, writer, hooks): every record of the log at `path` into `writer`.
Copier = Callable[[Path, Writer, CopyHooks], Copied]


class reading_errors:
    """Context manager: failures while reading the input become one-line SourceErrors."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __enter__(self) -> None:
        return None

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, _: Any) -> None:
        if exc is None or isinstance(exc, DoseqslamError) or not isinstance(exc, Exception):
            return
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SourceError(f"{self.path}: cannot read the log: {message}") from exc


def guarded_reads(path: Path, items: Iterable[T]) -> Iterator[T]:
    """`items`, with any failure while producing them raised as SourceError."""
    iterator = iter(items)
    while True:
        with reading_errors(path):
            try:
                item = next(iterator)
            except StopIteration:
                return
        yield item
