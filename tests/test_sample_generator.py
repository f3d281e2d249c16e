"""tools/loggen/make_sample_logs.py and camera_log_writers.py: determinism, ground truth,
images.

The committed sample logs are opened here with the plain libraries (mcap + decoder factories,
rosbags AnyReader), not with the package's own sources, so a bug shared by the package's
readers and the generator cannot hide.
"""

from __future__ import annotations

import io
import itertools
import json
import math
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoders
from mcap_ros2.decoder import DecoderFactory as Ros2Decoders
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from scipy import sparse

from loggen import camera_log_writers as clw
from loggen import make_sample_logs as gen

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "sample_logs"


STEMS = ("drive_loops", "drive_parked", "drive_varrate")
SAMPLE_LOGS = {
    "drive_loops.ros2.mcap": "drive_loops",
    "drive_loops.foxglove.mcap": "drive_loops",
    "drive_loops.bag": "drive_loops",
    "drive_loops.rosbag2": "drive_loops",
    "drive_parked.ros2.mcap": "drive_parked",
    "drive_varrate.bag": "drive_varrate",
}
TINY = gen.Config(name="tiny", route="loops", duration=4.0, rate=2.0, width=64, height=48)


# -- reading logs with the plain libraries -------------------------------------------------


def read_images(path: Path) -> list[tuple[int, int, bytes]]:
    """(header stamp ns, log time ns, data) of every camera image, in log order."""
    if path.suffix == ".mcap":
        return list(_mcap_images(path))
    return list(_rosbags_images(path))


def _mcap_images(path: Path) -> Iterator[tuple[int, int, bytes]]:
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[Ros2Decoders(), ProtobufDecoders()])
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            if "image" not in channel.topic:
                continue
            if hasattr(decoded, "header"):
                stamp = decoded.header.stamp.sec * 10**9 + decoded.header.stamp.nanosec
            else:
                stamp = decoded.timestamp.seconds * 10**9 + decoded.timestamp.nanos
            yield stamp, message.log_time, bytes(decoded.data)


def _rosbags_images(path: Path) -> Iterator[tuple[int, int, bytes]]:
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        images = [c for c in reader.connections if "image" in c.topic]
        for connection, log_time, raw in reader.messages(connections=images):
            msg: Any = reader.deserialize(raw, connection.msgtype)
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            yield stamp, log_time, bytes(msg.data)


def load_gt(stem: str) -> np.ndarray:
    with np.load(SAMPLES / f"{stem}.gt.npz") as archive:
        assert archive.files == ["gt"]
        return archive["gt"]


def load_poses(stem: str) -> dict[str, np.ndarray]:
    return gen.read_poses_csv((SAMPLES / f"{stem}.poses.csv").read_text())


def load_info(stem: str) -> dict[str, Any]:
    return json.loads((SAMPLES / f"{stem}.json").read_text())


def files_under(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


# -- determinism --------------------------------------------------------------------------------


def test_same_seed_gives_the_same_bytes_in_every_format_also_with_workers(tmp_path) -> None:
    gen.generate(TINY, tmp_path / "a", jobs=1, progress=False)
    gen.generate(TINY, tmp_path / "b", jobs=2, progress=False)
    a, b = files_under(tmp_path / "a"), files_under(tmp_path / "b")
    names = {clw.output_path(Path(), "tiny", fmt).name for fmt in clw.FORMATS}
    assert names <= {name.split("/")[0] for name in a}
    assert a == b
    assert not [name for name in a if name.startswith(".") or ".tmp" in name]  # no leftovers


def test_different_seeds_give_different_logs_in_every_format(tmp_path) -> None:
    gen.generate(TINY, tmp_path / "a", progress=False)
    gen.generate(replace(TINY, seed=1), tmp_path / "b", progress=False)
    a, b = files_under(tmp_path / "a"), files_under(tmp_path / "b")
    assert a.keys() == b.keys()
    for name in a:
        # A few seconds hold no loop (the GT is all zeros) and rosbag2's metadata has only
        # counts and times, which the seed does not change.
        if not name.endswith(("metadata.yaml", ".gt.npz")):
            assert a[name] != b[name], name


def test_mcap_headers_name_no_version_and_no_time(tmp_path) -> None:
    gen.generate(replace(TINY, formats=("ros2mcap", "foxglove")), tmp_path, progress=False)
    for fmt, profile in (("ros2mcap", "ros2"), ("foxglove", "")):
        with clw.output_path(tmp_path, "tiny", fmt).open("rb") as f:
            header = make_reader(f).get_header()
        assert (header.profile, header.library) == (profile, clw.MCAP_LIBRARY)


def test_a_failed_write_leaves_nothing_behind(tmp_path) -> None:
    for fmt in clw.FORMATS:
        path = clw.output_path(tmp_path, "broken", fmt)
        with pytest.raises(RuntimeError), clw.open_writer(fmt, path) as writer:
            writer.write_image(clw.ImageFrame(1, b"\xff\xd8", "jpeg"))
            raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []


def test_npz_files_are_deterministic_and_readable_dense_and_sparse() -> None:
    rows, cols = np.array([3, 5, 5]), np.array([0, 1, 2])
    dense = gen.gt_npz_bytes(6, rows, cols, dense=True)
    assert dense == gen.gt_npz_bytes(6, rows, cols, dense=True)
    with np.load(io.BytesIO(dense)) as archive:
        gt = archive["gt"]
    assert gt.dtype == np.uint8 and gt.shape == (6, 6) and gt.sum() == 3 and gt[5, 2] == 1
    matrix = sparse.load_npz(io.BytesIO(gen.gt_npz_bytes(6, rows, cols, dense=False)))
    assert (matrix.toarray() == gt).all()


# -- ground truth -----------------------------------------------------------------------------


def brute_force_gt(poses: dict[str, np.ndarray]) -> np.ndarray:
    """The documented rule, written independently of the generator's KD-tree version."""
    x, y, yaw, stamp = poses["x"], poses["y"], poses["yaw"], poses["stamp_ns"]
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    near = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :]) <= gen.GT_DISTANCE_M
    turn = np.abs(np.angle(np.exp(1j * (yaw[:, None] - yaw[None, :]))))
    aligned = turn <= math.radians(gen.GT_HEADING_DEG) + 1e-12
    old = stamp[:, None] - stamp[None, :] >= gen.GT_MIN_AGE_S * 1e9
    left = travelled[:, None] - travelled[None, :] >= gen.GT_MIN_TRAVEL_M
    return (near & aligned & old & left).astype(np.uint8)


@pytest.mark.parametrize("stem", STEMS)
def test_committed_gt_is_lower_triangular_and_follows_the_documented_rule(stem) -> None:
    gt, poses = load_gt(stem), load_poses(stem)
    assert gt.dtype == np.uint8 and gt.shape == (len(poses["x"]),) * 2
    assert not np.triu(gt).any()
    assert (gt == brute_force_gt(poses)).all()
    facts = load_info(stem)["ground_truth"]
    assert facts["loop_cells"] == gt.sum() > 0
    assert facts["loop_events"] == np.count_nonzero(gt.any(axis=1))
    assert (facts["distance_m"], facts["heading_deg"]) == (gen.GT_DISTANCE_M, gen.GT_HEADING_DEG)


@pytest.mark.parametrize("route", gen.ROUTES)
def test_every_route_revisits_in_the_same_direction_only_where_documented(route) -> None:
    config = gen.Config(route=route, duration=200.0, rate=1.0)
    world = gen.build_world(route, config.lap(), 3)
    drive = gen.simulate_drive(world.centerline, config.drive_spec(), 3)
    poses = gen.read_poses_csv(gen.poses_csv(drive))
    gt = np.zeros((len(poses["x"]),) * 2, np.uint8)
    rows, cols = gen.ground_truth_pairs(poses["stamp_ns"], poses["x"], poses["y"], poses["yaw"])
    gt[rows, cols] = 1
    assert (gt == brute_force_gt(poses)).all() and gt.sum() > 0
    # Some pairs are close but excluded by heading: crossings (figure 8), back legs (out and back).
    dx = poses["x"][:, None] - poses["x"][None, :]
    dy = poses["y"][:, None] - poses["y"][None, :]
    turn = np.abs(np.angle(np.exp(1j * (poses["yaw"][:, None] - poses["yaw"][None, :]))))
    opposite = (np.hypot(dx, dy) < gen.GT_DISTANCE_M) & (turn > math.radians(45))
    if route in ("figure8", "outandback"):
        assert opposite.any()  # revisited, but not a loop: the GT leaves them out
    assert not (gt.astype(bool) & opposite).any()


# -- the drives -----------------------------------------------------------------------------


def test_parked_drive_is_still_for_the_documented_minute_in_the_middle() -> None:
    info, poses = load_info("drive_parked"), load_poses("drive_parked")
    span = info["parked"]
    first, last = span["frames"]
    assert span["end_s"] - span["start_s"] == pytest.approx(60.0, abs=1e-3)
    middle = (span["start_s"] + span["end_s"]) / 2
    assert abs(middle - info["config"]["duration"] / 2) < 5
    t = poses["t"]
    inside = (t >= span["start_s"]) & (t <= span["end_s"])
    assert np.flatnonzero(inside)[[0, -1]].tolist() == [first, last]
    for key in ("x", "y", "yaw"):
        assert np.ptp(poses[key][inside]) == 0  # truly still
    step = np.hypot(np.diff(poses["x"]), np.diff(poses["y"]))
    assert step[: first - 1].min() > 0.05 and step[last + 1 :].min() > 0.05  # and moving else


def test_variable_rate_drive_has_uneven_intervals_and_exactly_the_documented_drops() -> None:
    info = load_info("drive_varrate")
    config = gen.Config(**{**info["config"], "formats": tuple(info["config"]["formats"])})
    dropped = info["dropped_nominal_frames"]
    assert len(dropped) == config.drop_frames == 4
    world = gen.build_world(config.route, config.lap(), config.seed)
    nominal = gen.simulate_drive(
        world.centerline, replace(config, drop_frames=0).drive_spec(), config.seed
    )
    stamps = load_poses("drive_varrate")["stamp_ns"]
    assert (stamps == np.delete(nominal.stamps_ns, dropped)).all()
    assert len(nominal.stamps_ns) == info["nominal_frames"] == len(stamps) + 4
    intervals = np.diff(stamps) / 1e9
    assert intervals.std() / intervals.mean() > 0.15 and intervals.min() > 0


def test_odometry_drifts_a_little() -> None:
    for stem in STEMS:
        info = load_info(stem)
        assert 0 < info["odometry_end_error_m"] < 0.1 * info["distance_m"]


def test_sample_command_lines_reproduce_the_sample_configs() -> None:
    for config in gen.SAMPLES:
        argv = gen.command_line(config, "sample_logs").removeprefix(gen.COMMAND).split()
        args = gen._parser().parse_args(argv)
        assert gen._config(args) == config


# -- the committed logs -----------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(SAMPLE_LOGS))
def test_committed_logs_open_and_hold_one_image_per_gt_frame(name) -> None:
    stem = SAMPLE_LOGS[name]
    images = read_images(SAMPLES / name)
    poses = load_poses(stem)
    assert len(images) == len(load_gt(stem)) == len(poses["x"])
    assert [s for s, _, _ in images] == poses["stamp_ns"].tolist()
    latency = round(load_info(stem)["config"]["latency_ms"] * 1e6)
    assert all(log - stamp == latency for stamp, log, _ in images)
    first = cv2.imdecode(np.frombuffer(images[0][2], np.uint8), cv2.IMREAD_COLOR)
    assert first.shape == (192, 256, 3)


def test_the_same_drive_carries_identical_jpegs_in_all_four_containers() -> None:
    data = [
        [d for _, _, d in read_images(SAMPLES / n)]
        for n, s in SAMPLE_LOGS.items()
        if s == "drive_loops"
    ]
    assert len(data) == 4 and all(d == data[0] for d in data)


def test_camera_info_matches_the_pinhole_render() -> None:
    with (SAMPLES / "drive_loops.ros2.mcap").open("rb") as f:
        reader = make_reader(f, decoder_factories=[Ros2Decoders()])
        _, _, _, info = next(reader.iter_decoded_messages(topics=["/camera/camera_info"]))
    f_expected = 128 / math.tan(math.radians(gen.HFOV_DEG / 2))
    assert (info.width, info.height) == (256, 192)
    assert list(info.k) == pytest.approx([f_expected, 0, 128, 0, f_expected, 96, 0, 0, 1])


# -- the images mean something -----------------------------------------------------------------


def signature(jpeg: bytes) -> np.ndarray:
    """SeqSLAM-like: grey, 32 x 24, patch-normalised (8 x 8 patches)."""
    grey = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
    small = cv2.resize(grey, (32, 24), interpolation=cv2.INTER_AREA).astype(np.float64)
    patches = small.reshape(3, 8, 4, 8).transpose(0, 2, 1, 3).reshape(12, 64)
    patches = (patches - patches.mean(1, keepdims=True)) / (patches.std(1, keepdims=True) + 1e-6)
    return patches.ravel()


@pytest.mark.parametrize(
    ("log", "stem"),
    [("drive_loops.ros2.mcap", "drive_loops"), ("drive_varrate.bag", "drive_varrate")],
)
def test_the_most_similar_older_frame_is_usually_the_true_place(log, stem) -> None:
    """Single-image retrieval: for a GT query, the best match among frames 40 s older."""
    sig = np.array([signature(d) for _, _, d in read_images(SAMPLES / log)])
    gt, stamps = load_gt(stem), load_poses(stem)["stamp_ns"]
    hits, chance = [], []
    for q in np.flatnonzero(gt.any(axis=1)):
        older = np.flatnonzero(stamps[q] - stamps >= gen.GT_MIN_AGE_S * 1e9)
        best = older[np.argmin(np.abs(sig[older] - sig[q]).mean(axis=1))]
        hits.append(gt[q, max(best - 2, 0) : best + 3].any())
        chance.append(gt[q].sum() / len(older))
        # A revisit is not a copy: light, exposure, position and noise differ.
        assert np.abs(sig[q] - sig[np.flatnonzero(gt[q])]).mean() > 0.1
    assert np.mean(hits) > 0.6 > 5 * np.mean(chance)


def test_frames_move_and_have_contrast() -> None:
    images = [d for _, _, d in read_images(SAMPLES / "drive_loops.ros2.mcap")]
    grey = [cv2.imdecode(np.frombuffer(d, np.uint8), cv2.IMREAD_GRAYSCALE) for d in images]
    steps = [np.abs(a.astype(int) - b).mean() for a, b in itertools.pairwise(grey)]
    assert min(steps) > 2.0
    assert min(float(g.std()) for g in grey) > 12.0
