"""`batch --engine ray` on a local Ray instance: the same outputs as the local engine."""

from __future__ import annotations

import json
import shutil
import signal
from pathlib import Path

import pytest
from test_batch import SAMPLES, T0_NS, run_batch_cli, truncated_copy

from doseqslam_logs.batch.manifest import read_entries
from doseqslam_logs.cli.main import main
from doseqslam_logs.errors import ExitCode

pytestmark = pytest.mark.slow  # the pipeline runs in its fixtures (pyproject: markers)

ray = pytest.importorskip("ray")

# Past the samples' first revisit (60.5 s), so that the outputs hold loop closures to diff.
END = str(T0_NS + 65 * 10**9)


@pytest.fixture(scope="module")
def local_ray():
    """A private 2-CPU Ray instance for this module; the engine uses it and leaves it up."""
    sigterm = signal.getsignal(signal.SIGTERM)  # ray.init replaces it
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    yield ray
    ray.shutdown()
    signal.signal(signal.SIGTERM, sigterm)


def test_ray_outputs_are_byte_identical_to_the_local_engine(local_ray, tmp_path, capsys) -> None:
    logs = tmp_path / "logs"
    (logs / "sub").mkdir(parents=True)
    shutil.copy(SAMPLES / "drive_loops.ros2.mcap", logs)
    shutil.copytree(SAMPLES / "drive_loops.rosbag2", logs / "sub" / "drive_loops.rosbag2")
    truncated_copy(SAMPLES / "drive_loops.ros2.mcap", logs / "broken.mcap")
    outputs = ["drive_loops.ros2.annotated.mcap", "sub/drive_loops.rosbag2.annotated.mcap"]

    code, _, _ = run_batch_cli(str(logs), "-o", str(tmp_path / "local"), "-j", "2", "-E", END)
    assert code == 1
    code, stdout, stderr = run_batch_cli(
        str(logs), "-o", str(tmp_path / "ray"), "--engine", "ray", "-E", END
    )
    assert code == 1
    assert "broken.mcap: FAILED (3 unreadable input)" in stderr
    assert "3 logs: 2 annotated, 0 up to date, 1 failed" in stdout
    for name in outputs:
        ray_bytes = (tmp_path / "ray" / name).read_bytes()
        assert ray_bytes == (tmp_path / "local" / name).read_bytes(), name
    # diff of the two manifests (issue #39): every log matched by source and identical.
    code = main(["diff", *(str(tmp_path / s / "manifest.jsonl") for s in ("local", "ray")),
                 "--json"])  # fmt: skip
    fleet = json.loads(capsys.readouterr().out)
    assert code == ExitCode.OK and fleet["only_a"] == fleet["only_b"] == []
    assert sorted((row["name"], row["state"]) for row in fleet["logs"]) == [
        ("broken.mcap", "failed in both"),
        ("drive_loops.ros2.mcap", "compared"),
        ("drive_loops.rosbag2", "compared"),
    ]
    assert fleet["totals"]["common"] > 0 and fleet["totals"]["changed_logs"] == 0

    entries = list(read_entries(tmp_path / "ray" / "manifest.jsonl"))
    assert sorted((Path(e.input).name, e.status, e.engine) for e in entries) == [
        ("broken.mcap", "failed", "ray"),
        ("drive_loops.ros2.mcap", "ok", "ray"),
        ("drive_loops.rosbag2", "ok", "ray"),
    ]
    local = {Path(e.input).name: e for e in read_entries(tmp_path / "local" / "manifest.jsonl")}
    for entry in entries:
        same = local[Path(entry.input).name]
        assert (entry.sha256, entry.counts, entry.exit_code) == (
            same.sha256,
            same.counts,
            same.exit_code,
        )

    # The driver's manifest resumes across engines: only the failed log runs again.
    code, stdout, _ = run_batch_cli(
        str(logs), "-o", str(tmp_path / "ray"), "--engine", "ray", "-E", END
    )
    assert code == 1 and "2 of 3 logs up to date" in stdout
    assert len(list(read_entries(tmp_path / "ray" / "manifest.jsonl"))) == 4
    assert ray.is_initialized()  # the engine did not shut down an instance it did not start
