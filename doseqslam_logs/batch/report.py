"""What a batch prints: a line per finished log, a live status line on a terminal, a summary.

On a terminal, stderr carries one status line redrawn in place: logs done of total, failures,
elapsed time, ETA, and the frames done of each running log. Elsewhere (CI, files) nothing is
redrawn: each finished log's line starts with the overall counts instead. Lines of logs that
succeed go to stdout, of logs that fail to stderr (one line each, with the exit-code class).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import TextIO

from .job import Job, Outcome
from .runner import BatchPlan, BatchResult, Display

REDRAW_S = 0.2
CLEAR_LINE = "\r\x1b[K"


def _duration(seconds: float) -> str:
    seconds = max(0, round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    minutes, seconds = divmod(seconds, 60)
    if minutes < 60:
        return f"{minutes}:{seconds:02d} min"
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{seconds:02d} h"


def outcome_text(outcome: Outcome) -> str:
    if not outcome.ok:
        return f"FAILED ({outcome.error_kind}): {outcome.error}"
    c = outcome.counts
    return (
        f"ok: {c.frames} frames, {c.sequences} sequences, {c.loop_closures} loop closures, "
        f"{c.skipped} skipped frames, {outcome.timings.get('total_s', 0.0):.1f} s"
        + (f"; WARNING: {outcome.warning}" if outcome.warning else "")
    )


class ConsoleDisplay(Display):
    def __init__(
        self,
        out: TextIO | None = None,
        err: TextIO | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.out = out or sys.stdout
        self.err = err or sys.stderr
        self.live = self.err.isatty()
        self.clock = clock
        self.started = clock()
        self.total = self.done = self.failed = 0
        self.total_bytes = self.done_bytes = 0
        self.frames: dict[str, tuple[Job, int, int | None]] = {}  # running: done, expected
        self.stages: dict[str, str] = {}  # running: the stage after the replay, if any
        self._drawn = False
        self._last_draw = 0.0

    def start(self, plan: BatchPlan) -> None:
        self.started = self.clock()
        self.total = len(plan.to_run)
        self.total_bytes = sum(job.size for job in plan.to_run)
        if plan.up_to_date:
            self._line(
                self.out,
                f"{len(plan.up_to_date)} of {len(plan.to_run) + len(plan.up_to_date)} logs "
                "up to date (manifest): skipped; --force redoes them",
            )

    def expected(self, job: Job, total: int | None) -> None:
        self.frames[job.key] = (job, 0, total)

    def progress(self, job: Job, done: int) -> None:
        total = self.frames.get(job.key, (job, 0, None))[2]
        self.frames[job.key] = (job, done, total)

    def stage(self, job: Job, name: str) -> None:
        if name != "replay":
            self.stages[job.key] = name

    def finished(self, job: Job, outcome: Outcome) -> None:
        self.frames.pop(job.key, None)
        self.stages.pop(job.key, None)
        self.done += 1
        self.done_bytes += job.size
        self.failed += 0 if outcome.ok else 1
        prefix = "" if self.live else f"[{self.overall()}] "
        stream = self.out if outcome.ok else self.err
        self._line(stream, f"{prefix}{job.name}: {outcome_text(outcome)}")

    def tick(self) -> None:
        now = self.clock()
        if self.live and now - self._last_draw >= REDRAW_S:
            self._last_draw = now
            self._draw()

    def close(self) -> None:
        self._clear()

    def overall(self) -> str:
        elapsed = self.clock() - self.started
        eta = self._eta(elapsed)
        return (
            f"{self.done}/{self.total} logs, {self.failed} failed, {_duration(elapsed)}"
            f"{'' if eta is None else f', ETA {_duration(eta)}'}"
        )

    def _eta(self, elapsed: float) -> float | None:
        """Remaining time from the bytes done so far (running logs count by frames done)."""
        running = sum(
            job.size * min(done / total, 1.0) for job, done, total in self.frames.values() if total
        )
        done = self.done_bytes + running
        if done <= 0 or self.total_bytes <= 0:
            return None
        return elapsed * max(self.total_bytes - done, 0) / done

    def _draw(self) -> None:
        logs = " | ".join(
            f"{job.name} {done}/{total if total is not None else '?'}"
            + (f" {self.stages[job.key]}" if job.key in self.stages else "")
            for job, done, total in self.frames.values()
        )
        self.err.write(f"{CLEAR_LINE}batch: {self.overall()}" + (f" | {logs}" if logs else ""))
        self.err.flush()
        self._drawn = True

    def _clear(self) -> None:
        if self._drawn:
            self.err.write(CLEAR_LINE)
            self.err.flush()
            self._drawn = False

    def _line(self, stream: TextIO, text: str) -> None:
        self._clear()
        stream.write(text + "\n")
        stream.flush()
        if self.live:
            self._draw()


def summary_table(result: BatchResult) -> str:
    """One row per log run (failures last), then the totals."""
    plan = result.planned
    jobs = {job.key: job for job in plan.to_run}
    rows = [["status", "frames", "seqs", "loops", "skipped", "time s", "log"]]
    outcomes = sorted(result.outcomes.values(), key=lambda o: (not o.ok, jobs[o.key].name))
    for o in outcomes:
        c = o.counts
        numbers = [c.frames, c.sequences, c.loop_closures, c.skipped] if o.ok else ["-"] * 4
        name = jobs[o.key].name + ("" if o.ok else f"  ({o.error_kind})")
        name += "  (feature-poor: see its line or the manifest)" if o.warning else ""
        seconds = f"{o.timings.get('total_s', 0.0):.1f}" if o.timings else "-"
        rows.append(["ok" if o.ok else "FAILED", *map(str, numbers), seconds, name])
    widths = [max(len(row[i]) for row in rows) for i in range(6)]
    lines = [
        "  ".join(
            [row[0].ljust(widths[0])]
            + [value.rjust(width) for value, width in zip(row[1:6], widths[1:], strict=True)]
            + [row[6]]
        )
        for row in rows
    ]
    return "\n".join([*lines, totals_line(result)]) if outcomes else totals_line(result)


def totals_line(result: BatchResult) -> str:
    plan = result.planned
    ok = [o for o in result.outcomes.values() if o.ok]
    frames = sum(o.counts.frames for o in ok)
    loops = sum(o.counts.loop_closures for o in ok)
    not_run = len(plan.to_run) - len(result.outcomes)
    parts = [
        f"{len(plan.to_run) + len(plan.up_to_date)} logs: {len(ok)} annotated",
        f"{len(plan.up_to_date)} up to date",
        f"{len(result.failed)} failed",
    ]
    if not_run:
        parts.append(f"{not_run} not run")
    poor = sum(bool(o.warning) for o in ok)
    if poor:
        parts.append(f"{poor} too poor in features to trust a count of 0 (see their lines)")
    return f"{', '.join(parts)}; {frames} frames, {loops} loop closures in {result.wall_s:.1f} s"
