"""The local engine: logs annotated in parallel worker processes on this machine.

Processes are started with "spawn": OpenCV's thread pools deadlock in a forked child. Workers
send frame progress through a queue. A worker that dies (killed, out of memory, a crash in C
code) breaks a ProcessPoolExecutor for every log it was running, and which one killed it is
unknown: those logs are then run again one at a time in a fresh pool, so only the culprit
fails and the others go on. On KeyboardInterrupt (Ctrl-C, or SIGTERM via the command line)
the workers get SIGTERM, which they turn into KeyboardInterrupt: annotate_log removes its
temporary file, and no output appears half-written.

A worker must not outlive its batch, even one killed outright (SIGKILL, the OOM killer): on
Linux each worker asks the kernel for SIGTERM when its parent dies (PR_SET_PDEATHSIG), a
thread of it watches the parent pid too (other systems, idle workers), and an orphaned worker
gets ORPHAN_GRACE_S to remove its temporary file before it exits regardless.
multiprocessing's resource tracker then goes too: it ends when the last process holding its
pipe (the batch and its workers) is gone.
"""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing
import os
import queue
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import replace
from multiprocessing.context import SpawnContext
from types import FrameType
from typing import Any

from ..pipeline.stages import STAGES
from .engine import EngineSettings, Events
from .job import Job, Outcome, crashed_outcome, run_job

POLL_S = 0.2  # how often the driver drains progress and redraws
PROGRESS_EVERY_S = 0.25  # a worker reports frames done at most this often
STOP_GRACE_S = 5.0  # after SIGTERM, how long a worker may take to clean up before SIGKILL
# A worker whose batch died exits this long after it heard of it, whatever it was doing (the
# promise: no process of ours outlives its batch by more than a second).
ORPHAN_GRACE_S = 0.5
PR_SET_PDEATHSIG = 1  # linux/prctl.h
PARENT_POLL_S = 0.2  # how often a worker's watcher thread checks that its batch still runs

# In each worker process: the progress queue, when each log last reported, whether a log runs,
# the batch process that started it, whether it is stopping, and when it exits regardless.
_queue: Any = None
_last_report: dict[str, float] = {}
_busy = False
_parent_pid = 0
_stopping = False
_exit_timer: threading.Timer | None = None


def _exit_terminated() -> None:
    os._exit(128 + signal.SIGTERM)


def _on_sigterm(signum: int, frame: FrameType | None) -> None:
    global _stopping
    if not _busy:
        _exit_terminated()  # idle: nothing to clean up, and no traceback
    if os.getppid() != _parent_pid:  # orphaned: nobody will SIGKILL us after a grace period
        _exit_soon()
    if not _stopping:  # a second KeyboardInterrupt could cut the first one's clean-up short
        _stopping = True
        raise KeyboardInterrupt()  # unwinds annotate_log, which removes its temporary file


def _exit_soon() -> None:
    global _exit_timer
    if _exit_timer is None:
        _exit_timer = threading.Timer(ORPHAN_GRACE_S, _exit_terminated)
        _exit_timer.daemon = True
        _exit_timer.start()


def _die_with_parent(parent_pid: int) -> None:
    """SIGTERM when the batch process dies, from the kernel (Linux) and from a thread that
    watches the parent pid (everywhere; also where prctl is refused, e.g. by a sandbox).

    The kernel's signal follows the death of the thread that started the worker: the driver's
    main thread (ProcessPoolExecutor spawns from `submit`), which ends only with the process.
    It may be delivered to any thread of the worker, and an idle worker's main thread, blocked
    reading its next job, would not run the handler: the watcher signals that thread itself."""
    _parent_death_signal()
    threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True).start()
    if os.getppid() != parent_pid:  # it died before prctl took effect
        _exit_terminated()


def _parent_death_signal() -> None:
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)


def _watch_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(PARENT_POLL_S)
    main = threading.main_thread().ident
    if main is not None:
        signal.pthread_kill(main, signal.SIGTERM)


def _init_worker(progress_queue: Any, parent_pid: int) -> None:
    global _queue, _parent_pid
    _queue, _parent_pid = progress_queue, parent_pid
    # The driver decides when to stop: Ctrl-C reaches the whole process group, but only the
    # driver acts on it (it then sends SIGTERM, which cleans up like Ctrl-C would).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _on_sigterm)
    _die_with_parent(parent_pid)


def _notify(key: str, kind: str, value: int | None) -> None:
    now = time.monotonic()
    if kind == "progress" and now - _last_report.get(key, 0.0) < PROGRESS_EVERY_S:
        return
    _last_report[key] = now
    with contextlib.suppress(Exception):  # progress is a nicety: never fail a log over it
        _queue.put_nowait((key, kind, value))


def _work(job: Job) -> Outcome:
    global _busy
    _busy = True
    try:
        return run_job(job, _notify)
    except KeyboardInterrupt:
        # Stopped by the driver: annotate_log has removed its temporary file on the way up.
        os._exit(128 + signal.SIGTERM)
    finally:
        _busy = False


class LocalEngine:
    name = "local"

    def __init__(self, jobs: int, work: Callable[[Job], Outcome] = _work) -> None:
        self.jobs = max(1, jobs)
        self.work = work  # what a worker runs per job (tests pass one that crashes)

    def run(self, jobs: Sequence[Job], events: Events) -> None:
        context = multiprocessing.get_context("spawn")
        if self.jobs > 1:
            # The processes already keep every core busy: a second frame-preparing thread per
            # log would only compete with the other logs for the same cores.
            jobs = [replace(job, options=replace(job.options, workers=1)) for job in jobs]
        waiting = deque(jobs)
        while waiting:
            suspects = self._run_pool(waiting, self.jobs, context, events)
            for job in suspects:  # alone, so that a crash names its log
                if self._run_pool(deque([job]), 1, context, events):
                    events.finished(crashed_outcome(job, "the worker process died"))

    def _run_pool(
        self, waiting: deque[Job], size: int, context: SpawnContext, events: Events
    ) -> list[Job]:
        """Run jobs from `waiting` until it is empty, or the pool breaks: then return the
        jobs that were running (one of them crashed it)."""
        # A fresh queue per pool: a worker killed while writing could leave a queue locked.
        progress_queue = context.Queue()
        pool = ProcessPoolExecutor(
            min(size, len(waiting)),
            mp_context=context,
            initializer=_init_worker,
            initargs=(progress_queue, os.getpid()),
        )
        running: dict[Future[Outcome], Job] = {}
        try:
            while waiting or running:
                while waiting and len(running) < size:
                    job = waiting.popleft()
                    running[pool.submit(self.work, job)] = job
                done, _ = wait(running, timeout=POLL_S, return_when=FIRST_COMPLETED)
                _drain(progress_queue, events)
                events.tick()
                broken = self._collect(done, running, events)
                if broken:
                    return broken
            return []
        except BaseException:
            _stop_workers(pool)
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
            progress_queue.close()
            progress_queue.cancel_join_thread()

    @staticmethod
    def _collect(
        done: set[Future[Outcome]], running: dict[Future[Outcome], Job], events: Events
    ) -> list[Job]:
        """Report finished jobs; if the pool broke, return every job it was running."""
        broken = False
        for future in done:
            job = running.pop(future)
            try:
                outcome = future.result()
            except BrokenProcessPool:
                broken = True
                running[future] = job
                continue
            except Exception as exc:  # e.g. a job that cannot be sent to the worker
                outcome = crashed_outcome(job, f"{type(exc).__name__}: {exc}")
            events.finished(outcome)
        if not broken:
            return []
        suspects = list(running.values())
        running.clear()
        return suspects


def _drain(progress_queue: Any, events: Events) -> None:
    while True:
        try:
            key, kind, value = progress_queue.get_nowait()
        except (queue.Empty, OSError, ValueError, EOFError):
            return
        if kind == "expected":
            events.expected(key, value)
        elif kind == "stage":
            events.stage(key, STAGES[value])
        else:
            events.progress(key, value)


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """SIGTERM every worker, give them time to remove their temporary files, then SIGKILL."""
    # The executor has no public way to stop running workers.
    processes = list((pool._processes or {}).values())
    for process in processes:
        with contextlib.suppress(Exception):
            process.terminate()
    deadline = time.monotonic() + STOP_GRACE_S
    for process in processes:
        process.join(max(0.0, deadline - time.monotonic()))
        if process.is_alive():
            process.kill()
            process.join(1.0)


def create(settings: EngineSettings) -> LocalEngine:
    return LocalEngine(settings.jobs)
