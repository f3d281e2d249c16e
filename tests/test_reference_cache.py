"""The byte-comparison tests keep an earlier version's outputs between runs
(reproduce.compare_versions `cache`): the key must change with everything the bytes depend on,
and a kept output must be used instead of running the earlier version again."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from reproduce import compare_versions

REPO = Path(__file__).resolve().parents[1]
LOG = REPO / "sample_logs" / "drive_loops.ros2.mcap"
REVISION = "HEAD"


def test_the_key_changes_with_the_commit_the_log_the_options_and_the_machine(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    key = compare_versions.cache_key(REVISION, LOG, [])
    assert key == compare_versions.cache_key(REVISION, LOG, [])
    assert key != compare_versions.cache_key(f"{REVISION}~1", LOG, [])
    assert key != compare_versions.cache_key(REVISION, LOG, ["--no-verify"])
    renamed = tmp_path / "other.ros2.mcap"
    shutil.copyfile(LOG, renamed)  # the name is in the output's metadata
    assert key != compare_versions.cache_key(REVISION, renamed, [])
    folder = REPO / "sample_logs" / "drive_loops.rosbag2"  # a bag folder: its files
    assert compare_versions.cache_key(REVISION, folder, []) != key
    environment = compare_versions.environment()
    assert "numpy==" in environment and "opencv-contrib-python-headless==" in environment
    monkeypatch.setattr(compare_versions, "environment", lambda: environment + "\nanother cpu")
    assert key != compare_versions.cache_key(REVISION, LOG, [])


def test_a_kept_output_is_used_and_a_new_one_kept(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    runs: list[Path] = []

    def annotate(python_path: Path | None, log: Path, output: Path, extra: list[str]) -> None:
        runs.append(log)
        output.write_bytes(b"output of " + log.name.encode())

    monkeypatch.setattr(compare_versions, "annotate", annotate)
    monkeypatch.setattr(compare_versions, "extract", lambda revision, folder: folder)
    cache = tmp_path / "cache"
    for attempt in range(2):
        work = tmp_path / f"work{attempt}"
        work.mkdir()
        mine = work / "mine.mcap"
        mine.write_bytes(b"output of " + LOG.name.encode())
        found = compare_versions.compare(
            REVISION, [LOG], [], work, current=lambda log, mine=mine: mine, cache=cache
        )
        assert found == [(LOG.name, True)]
    assert runs == [LOG]  # the second comparison read the kept output
    assert [p.name for p in cache.iterdir()] == [
        f"{compare_versions.cache_key(REVISION, LOG, [])}.mcap"
    ]
