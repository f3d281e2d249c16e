"""One log of a batch (`Job`), what became of it (`Outcome`), and the work itself (`run_job`).

`run_job` is what every engine runs in its worker processes: it never raises for a bad log
(the error becomes a failed Outcome), only KeyboardInterrupt passes through.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from ..detector import Parameters
from ..detector.fingerprint import fingerprint
from ..errors import DoseqslamError, ExitCode, OutputError
from ..pipeline.annotate import (
    AnnotateOptions,
    AnnotateResult,
    annotate_log,
)
from ..pipeline.stages import STAGES
from ..sources.digest import source_sha256
from .manifest import Counts, FileStamp

# (input key, "expected" | "progress" | "stage", number): frames expected or done, or the
# index in STAGES of the stage that began, from a worker.
Notify = Callable[[str, str, int | None], None]

CRASHED = "worker crashed"


# AnnotateOptions fields that change speed or memory, never the output.
NOT_IN_OUTPUT = frozenset({"workers", "verification_cache_bytes"})


def options_hash(options: AnnotateOptions) -> str:
    """Fingerprint of the options that change the output."""
    values = dataclasses.asdict(options)
    return fingerprint({k: v for k, v in values.items() if k not in NOT_IN_OUTPUT})


def error_class(code: int) -> str:
    """The exit-code class of an error, as the summary names it: "3 unreadable input"."""
    try:
        name = ExitCode(code).name.lower().replace("_", " ")
    except ValueError:
        name = "unknown"
    return f"{code} {name}"


@dataclass(frozen=True)
class Job:
    key: str  # the log's absolute path, as the manifest records it
    input: Path
    output: Path
    params: Parameters
    options: AnnotateOptions
    name: str = ""  # the log as reports show it: its path relative to the inputs' folder
    size: int = 0  # bytes, for the ETA


@dataclass(frozen=True)
class Outcome:
    key: str
    status: str  # "ok" | "failed"
    sha256: str = ""
    stamp: FileStamp | None = None
    counts: Counts = field(default_factory=Counts)
    timings: dict[str, float] = field(default_factory=dict)
    error: str = ""
    exit_code: int = 0
    error_kind: str = ""  # "3 unreadable input", "worker crashed", ...
    # The run's feature-poor warning and advice (pipeline.feature_health), "" when healthy.
    warning: str = ""

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def crashed_outcome(job: Job, detail: str) -> Outcome:
    """The outcome of a log whose worker process died (killed, out of memory, a crash in C)."""
    return Outcome(
        job.key,
        "failed",
        sha256=_sha256_or_empty(job.input),
        stamp=_stamp_or_none(job.input),
        error=f"{job.input}: {CRASHED}: {detail}",
        exit_code=int(ExitCode.INTERNAL),
        error_kind=CRASHED,
    )


def _sha256_or_empty(path: Path) -> str:
    try:
        return source_sha256(path)
    except OSError:
        return ""


def _stamp_or_none(path: Path) -> FileStamp | None:
    try:
        return FileStamp.of(path)
    except OSError:
        return None


def _ok_outcome(job: Job, result: AnnotateResult, stamp: FileStamp | None, wall: float) -> Outcome:
    replay = result.replay
    counts = Counts(
        frames=replay.frames,
        sequences=len(replay.decisions),
        loop_closures=result.loop_closures,  # reported: verified when verification is on
        skipped=result.counts.skipped_total,
    )
    timings = {"total_s": round(wall, 3), "replay_s": round(replay.wall_time_s, 3)}
    warning = "" if result.health is None else result.health.note()
    return Outcome(job.key, "ok", result.source_sha256, stamp, counts, timings, warning=warning)


def run_job(job: Job, notify: Notify | None = None) -> Outcome:
    """Annotate one log; every error becomes a failed Outcome naming the log."""
    started = time.perf_counter()
    stamp = _stamp_or_none(job.input)  # before reading: a change while we run shows next time

    def progress(done: int) -> None:
        if notify is not None:
            notify(job.key, "progress", done)

    def expected(total: int | None) -> None:
        if notify is not None:
            notify(job.key, "expected", total)

    def stage(name: str) -> None:
        if notify is not None:
            notify(job.key, "stage", STAGES.index(name))

    try:
        try:
            job.output.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"{job.output.parent}: cannot create: {exc.strerror}") from exc
        result = annotate_log(
            job.input, job.output, job.params, job.options, progress, expected, stage
        )
    except DoseqslamError as exc:
        code, kind, message = int(exc.exit_code), error_class(int(exc.exit_code)), str(exc)
    except Exception as exc:  # a bug in one log must not stop the batch
        code = int(ExitCode.INTERNAL)
        kind = error_class(code)
        message = f"{job.input}: internal error: {type(exc).__name__}: {exc}"
    else:
        return _ok_outcome(job, result, stamp, time.perf_counter() - started)
    return Outcome(
        job.key,
        "failed",
        sha256=_sha256_or_empty(job.input),
        stamp=stamp,
        timings={"total_s": round(time.perf_counter() - started, 3)},
        error=" ".join(message.split()),
        exit_code=code,
        error_kind=kind,
    )
