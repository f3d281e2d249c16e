"""The Ray engine: one Ray task per log (num_cpus=1), on an existing cluster or a local instance.

Every node must see the logs and OUTDIR under the same paths (a shared file system) and have
doseqslam-logs installed. Tasks only annotate; the driver gathers their outcomes with ray.wait
and writes the manifest. A task whose worker dies is not retried: it is reported as failed
(a re-run of the batch redoes it), as with the local engine.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections.abc import Sequence
from dataclasses import replace
from types import FrameType
from typing import Any

from ..errors import UsageError
from .engine import EngineSettings, Events
from .job import Job, Outcome, crashed_outcome, run_job

POLL_S = 0.5
STOP_GRACE_S = 5.0  # after cancelling, how long tasks may take to remove temporary files


def _import_ray() -> Any:
    try:
        import ray
    except ImportError:
        raise UsageError(
            "--engine ray needs Ray: pip install 'doseqslam-logs[ray]' (or pip install ray)"
        ) from None
    return ray


def _put_back_sigterm_handler(previous: Any, raised: list[BaseException]) -> None:
    """ray.init replaces the SIGTERM handler (with one that exits at once): put the caller's
    back, so that SIGTERM stops the batch like Ctrl-C (tasks cancelled, Ray shut down), and
    keep what it raises in `raised`."""
    if not callable(previous) or threading.current_thread() is not threading.main_thread():
        return

    def on_sigterm(signum: int, frame: FrameType | None) -> None:
        try:
            previous(signum, frame)
        except BaseException as exc:
            raised.append(exc)
            raise

    signal.signal(signal.SIGTERM, on_sigterm)


def _annotate_task(job: Job) -> Outcome:
    # One CPU per task: a second frame-preparing thread would take another task's core.
    return run_job(replace(job, options=replace(job.options, workers=1)))


class RayEngine:
    name = "ray"

    def __init__(self, address: str | None) -> None:
        self.ray = _import_ray()
        self.address = address

    def run(self, jobs: Sequence[Job], events: Events) -> None:
        ray = self.ray
        started_here = not ray.is_initialized()
        previous = signal.getsignal(signal.SIGTERM)
        raised: list[BaseException] = []
        try:
            if started_here:
                # address None: RAY_ADDRESS if set, else a new local instance (no dashboard:
                # the batch prints its own progress).
                local = {"include_dashboard": False} if self.address is None else {}
                ray.init(
                    address=self.address, logging_level=logging.ERROR, log_to_driver=False, **local
                )
            _put_back_sigterm_handler(previous, raised)
            self._run_tasks(jobs, events)
        except KeyboardInterrupt as exc:
            # ray.wait turns what a signal handler raises into a plain KeyboardInterrupt.
            if raised and exc is not raised[0]:
                raise raised[0] from None
            raise
        except SystemExit as exc:
            # SIGTERM during ray.init: Ray's own handler exits; raise what ours would have.
            if exc.code == signal.SIGTERM and callable(previous):
                previous(signal.SIGTERM, None)
            raise
        finally:
            if started_here:
                ray.shutdown()
            if threading.current_thread() is threading.main_thread():
                signal.signal(signal.SIGTERM, previous)

    def _run_tasks(self, jobs: Sequence[Job], events: Events) -> None:
        ray = self.ray
        task = ray.remote(num_cpus=1, max_retries=0)(_annotate_task)
        pending: dict[Any, Job] = {task.remote(job): job for job in jobs}
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1, timeout=POLL_S)
                events.tick()
                for ref in done:
                    job = pending.pop(ref)
                    events.finished(self._outcome(ref, job))
        except BaseException:
            self._cancel(list(pending))
            raise

    def _outcome(self, ref: Any, job: Job) -> Outcome:
        try:
            outcome: Outcome = self.ray.get(ref)
        except self.ray.exceptions.RayError as exc:
            detail = " ".join(str(exc).split())[:300]
            return crashed_outcome(job, f"{type(exc).__name__}: {detail}")
        return outcome

    def _cancel(self, refs: list[Any]) -> None:
        """Cancel gently (KeyboardInterrupt in the task: temporary files are removed), then
        force the ones still running after a grace period."""
        ray = self.ray
        for ref in refs:
            ray.cancel(ref)
        deadline = time.monotonic() + STOP_GRACE_S
        remaining = refs
        while remaining and time.monotonic() < deadline:
            _, remaining = ray.wait(remaining, num_returns=len(remaining), timeout=0.2)
        for ref in remaining:
            ray.cancel(ref, force=True)


def create(settings: EngineSettings) -> RayEngine:
    return RayEngine(settings.address)
