"""Hostile side topics on the default path: `annotate` with verification, the motion rule,
metric poses and the visualization on, then `optimize` of its output, over copies of
drive_loops whose odometry, camera info and ground-truth messages are damaged at random
(seeded: flipped bytes, cut short, grown, emptied). Whatever the damage, each command
succeeds or exits with a documented code and one line, never a traceback; an output is whole
or absent (no temporary file left); the input is never modified; a successful output reads
back."""

from __future__ import annotations

import contextlib
import hashlib
import io
import random
from collections.abc import Callable
from pathlib import Path

import pytest
from test_side_topics import LOOPS, rewrite_messages

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.cli.main import main
from doseqslam_logs.errors import ExitCode

SIDE_TOPICS = ("/odom", "/camera/camera_info", "/ground_truth/pose")
# What a command may exit with on a damaged log (docs/cli.md): success, or a documented error.
# (USAGE: optimize refuses an annotated log it cannot build a pose graph from, e.g. without a
# usable pose topic.)
DOCUMENTED = {0, ExitCode.USAGE, ExitCode.UNREADABLE_INPUT, ExitCode.NO_CAMERA, ExitCode.BAD_IMAGE}
SEEDS = range(6)


def damage(data: bytes, rng: random.Random) -> bytes:
    """One of: a few flipped bytes, cut short, grown by junk, emptied."""
    kind = rng.choice(["flip", "cut", "grow", "empty"])
    if kind == "flip":
        raw = bytearray(data)
        for _ in range(rng.randint(1, 8)):
            raw[rng.randrange(len(raw))] ^= 1 << rng.randrange(8)
        return bytes(raw)
    if kind == "cut":
        return data[: rng.randrange(len(data))]
    if kind == "grow":
        return data + bytes(rng.randrange(256) for _ in range(rng.randint(1, 64)))
    return b""


def damaged_copy(out: Path, seed: int) -> Path:
    """drive_loops with a fifth of the messages of one or more side topics damaged."""
    rng = random.Random(seed)
    topics = rng.sample(SIDE_TOPICS, rng.randint(1, len(SIDE_TOPICS)))

    def change(topic: str, index: int, data: bytes, decode: Callable[[bytes], object]) -> bytes:
        return damage(data, rng) if topic in topics and rng.random() < 0.2 else data

    return rewrite_messages(LOOPS, out, change)


def run(argv: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, err.getvalue()


def check(code: int, err: str, output: Path) -> None:
    assert code in DOCUMENTED, (code, err)
    assert "Traceback" not in err
    errors = [line for line in err.splitlines() if line.startswith("doseqslam-logs: error:")]
    if code:
        assert len(errors) == 1 and len(err.splitlines()) == 1, err
        assert not output.exists()
    else:
        assert not errors and output.is_file()
    leftovers = [p.name for p in output.parent.iterdir() if p.name.startswith(".")]
    assert leftovers == []  # no temporary file of an output


@pytest.mark.slow
@pytest.mark.parametrize("seed", SEEDS)
def test_damaged_side_topics_on_the_default_path_end_as_documented(
    seed: int, tmp_path: Path
) -> None:
    log = damaged_copy(tmp_path / "damaged.mcap", seed)
    before = hashlib.sha256(log.read_bytes()).hexdigest()
    out, optimized = tmp_path / "out" / "annotated.mcap", tmp_path / "out" / "optimized.mcap"
    out.parent.mkdir()
    code, err = run(["annotate", str(log), "-o", str(out)])
    check(code, err, out)
    assert hashlib.sha256(log.read_bytes()).hexdigest() == before
    if code:
        return
    annotated = read_annotations(out)
    assert annotated.metadata.verification == "on" and annotated.metadata.frames_used == 240
    code, err = run(["optimize", str(out), "-o", str(optimized)])
    check(code, err, optimized)
