"""Issue #40 item 6: commands that do nothing heavy start fast.

OpenCV, faiss and SciPy took about 1 s to import, before any command could even print its
version: now only the stages that use them import them. Checked by what a fresh interpreter
has imported after the command, not by wall time (a loaded machine would make that flaky);
`tools/bench/startup_time.py` prints the times.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

SAMPLE = Path(__file__).resolve().parents[1] / "sample_logs" / "drive_loops.ros2.mcap"
HEAVY = ("cv2", "faiss", "scipy")

# Imports the command line, runs main(argv) with its output swallowed, then prints the exit
# code and the heavy modules imported.
SCRIPT = f"""
import contextlib, io, json, sys
import doseqslam_logs.cli.main as m
argv, code = json.loads(sys.argv[1]), None
if argv is not None:
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        try:
            code = m.main(argv)
        except SystemExit as exc:
            code = exc.code
print(json.dumps([code, sorted(n for n in {HEAVY!r} if n in sys.modules)]))
"""


def imported_after(argv: list[str] | None, cwd: Path) -> tuple[int | None, list[str]]:
    """(exit code, heavy modules imported) of main(argv) in a fresh interpreter; argv None:
    importing the command line only."""
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT, json.dumps(argv)],
        capture_output=True,
        text=True,
        check=True,
        cwd=cwd,
    )
    code, heavy = json.loads(done.stdout)
    return code, heavy


@pytest.mark.parametrize(
    ("argv", "code"),
    [
        (None, None),
        (["--version"], 0),
        (["--help"], 0),
        (["annotate"], 2),  # required arguments missing
        (["annotate", str(SAMPLE), "-o", "out.mcap", "--no-such-option"], 2),
        (["evaluate", "--help"], 0),
        (["to-bag", "--help"], 0),
    ],
    ids=[
        "import",
        "--version",
        "--help",
        "annotate",
        "unknown option",
        "evaluate --help",
        "to-bag --help",
    ],
)
def test_parsing_the_arguments_imports_nothing_heavy(
    argv: list[str] | None, code: int | None, tmp_path: Path
) -> None:
    assert imported_after(argv, tmp_path) == (code, [])
    assert not (tmp_path / "out.mcap").exists()


def test_info_imports_opencv_only_to_decode_a_frame(tmp_path: Path) -> None:
    # info reports the resolution of the first image that decodes: the sample's are JPEGs.
    assert imported_after(["info", str(SAMPLE)], tmp_path) == (0, ["cv2"])
