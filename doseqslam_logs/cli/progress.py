"""Progress of a run on stderr, stage by stage.

On a terminal: a bar for each stage with its count and the time left, redrawn at most ten
times a second. Off a terminal (batch logs, CI, `nohup`): nothing for a run that ends within
QUIET_S, so that short runs and errors stay one line; past it, a line as each stage begins and
one every LINE_EVERY_S seconds with the count and the time left.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

from ..pipeline.stages import StageObserver

# What each stage counts, and what its line says.
UNITS = {"replay": "frames", "verify": "sequences", "metric": "fits", "write": "messages"}
STAGE_LINES = {
    "replay": "replaying the detector",
    "verify": "verifying the candidate pairs geometrically",
    "metric": "metric poses of the accepted pairs",
    "write": "writing the output",
    # evaluate OUT.mcap
    "read": "reading the annotations",
    "truth": "reading the ground truth",
    "score": "scoring the run",
    "draw": "drawing the pictures",
}
QUIET_S = 10.0  # off a terminal, a run that ends before this prints nothing
LINE_EVERY_S = 60.0  # off a terminal, a progress line this often
REDRAW_S = 0.1  # on a terminal, the bar's redraws


def remaining(done: int, total: int | None, elapsed_s: float) -> str:
    """The time left at the rate so far, as ", M:SS left" ("" before a rate is known)."""
    if not total or done <= 0 or done >= total or elapsed_s <= 0:
        return ""
    seconds = round(elapsed_s * (total - done) / done)
    minutes, seconds = divmod(seconds, 60)
    hours, minutes = divmod(minutes, 60)
    clock = f"{hours}:{minutes:02d}:{seconds:02d}" if hours else f"{minutes}:{seconds:02d}"
    return f", {clock} left"


class Progress(StageObserver):
    """The run's progress: `Progress(total, label)(frames done)` for the replay, and as the
    run's StageObserver the later stages (`started`, `advanced`)."""

    def __init__(self, total: int | None, label: str, stream: TextIO | None = None) -> None:
        self.total = total  # the replay's frames (None: unknown)
        self.label = label
        self.stream = stream or sys.stderr
        self.terminal = self.stream.isatty()
        self._run_start = time.perf_counter()
        self._stage_start = self._run_start
        self._last_draw = 0.0
        self._line_open = False  # a bar is drawn and not yet ended

    def __call__(self, done: int) -> None:
        self.advanced("replay", done, self.total)

    def started(self, stage: str) -> None:
        now = time.perf_counter()
        self._stage_start = now
        if self.terminal:
            self._last_draw = 0.0  # the new stage's bar at once
            if stage != "replay":
                self._end_line()
                self._write(f"{self.label}: {STAGE_LINES.get(stage, stage)}")
        elif self._past_quiet():
            self._last_draw = now  # its first count a LINE_EVERY_S later
            self._line(f"{self.label}: {STAGE_LINES.get(stage, stage)}")

    def advanced(self, stage: str, done: int, total: int | None) -> None:
        now = time.perf_counter()
        if self.terminal:
            if now - self._last_draw < REDRAW_S and done != total:
                return
        elif not self._past_quiet() or now - self._last_draw < LINE_EVERY_S:
            return
        self._last_draw = now
        text = self._count(stage, done, total, now - self._stage_start)
        if self.terminal:
            self._write("\r" + text)
        else:
            self._line(text)

    def close(self) -> None:
        if self.terminal:
            self._end_line()

    def _count(self, stage: str, done: int, total: int | None, elapsed_s: float) -> str:
        unit = UNITS.get(stage, "")
        rate = f", {done / elapsed_s:.0f} {unit}/s" if elapsed_s > 0 else ""
        if not total:
            return f"{self.label} {stage} {done} {unit}{rate}"
        width = 30
        filled = int(width * min(done / total, 1.0))
        bar = "#" * filled + "-" * (width - filled)
        left = remaining(done, total, elapsed_s)
        return f"{self.label} {stage} [{bar}] {done}/{total} {unit}{rate}{left}"

    def _past_quiet(self) -> bool:
        return time.perf_counter() - self._run_start >= QUIET_S

    def _line(self, text: str) -> None:
        self.stream.write(text + "\n")
        self.stream.flush()

    def _write(self, text: str) -> None:
        self.stream.write(text)
        self.stream.flush()
        self._line_open = True

    def _end_line(self) -> None:
        if self._line_open:
            self.stream.write("\n")
            self.stream.flush()
            self._line_open = False
