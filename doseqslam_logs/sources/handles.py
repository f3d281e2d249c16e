"""Open readers of one log, lent to one iteration at a time.

A run reads its log many times (the frames, the camera info, the odometry, frames again for
verification, the match images): each read borrows an idle reader of the source and gives it
back when done, so the file is opened about as often as it is read *at once* (two threads,
or two iterations interleaved), not once per read. Two iterations never share a reader:
each seeks its own.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator
from typing import Generic, TypeVar

T = TypeVar("T")


class HandlePool(Generic[T]):
    """Readers made by `open_one` (`first`: one already open), closed by `close_one`."""

    def __init__(
        self, open_one: Callable[[], T], close_one: Callable[[T], None], first: T | None = None
    ) -> None:
        self._open_one, self._close_one = open_one, close_one
        self._idle: list[T] = [] if first is None else [first]
        self._lock = threading.Lock()
        self._closed = False
        self.opened = 0 if first is None else 1  # readers made, for tests and benchmarks

    @contextlib.contextmanager
    def borrowed(self) -> Iterator[T]:
        """An idle reader (a new one when every reader is lent), given back on exit; closed
        instead when the pool was closed meanwhile."""
        with self._lock:
            handle = self._idle.pop() if self._idle else None
        if handle is None:
            handle = self._open_one()
            with self._lock:
                self.opened += 1
        try:
            yield handle
        finally:
            with self._lock:
                keep = not self._closed
                if keep:
                    self._idle.append(handle)
            if not keep:
                self._close_one(handle)

    def close(self) -> None:
        """Close the idle readers; lent ones close when they are given back."""
        with self._lock:
            self._closed, idle, self._idle = True, self._idle, []
        for handle in idle:
            self._close_one(handle)
