"""Blocking waits of the main thread that still hear Ctrl-C and SIGTERM at once.

A signal may be delivered to any thread of the process (an OpenCV or verification thread, say);
Python then only flags it, and the main thread runs the handler when it next executes Python
code. A main thread blocked without a timeout (Future.result(), Queue.get()) would hear the
signal only when the wait ends, minutes later on a long verification stage. These waits wake
up every POLL_S to let the handler run (and raise KeyboardInterrupt).
"""

from __future__ import annotations

import queue
from concurrent.futures import Future
from typing import TypeVar

T = TypeVar("T")

POLL_S = 0.1


def result(future: Future[T]) -> T:
    """`future.result()`, woken every POLL_S."""
    while True:
        try:
            return future.result(timeout=POLL_S)
        except TimeoutError:
            continue


def get(items: queue.Queue[T]) -> T:
    """`items.get()`, woken every POLL_S."""
    while True:
        try:
            return items.get(timeout=POLL_S)
        except queue.Empty:
            continue
