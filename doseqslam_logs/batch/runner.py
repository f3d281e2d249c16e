"""The batch driver: decide what to run, hand it to an engine, record every outcome.

Only the driver writes the manifest, one line per finished attempt, as soon as it finishes:
an interrupted batch keeps everything done before the interruption.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from .. import __version__
from ..detector import Parameters
from ..errors import OutputError
from ..pipeline.annotate import AnnotateOptions
from ..sources.digest import source_sha256
from .discovery import LogInput
from .engine import EngineSettings, create_engine
from .job import Job, Outcome, options_hash
from .manifest import MANIFEST_NAME, Entry, FileStamp, append_entry, is_up_to_date, last_entries


@dataclass(frozen=True)
class BatchPlan:
    to_run: list[Job]
    up_to_date: list[Job]


@dataclass
class BatchResult:
    planned: BatchPlan
    outcomes: dict[str, Outcome] = field(default_factory=dict)  # by job key, finishing order
    wall_s: float = 0.0

    @property
    def failed(self) -> list[Outcome]:
        return [o for o in self.outcomes.values() if not o.ok]


def _current_sha256(path: Path, last: Entry) -> str:
    """The log's sha256; the recorded one when size and mtime are those recorded with it;
    "" when it cannot be read (the log then runs again, and its run reports the problem)."""
    try:
        if last.stamp is not None and last.stamp == FileStamp.of(path):
            return last.sha256
        return source_sha256(path)
    except OSError:
        return ""


def plan_batch(
    logs: Sequence[LogInput],
    outdir: Path,
    params: Parameters,
    options: AnnotateOptions,
    force: bool = False,
) -> BatchPlan:
    """Split the logs into those to run and those whose last run is still good."""
    outdir = outdir.resolve()
    last = {} if force else last_entries(outdir / MANIFEST_NAME)
    hashes = (params.hash, options_hash(options), __version__)
    to_run, up_to_date = [], []
    for log in logs:
        job = Job(
            key=str(log.path),
            input=log.path,
            output=outdir / log.relative_output,
            params=params,
            options=options,
            name=str(log.relative_output.parent / log.path.name),
            size=_size(log.path),
        )
        previous = last.get(job.key)
        current = "" if previous is None else _current_sha256(log.path, previous)
        if is_up_to_date(previous, job.output, *hashes, current):
            up_to_date.append(job)
        else:
            to_run.append(job)
    return BatchPlan(to_run, up_to_date)


def _size(path: Path) -> int:
    try:
        return FileStamp.of(path).size
    except OSError:
        return 0


class _Recorder:
    """The engine's Events: writes the manifest, then passes everything to the display."""

    def __init__(
        self, plan: BatchPlan, outdir: Path, engine: str, display: Display, result: BatchResult
    ) -> None:
        self.jobs = {job.key: job for job in plan.to_run}
        self.manifest = outdir.resolve() / MANIFEST_NAME
        self.engine = engine
        self.display = display
        self.result = result

    def expected(self, key: str, total: int | None) -> None:
        self.display.expected(self.jobs[key], total)

    def progress(self, key: str, done: int) -> None:
        self.display.progress(self.jobs[key], done)

    def stage(self, key: str, name: str) -> None:
        self.display.stage(self.jobs[key], name)

    def tick(self) -> None:
        self.display.tick()

    def finished(self, outcome: Outcome) -> None:
        job = self.jobs[outcome.key]
        append_entry(self.manifest, self._entry(job, outcome))
        self.result.outcomes[outcome.key] = outcome
        self.display.finished(job, outcome)

    def _entry(self, job: Job, outcome: Outcome) -> Entry:
        return Entry(
            input=job.key,
            output=str(job.output),
            status=outcome.status,
            sha256=outcome.sha256,
            stamp=outcome.stamp,
            parameters_hash=job.params.hash,
            options_hash=options_hash(job.options),
            tool_version=__version__,
            engine=self.engine,
            counts=outcome.counts,
            timings=outcome.timings,
            error=outcome.error,
            exit_code=outcome.exit_code,
            finished_at=datetime.now(timezone.utc).isoformat(timespec="seconds"),
            warning=outcome.warning,
        )


class Display:
    """What the driver shows while a batch runs (see report.py); the default shows nothing."""

    def start(self, plan: BatchPlan) -> None: ...

    def expected(self, job: Job, total: int | None) -> None: ...

    def progress(self, job: Job, done: int) -> None: ...

    def stage(self, job: Job, name: str) -> None: ...

    def finished(self, job: Job, outcome: Outcome) -> None: ...

    def tick(self) -> None: ...

    def close(self) -> None: ...


def run_batch(
    plan: BatchPlan,
    outdir: Path,
    engine: str = "local",
    settings: EngineSettings | None = None,
    display: Display | None = None,
    clock: Callable[[], float] = time.perf_counter,
) -> BatchResult:
    """Run the plan's jobs on the engine; every outcome is in the manifest when this returns
    (or raises KeyboardInterrupt: then the outcomes so far are)."""
    settings = settings or EngineSettings(jobs=1)
    display = display or Display()
    chosen = create_engine(engine, settings)  # before any output: a missing extra is exit 2
    try:
        outdir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{outdir}: cannot create the output folder: {exc.strerror}") from exc
    result = BatchResult(plan)
    started = clock()
    display.start(plan)
    try:
        if plan.to_run:
            chosen.run(plan.to_run, _Recorder(plan, outdir, chosen.name, display, result))
    finally:
        display.close()
        result.wall_s = clock() - started
    return result
