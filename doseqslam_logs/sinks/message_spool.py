"""Our output messages kept in an unlinked temporary file until they are written.

A loop closure message is a record of about 35 fields (frame references, the relative pose, the
metric pose): a few KB of Python objects, and with verification every pair of an accepted
sequence has one, checked or not: thousands in a few minutes of a 10 Hz drive. The writer needs
them all before it starts, to interleave them with the input by log time, so held as objects
they would grow with the log.
`SpooledMessages` pickles each message into the file as it comes and keeps in memory only its
sort key and place in the file (32 B); the writer reads them back one at a time, in order.

The file is created already unlinked (`tempfile.TemporaryFile`, in TMPDIR or the system's
temporary folder): nothing is left behind, even when the process is killed.
"""

from __future__ import annotations

import os
import pickle
import tempfile
from array import array
from collections.abc import Iterable, Iterator, Sequence
from typing import overload

import numpy as np

from ..annotations.records import TimedMessage
from ..closing import Closing
from ..errors import OutputError


class SpooledMessages(Sequence[TimedMessage], Closing):
    """Messages in a temporary file, in the order given; `in_order()` sorts them by
    `TimedMessage.sort_key` (stable, as `sorted` is). Close it (or use it as a context manager)
    when done."""

    def __init__(self, messages: Iterable[TimedMessage]) -> None:
        self._log_times, self._ranks, self._indices = array("q"), array("q"), array("q")
        self._offsets = array("q", [0])
        try:
            self._file = tempfile.TemporaryFile()  # noqa: SIM115 (closed by close)
            for message in messages:
                data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
                self._file.write(data)
                self._offsets.append(self._offsets[-1] + len(data))
                log_time, rank, index = message.sort_key
                self._log_times.append(log_time)
                self._ranks.append(rank)
                self._indices.append(index)
            self._file.flush()
        except OSError as exc:
            self.close()
            raise OutputError(
                f"cannot write the output messages' temporary file: {exc.strerror or exc}"
            ) from exc
        except BaseException:  # a message that cannot be made: no file left open
            self.close()
            raise

    def __len__(self) -> int:
        return len(self._log_times)

    @overload
    def __getitem__(self, position: int) -> TimedMessage: ...

    @overload
    def __getitem__(self, position: slice) -> list[TimedMessage]: ...

    def __getitem__(self, position: int | slice) -> TimedMessage | list[TimedMessage]:
        if isinstance(position, slice):
            return [self[i] for i in range(len(self))[position]]
        if position < 0:
            position += len(self)
        if not 0 <= position < len(self):
            raise IndexError("message position out of range")
        start, stop = self._offsets[position], self._offsets[position + 1]
        data = os.pread(self._file.fileno(), stop - start, start)
        if len(data) != stop - start:
            raise OSError("output messages' temporary file: bytes missing")
        message: TimedMessage = pickle.loads(data)
        return message

    def __iter__(self) -> Iterator[TimedMessage]:
        return (self[i] for i in range(len(self)))

    def in_order(self) -> Iterator[TimedMessage]:
        """The messages by (log time, type rank, index), ties in the order given."""
        if not len(self):
            return iter(())
        keys = [np.frombuffer(a, np.int64) for a in (self._indices, self._ranks, self._log_times)]
        return (self[int(i)] for i in np.lexsort(keys))

    def close(self) -> None:
        file = getattr(self, "_file", None)  # absent when it could not be created
        if file is not None:
            file.close()


def in_order(messages: Sequence[TimedMessage]) -> Iterator[TimedMessage]:
    """Any sequence of messages sorted by `sort_key` (stable), a spool read back one by one."""
    if isinstance(messages, SpooledMessages):
        return messages.in_order()
    return iter(sorted(messages, key=lambda m: m.sort_key))
