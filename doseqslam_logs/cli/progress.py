"""A progress line on stderr when it is a terminal; silent otherwise (logs, CI, batch)."""

from __future__ import annotations

import sys
import time
from typing import TextIO

# What each stage after the replay shows (the replay shows its frames).
STAGE_LINES = {
    "verify": "verifying the candidate pairs geometrically",
    "metric": "metric poses of the accepted pairs",
    "write": "writing the output",
}


class Progress:
    """`Progress(total, label)(done)` redraws at most ten times a second; `stage(name)` puts
    each later stage of the run on a line of its own, so that a long wait says what it is."""

    def __init__(self, total: int | None, label: str, stream: TextIO | None = None) -> None:
        self.total = total
        self.label = label
        self.stream = stream or sys.stderr
        self.enabled = self.stream.isatty()
        self._start = time.perf_counter()
        self._last_draw = 0.0
        self._line_open = False  # a line is drawn and not yet ended

    def __call__(self, done: int) -> None:
        now = time.perf_counter()
        if not self.enabled or (now - self._last_draw < 0.1 and done != self.total):
            return
        self._last_draw = now
        rate = done / max(now - self._start, 1e-9)
        if self.total:
            width = 30
            filled = int(width * min(done / self.total, 1.0))
            bar = "#" * filled + "-" * (width - filled)
            text = f"{self.label} [{bar}] {done}/{self.total} frames, {rate:.0f} frames/s"
        else:
            text = f"{self.label} {done} frames, {rate:.0f} frames/s"
        self._write("\r" + text)

    def stage(self, name: str) -> None:
        if self.enabled and name in STAGE_LINES:
            self._end_line()
            self._write(f"{self.label}: {STAGE_LINES[name]}")

    def close(self) -> None:
        if self.enabled:
            self._end_line()

    def _write(self, text: str) -> None:
        self.stream.write(text)
        self.stream.flush()
        self._line_open = True

    def _end_line(self) -> None:
        if self._line_open:
            self.stream.write("\n")
            self.stream.flush()
            self._line_open = False
