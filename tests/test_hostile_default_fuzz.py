"""Hostile inputs on the default path, every stage on: a small generated drive with odometry,
CameraInfo and an aligned depth topic (so that the metric stage takes depth PnP and the
visualization draws the trajectory) is damaged two ways and goes through `annotate` with its
defaults (verification, motion rule, metric poses, visualization) and then `optimize`:

- message by message: a fifth of the depth, odometry and CameraInfo messages, or of the camera
  images, damaged (seeded: flipped bytes, cut short, grown, emptied);
- container bytes mutated by hypothesis (test_fuzz's mutations: bit flips, cuts, inserted and
  duplicated ranges, huge length fields), in a ROS 2 MCAP (also with --recover) and a ROS 1
  bag.

Each command succeeds or ends with a documented code and one line, never a traceback; an
output is whole or absent; the input is never modified."""

from __future__ import annotations

import hashlib
import random
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from test_fuzz import PER_FILE_S, Op, fuzz_settings, mutate, ops, time_limit
from test_hostile_default_path import check, damage, run
from test_side_topics import rewrite_messages

from doseqslam_logs.annotations.reader import read_annotations
from loggen import make_sample_logs as gen

pytestmark = pytest.mark.slow

DEPTH, ODOM, CAMERA_INFO = "/camera/depth/image", "/odom", "/camera/camera_info"
CAMERA = "/camera/image/compressed"
# 90 frames at 1 Hz, about two laps: 9 loop closures, each with a depth PnP pose (4 s a run).
DRIVE = gen.Config(
    name="drive", seed=11, route="loops", duration=90.0, rate=1.0, width=160, height=120,
    depth=True, formats=("ros2mcap", "bag"),
)  # fmt: skip


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("hostile-drive")
    gen.generate(replace(DRIVE), out, progress=False)
    return {"mcap": out / "drive.ros2.mcap", "bag": out / "drive.bag"}


def annotate_and_optimize(log: Path, folder: Path, *options: str) -> tuple[int, str]:
    """annotate with the defaults (and `options`), then optimize a successful output; checked
    as documented. Returns annotate's exit code and stderr."""
    out, optimized = folder / "annotated.mcap", folder / "optimized.mcap"
    folder.mkdir()
    before = hashlib.sha256(log.read_bytes()).hexdigest()
    with time_limit(6 * PER_FILE_S):
        code, err = run(["annotate", str(log), "-o", str(out), *options])
        check(code, err, out)
        if code == 0:
            assert read_annotations(out).metadata.verification == "on"
            optimize_code, optimize_err = run(["optimize", str(out), "-o", str(optimized)])
            check(optimize_code, optimize_err, optimized)
    assert hashlib.sha256(log.read_bytes()).hexdigest() == before, "the input changed"
    return code, err


def test_the_undamaged_drive_takes_every_stage(drive: dict[str, Path], tmp_path: Path) -> None:
    # Else the damage below would not reach the metric stage and the visualization. (A pair
    # whose depth PnP fails falls back to the rotation only: one on this drive.)
    for name, log in drive.items():
        code, err = annotate_and_optimize(log, tmp_path / name)
        annotated = read_annotations(tmp_path / name / "annotated.mcap")
        methods = [c.metric_method for c in annotated.reported_loop_closures]
        assert code == 0 and methods.count("depth_pnp") >= len(methods) - 1, (err, methods)
        assert (tmp_path / name / "optimized.mcap").is_file()


@pytest.mark.parametrize("seed", range(4))
def test_damaged_depth_odometry_and_camera_info_end_as_documented(
    drive: dict[str, Path], tmp_path: Path, seed: int
) -> None:
    rng = random.Random(seed)
    topics = {DEPTH} | set(rng.sample([ODOM, CAMERA_INFO], rng.randint(0, 2)))

    def change(topic: str, index: int, data: bytes, decode: Callable[[bytes], object]) -> bytes:
        return damage(data, rng) if topic in topics and rng.random() < 0.2 else data

    log = rewrite_messages(drive["mcap"], tmp_path / "damaged.mcap", change)
    code, _ = annotate_and_optimize(log, tmp_path / "out")
    if code == 0:
        annotated = read_annotations(tmp_path / "out" / "annotated.mcap")
        assert annotated.metadata.frames_used == 90


@pytest.mark.parametrize("seed", range(3))
def test_damaged_camera_images_are_skipped_counted_and_the_rest_takes_every_stage(
    drive: dict[str, Path], tmp_path: Path, seed: int
) -> None:
    rng = random.Random(seed)
    damaged: list[int] = []

    def change(topic: str, index: int, data: bytes, decode: Callable[[bytes], object]) -> bytes:
        if topic != CAMERA or rng.random() >= 0.2:
            return data
        damaged.append(index)
        return damage(data, rng)

    log = rewrite_messages(drive["mcap"], tmp_path / "damaged.mcap", change)
    code, err = annotate_and_optimize(log, tmp_path / "out")
    assert code == 0, err  # a fifth of the frames lost is no reason to stop
    metadata = read_annotations(tmp_path / "out" / "annotated.mcap").metadata
    # A damaged JPEG may still decode (a flipped bit in its scan data): at most those are used.
    assert 90 - len(damaged) <= metadata.frames_used < 90 and damaged
    assert metadata.frames_used + metadata.frames_skipped == 90


@pytest.mark.parametrize(("name", "examples"), [("mcap", 12), ("bag", 8)])
def test_mutated_containers_on_the_default_path_end_as_documented(
    drive: dict[str, Path], name: str, examples: int
) -> None:
    data = drive[name].read_bytes()
    outcomes: list[int] = []

    @fuzz_settings(examples)
    @given(mutations=st.lists(ops, min_size=1, max_size=3))
    def fuzz(mutations: list[Op]) -> None:
        folder = Path(tempfile.mkdtemp(prefix="fuzz-default-"))
        try:
            log = folder / drive[name].name
            log.write_bytes(mutate(data, mutations))
            outcomes.append(annotate_and_optimize(log, folder / "out")[0])
            if name == "mcap":  # what it still holds, every stage on
                outcomes.append(annotate_and_optimize(log, folder / "recovered", "--recover")[0])
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    fuzz()
    print(name, sorted(outcomes))
