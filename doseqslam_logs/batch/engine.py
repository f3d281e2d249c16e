"""What an engine is: something that runs `run_job` for every Job and reports back.

A new engine is one module with a `create(settings) -> Engine` function, plus its name in
ENGINES. Engines only run jobs: the driver decides what to run and writes the manifest.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:  # a job runs the pipeline (OpenCV, SciPy): not needed to name the engines
    from .job import Job, Outcome

# engine name -> module (imported only when chosen, so optional extras stay optional)
ENGINES = {
    "local": "doseqslam_logs.batch.local",
    "ray": "doseqslam_logs.batch.ray_engine",
}


@dataclass(frozen=True)
class EngineSettings:
    jobs: int  # logs at a time (local engine)
    address: str | None = None  # cluster address (ray)


class Events(Protocol):
    """Called by an engine in the driver's main thread."""

    def expected(self, key: str, total: int | None) -> None: ...

    def progress(self, key: str, done: int) -> None: ...

    def stage(self, key: str, name: str) -> None:
        """A stage of the log's run began (pipeline.annotate.STAGES)."""

    def finished(self, outcome: Outcome) -> None: ...

    def tick(self) -> None:
        """Called a few times a second while jobs run (to redraw elapsed time and ETA)."""


class Engine(Protocol):
    name: str

    def run(self, jobs: Sequence[Job], events: Events) -> None:
        """Run every job, calling events.finished once for each; on KeyboardInterrupt stop
        every worker (no output is left half-written) and re-raise."""


def create_engine(name: str, settings: EngineSettings) -> Engine:
    module = importlib.import_module(ENGINES[name])
    engine: Engine = module.create(settings)
    return engine
