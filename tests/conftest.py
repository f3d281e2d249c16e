"""Shared test fixtures: where the real third-party data lives."""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import io
import os
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# CI clones the repository beside shared/, so ../shared/data from the repository root.
SHARED_DATA = Path(os.environ.get("DOSEQSLAM_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session", autouse=True)
def no_progress_lines() -> Iterator[None]:
    """Off a terminal, a run longer than QUIET_S prints progress lines on stderr: how long a
    run takes depends on the machine and its load, so in-process runs of the tests never
    print them (set up before every other fixture, module-scoped ones included;
    tests/test_progress.py sets QUIET_S itself)."""
    from doseqslam_logs.cli import progress

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(progress, "QUIET_S", float("inf"))
        yield


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.fail(f"real test data not found at {SHARED_DATA} (set DOSEQSLAM_SHARED_DATA)")
    return SHARED_DATA


SAMPLE_LOGS = REPO / "sample_logs"


def _run_folder(tmp_path_factory: pytest.TempPathFactory, name: str) -> Path:
    """A folder of the test run shared by the xdist workers: each worker's basetemp is a
    folder of the run's own temporary root."""
    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    folder = root / name
    folder.mkdir(exist_ok=True)
    return folder


def _once(folder: Path, key: str, out: Path, make: Callable[[Path], None]) -> Path:
    """`out`, made by `make(partial path)` by the first worker that asks, the others waiting
    for it; a partial output never takes its name."""
    with open(folder / f"{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not out.exists():
            made = folder / f".{key}.partial{out.suffix}"
            make(made)
            made.rename(out)
    return out


@pytest.fixture(scope="session")
def annotated_sample(tmp_path_factory: pytest.TempPathFactory) -> Callable[..., Path]:
    """`annotated_sample(name, *options)`: `sample_logs/NAME` annotated by this version with
    `doseqslam-logs annotate NAME -o OUT *options`, once per test run (shared by the xdist
    workers through a locked folder of the run's own temporary root), for tests that only
    read the output: a dozen test files read the same annotation of a sample."""
    folder = _run_folder(tmp_path_factory, "annotated-samples")

    def annotated(name: str, *options: str) -> Path:
        key = hashlib.sha256(repr((name, options)).encode()).hexdigest()[:12]
        out = folder / f"{key}-{Path(name).name}.mcap"
        return _once(folder, key, out, lambda made: _annotate(SAMPLE_LOGS / name, made, options))

    return annotated


def _annotate(log: Path, out: Path, options: tuple[str, ...] = ()) -> None:
    from doseqslam_logs.cli.main import main

    with contextlib.redirect_stdout(io.StringIO()):
        code = main(["annotate", str(log), "-o", str(out), *options])
    assert code == 0, f"annotate {log} {options} failed"


@pytest.fixture(scope="session")
def annotated_drifting_drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """reproduce.pose_graph_check's drifting drive (drive_loops' settings, seed 29: its
    odometry 4.4 m off at the end) annotated with the command's defaults, once per test run
    (shared like `annotated_sample`): test_optimize and test_pose_graph read it."""
    from reproduce import pose_graph_check

    folder = _run_folder(tmp_path_factory, "drifting-drive")

    def make(made: Path) -> None:
        _annotate(pose_graph_check.generate_drifting_drive(folder), made)

    return _once(folder, "annotated", folder / "annotated.mcap", make)


@pytest.fixture(scope="session")
def reference_cache() -> Path | None:
    """Where the byte-comparison tests keep an earlier version's outputs between runs
    (reproduce.compare_versions: keyed by commit, log, options, machine and libraries):
    DOSEQSLAM_REFERENCE_CACHE, default ~/.cache/doseqslam-reference; empty: none."""
    folder = os.environ.get("DOSEQSLAM_REFERENCE_CACHE")
    if folder is None:
        return Path.home() / ".cache" / "doseqslam-reference"
    return Path(folder) if folder else None


@pytest.fixture(scope="session")
def one_hz(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The matrix's 1 Hz cell, seed 1 (300 frames of 320x240): generated_cells."""
    from generated_cells import ONE_HZ, generate

    return generate(ONE_HZ, tmp_path_factory.mktemp("one_hz"))


@pytest.fixture(scope="session")
def two_hz(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The matrix's 2 Hz cell, seed 1 (600 frames of 320x240): generated_cells."""
    from generated_cells import TWO_HZ, generate

    return generate(TWO_HZ, tmp_path_factory.mktemp("two_hz"))
