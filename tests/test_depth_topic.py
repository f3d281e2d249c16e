"""The aligned depth topic: written by `make_sample_logs.py --depth`, found and read by
`sources.depth` (issue #20, the input of the depth rung of metric loop constraints).

The geometry is checked against the generator's world, not against its depth code: a pixel
back-projected with its depth, the camera's intrinsics and the true pose of `/ground_truth/pose`
must land on a wall or on the ground.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from doseqslam_logs.errors import DepthTopicError, ImageDecodeError
from doseqslam_logs.sources import open_source, pick_image_topic
from doseqslam_logs.sources.base import ImageMessage
from doseqslam_logs.sources.camera_info import read_camera_info
from doseqslam_logs.sources.depth import (
    NOT_DEPTH,
    SIZE_MISMATCH,
    DepthFrames,
    depth_metres,
    find_depth_topic,
    read_depth,
)
from doseqslam_logs.sources.images import RAW_SIZE_MISMATCH, TOO_LARGE
from doseqslam_logs.sources.poses import read_poses
from loggen import camera_log_writers as clw
from loggen import make_sample_logs as gen

REPO = Path(__file__).resolve().parents[1]


IMAGE, DEPTH = "/camera/image/compressed", "/camera/depth/image"
DRIVE = gen.Config(
    name="depth", seed=4, route="loops", duration=4.0, rate=2.0, width=128, height=96, depth=True
)
CONTAINERS = {"ros2mcap": "depth.ros2.mcap", "bag": "depth.bag", "db3": "depth.rosbag2"}


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> gen.Result:
    formats: tuple[clw.Format, ...] = ("ros2mcap", "bag", "db3", "foxglove")
    out = tmp_path_factory.mktemp("depth32")
    return gen.generate(replace(DRIVE, formats=formats), out, progress=False)


@pytest.fixture(scope="module")
def drive_mm(tmp_path_factory: pytest.TempPathFactory) -> gen.Result:
    """The same drive with 16UC1 depth (millimetres)."""
    config = replace(DRIVE, formats=("ros2mcap", "foxglove"), depth_encoding="16UC1")
    return gen.generate(config, tmp_path_factory.mktemp("depth16"), progress=False)


def camera_stamps(path: Path) -> list[int]:
    with open_source(path) as source:
        return [m.header_stamp_ns or m.log_time_ns for m in source.image_messages(IMAGE)]


def read_all(path: Path, **options: Any) -> tuple[list[int], DepthFrames]:
    stamps = camera_stamps(path)
    with open_source(path) as source:
        topic = find_depth_topic(source, IMAGE)
        assert topic == DEPTH
        return stamps, read_depth(source, topic, stamps, **options)


# -- the generator writes it, every container carries it --------------------------------------


@pytest.mark.parametrize("fmt", [*CONTAINERS, "foxglove"])
def test_every_container_carries_a_depth_image_per_camera_frame(
    drive: gen.Result, fmt: str
) -> None:
    path = drive.files[fmt]
    with open_source(path) as source:
        types = {c.topic: c.message_type for c in source.channels()}
        raw = [m.message for m in source.messages(DEPTH)]
    ros = fmt != "foxglove"
    assert types[DEPTH] == ("sensor_msgs/msg/Image" if ros else "foxglove.RawImage")
    assert types["/camera/depth/camera_info"] == types["/camera/camera_info"]
    assert len(raw) == drive.n_frames
    assert {(m.encoding, m.width, m.height, m.step) for m in raw} == {("32FC1", 128, 96, 512)}
    stamps, found = read_all(path, size=(128, 96))
    assert sorted(found.images) == sorted(stamps) and found.skipped == {}
    # Same stamp as its camera frame, not merely the nearest within the tolerance.
    assert all(image.stamp_ns == stamp for stamp, image in found.images.items())
    # The depth camera's intrinsics are the camera's.
    camera = read_camera_info(path, IMAGE)
    depth_camera = read_camera_info(path, DEPTH)
    assert camera is not None and depth_camera is not None
    assert camera.topic == "/camera/camera_info"
    assert depth_camera.topic == "/camera/depth/camera_info"
    assert dataclasses.replace(depth_camera, topic=camera.topic) == camera


def test_depth_is_the_same_in_every_container(drive: gen.Result) -> None:
    depths = [read_all(drive.files[fmt])[1] for fmt in [*CONTAINERS, "foxglove"]]
    for other in depths[1:]:
        for stamp, image in depths[0].images.items():
            np.testing.assert_array_equal(other.images[stamp].metres, image.metres)


# -- geometry: back-projected pixels land on the ray-cast surface --------------------------------


def back_project(
    depth: np.ndarray[Any, Any], camera: Any, x: float, y: float, z: float, yaw: float
) -> np.ndarray[Any, Any]:
    """World points (H, W, 3) of every pixel. The generator's pixel (u, v) is the ray through
    (u + 0.5, v + 0.5); its camera looks along yaw, level, x right, y down (REP 103 optical
    frame), mounted at the pose of /ground_truth/pose."""
    h, w = depth.shape
    right = (np.arange(w) + 0.5 - camera.cx) / camera.fx
    down = (np.arange(h) + 0.5 - camera.cy) / camera.fy
    d = depth.astype(np.float64)
    forward_xy = np.array([math.cos(yaw), math.sin(yaw)])
    right_xy = np.array([math.sin(yaw), -math.cos(yaw)])
    px = x + d * forward_xy[0] + (d * right[None, :]) * right_xy[0]
    py = y + d * forward_xy[1] + (d * right[None, :]) * right_xy[1]
    pz = z - d * down[:, None]
    return np.stack([px, py, pz], axis=-1)


def distance_to_walls(points: np.ndarray[Any, Any], world: gen.World) -> np.ndarray[Any, Any]:
    """Horizontal distance of each (x, y) to the nearest wall segment."""
    a, b = world.a.astype(np.float64), world.b.astype(np.float64)
    ab = b - a
    rel = points[:, None, :] - a[None, :, :]
    along = np.clip(np.sum(rel * ab, axis=-1) / np.sum(ab * ab, axis=-1), 0.0, 1.0)
    nearest = a[None, :, :] + along[..., None] * ab[None, :, :]
    return np.asarray(np.min(np.linalg.norm(points[:, None, :] - nearest, axis=-1), axis=1))


def yaw_of(quaternion_xyzw: Sequence[float]) -> float:
    qx, qy, qz, qw = quaternion_xyzw
    return math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))


@pytest.mark.parametrize("fmt", list(CONTAINERS))
def test_back_projected_depth_lands_on_a_wall_or_the_ground(drive: gen.Result, fmt: str) -> None:
    path = drive.files[fmt]
    camera = read_camera_info(path, DEPTH)
    assert camera is not None
    truth = read_poses(path, "/ground_truth/pose")
    _, found = read_all(path)
    on_walls = on_ground = 0
    for k, stamp in enumerate(truth.times_ns):
        depth = found.images[int(stamp)].metres
        x, y, z = truth.positions[k]
        assert z == pytest.approx(gen.CAMERA_HEIGHT_M)
        points = back_project(depth, camera, x, y, z, yaw_of(truth.quaternions_xyzw[k]))
        valid = np.isfinite(depth)
        ground = valid & (np.abs(points[..., 2]) < 1e-3 * np.maximum(depth, 1.0))
        wall_pixels = valid & ~ground
        wall_points = points[wall_pixels]
        gap = distance_to_walls(wall_points[:, :2], drive.world)
        # float32 ray-casting: measured 3.3e-6 m at most (12 m away). A ray length instead of
        # the depth along the optical axis, or a half-pixel shift, is off by centimetres.
        assert (gap <= 1e-5 * depth[wall_pixels] + 1e-4).all(), (stamp, gap.max())
        assert (wall_points[:, 2] >= -1e-3).all()
        on_walls += int(wall_pixels.sum())
        on_ground += int(ground.sum())
    pixels = len(truth.times_ns) * 128 * 96
    assert on_walls > 0.3 * pixels and on_ground > 0.2 * pixels


def test_depth_is_along_the_optical_axis_not_the_ray(drive: gen.Result) -> None:
    """The ground below the horizon: depth = camera height / tan(angle below the axis), the
    same in every column of a row (a ray length would grow towards the image's sides)."""
    path = drive.files["ros2mcap"]
    camera = read_camera_info(path, DEPTH)
    assert camera is not None
    _, found = read_all(path)
    depth = next(iter(found.images.values())).metres
    bottom = depth.shape[0] - 1
    expected = gen.CAMERA_HEIGHT_M * camera.fy / (bottom + 0.5 - camera.cy)
    assert depth[bottom] == pytest.approx(np.full(depth.shape[1], expected), rel=1e-6)


def test_nan_only_where_no_ray_hits(drive: gen.Result) -> None:
    """Below the horizon every ray hits the ground; NaN (the sky) only above it."""
    _, found = read_all(drive.files["ros2mcap"])
    camera = read_camera_info(drive.files["ros2mcap"], DEPTH)
    assert camera is not None
    rows = np.arange(96) + 0.5
    nan_rows = set()
    for image in found.images.values():
        invalid = ~np.isfinite(image.metres)
        assert not invalid[rows > camera.cy].any()
        # In each column the sky is the top of the image: NaN rows come first.
        assert (invalid.sum(axis=0) == np.argmax(~invalid, axis=0)).all()
        assert (image.metres[~invalid] > 0).all()
        nan_rows |= set(np.nonzero(invalid.any(axis=1))[0].tolist())
    assert nan_rows, "the drive shows some sky"


def test_millimetres_equal_metres_within_a_millimetre(
    drive: gen.Result, drive_mm: gen.Result
) -> None:
    _, metres = read_all(drive.files["ros2mcap"])
    for fmt in ("ros2mcap", "foxglove"):
        _, millimetres = read_all(drive_mm.files[fmt])
        assert millimetres.images.keys() == metres.images.keys()
        for stamp, image in metres.images.items():
            m, mm = image.metres, millimetres.images[stamp].metres
            in_range = np.isfinite(m) & (m <= 65.5)
            assert np.isfinite(mm[in_range]).all()
            assert np.abs(mm[in_range] - m[in_range]).max() <= 0.0005 + 1e-6
            # 0 mm (no depth, or beyond 65.535 m) reads as NaN, and only that.
            assert np.isnan(mm[~np.isfinite(m)]).all() and (~np.isfinite(m)).any()
            assert (~np.isfinite(m) | (m > 65.5))[~np.isfinite(mm)].all()


# -- topic discovery ---------------------------------------------------------------------------


def test_committed_samples_have_no_depth_topic() -> None:
    for path in sorted((REPO / "sample_logs").glob("drive_*")):
        if path.suffix in (".mcap", ".bag", ".rosbag2"):
            with open_source(path) as source:
                assert find_depth_topic(source, IMAGE) is None, path


@pytest.mark.parametrize("fmt", [*CONTAINERS, "foxglove"])
def test_the_camera_of_an_rgbd_log_is_its_image_not_its_depth(drive: gen.Result, fmt: str) -> None:
    # annotate without --topic: the depth topic is an image topic too, but never the camera.
    with open_source(drive.files[fmt]) as source:
        assert pick_image_topic(source) == IMAGE
        assert pick_image_topic(source, DEPTH) == DEPTH  # still readable when asked for


def test_a_depth_topic_asked_for_is_checked(drive: gen.Result) -> None:
    with open_source(drive.files["ros2mcap"]) as source:
        assert find_depth_topic(source, IMAGE, asked=DEPTH) == DEPTH
        for asked, says in [
            ("/camera/depth/nothing", "no topic"),
            ("/camera/depth/camera_info", "not depth images"),
            (IMAGE, "not depth images"),
        ]:
            with pytest.raises(DepthTopicError, match=says):
                find_depth_topic(source, IMAGE, asked=asked)


def write_depth_log(
    path: Path, fmt: clw.Format, items: Sequence[tuple[int, dict[str, Any]]]
) -> Path:
    """A log with a camera image topic and depth messages at the given stamps, each a valid
    4x3 32FC1 image unless `overrides` replace some of its message fields."""
    writer: Any = clw.open_writer(fmt, path)
    with writer:
        for stamp, overrides in items:
            writer.write_image(clw.ImageFrame(stamp, b"\xff\xd8jpeg", "jpeg"))
            metres = np.full((3, 4), stamp / 1e9, "<f4")
            frame = clw.ImageFrame(stamp, metres.tobytes(), "32FC1", 4, 3)
            typename, message = writer._msgs.image(DEPTH, frame, "camera")
            message = dataclasses.replace(message, **overrides)
            writer._emit(DEPTH, typename, message, stamp, stamp)
    return path


def test_a_raw_image_topic_that_is_not_depth_is_not_taken(tmp_path: Path) -> None:
    rgb = {"encoding": "rgb8", "step": 12, "data": np.zeros(36, np.uint8)}
    path = write_depth_log(tmp_path / "rgb.mcap", "ros2mcap", [(1_000_000_000, rgb)])
    with open_source(path) as source:
        assert find_depth_topic(source, IMAGE) is None
        with pytest.raises(DepthTopicError, match="encoding 'rgb8'"):
            find_depth_topic(source, IMAGE, asked=DEPTH)


def test_a_depth_topic_of_another_camera_is_not_taken(tmp_path: Path) -> None:
    path = write_depth_log(tmp_path / "d.mcap", "ros2mcap", [(1_000_000_000, {})])
    with open_source(path) as source:
        assert find_depth_topic(source, "/front/image/compressed") is None
        assert find_depth_topic(source, "/camera/left/image_raw") == DEPTH


# -- reading: nearest stamp, bounded, hostile messages skipped and counted ---------------------

S = 1_000_000_000


@pytest.mark.parametrize("fmt", ["ros2mcap", "bag"])
def test_hostile_depth_messages_are_skipped_and_counted(tmp_path: Path, fmt: clw.Format) -> None:
    huge = {"width": 40000, "height": 40000, "step": 160000}
    short = {"data": np.zeros(20, np.uint8)}  # 4x3 float32 needs 48 bytes
    wrong = {"encoding": "rgb8"}
    other_size = {"width": 2, "height": 6, "step": 8}
    items = [(1 * S, {}), (2 * S, huge), (3 * S, short), (4 * S, wrong), (5 * S, other_size)]
    path = write_depth_log(tmp_path / f"hostile.{fmt}", fmt, items)
    with open_source(path) as source:
        found = read_depth(source, DEPTH, [k * S for k in range(1, 6)], size=(4, 3))
    assert sorted(found.images) == [1 * S]
    assert found.messages == 5
    assert found.skipped == {TOO_LARGE: 1, RAW_SIZE_MISMATCH: 1, NOT_DEPTH: 1, SIZE_MISMATCH: 1}
    assert "40000x40000" in found.first_problem[TOO_LARGE]
    assert "2x6" in found.first_problem[SIZE_MISMATCH]
    with open_source(path) as source:  # without a camera size, 2x6 is a depth image
        found = read_depth(source, DEPTH, [5 * S], max_pixels=10_000)
    assert found.images[5 * S].metres.shape == (6, 2)


def test_the_nearest_depth_within_the_tolerance_is_kept(tmp_path: Path) -> None:
    stamps = [1 * S, 1 * S + 4_000_000, 2 * S + 9_000_000, 3 * S + 30_000_000]
    path = write_depth_log(tmp_path / "near.mcap", "ros2mcap", [(s, {}) for s in stamps])
    with open_source(path) as source:
        found = read_depth(source, DEPTH, [3 * S, 2 * S, 1 * S + 3_000_000])
    assert {w: i.stamp_ns for w, i in found.images.items()} == {
        1 * S + 3_000_000: 1 * S + 4_000_000,
        2 * S: 2 * S + 9_000_000,
    }  # 3 s: the nearest depth is 30 ms away, beyond the 10 ms tolerance
    assert found.images[2 * S].metres == pytest.approx(np.full((3, 4), 2.009, np.float32))
    with open_source(path) as source:
        assert read_depth(source, DEPTH, []).images == {}


# -- decoding the buffers ----------------------------------------------------------------------


def depth_message(
    values: np.ndarray[Any, Any], encoding: str, big: bool, pad: bytes
) -> ImageMessage:
    """A raw depth ImageMessage of `values` (H, W) with `pad` bytes after every row."""
    dtype = {"32FC1": "f4", "16UC1": "u2"}[encoding]
    rows = values.astype((">" if big else "<") + dtype).view(np.uint8).reshape(len(values), -1)
    data = b"".join(row.tobytes() + pad for row in rows)
    h, w = values.shape
    step = rows.shape[1] + len(pad)
    return ImageMessage(DEPTH, 0, None, "raw", encoding, w, h, step, big, data)


SHAPES = st.tuples(st.integers(1, 6), st.integers(1, 6))
PADDING = st.binary(max_size=7)


@settings(max_examples=200, deadline=None)
@given(
    shape=SHAPES,
    big=st.booleans(),
    pad=PADDING,
    data=st.data(),
)
def test_property_32fc1_is_metres_with_nan_for_invalid(
    shape: tuple[int, int], big: bool, pad: bytes, data: st.DataObject
) -> None:
    special = st.sampled_from([math.nan, math.inf, -math.inf, 0.0, -1.5])
    element = st.floats(0.0625, 1000.0, width=32) | special
    values = np.array(
        data.draw(st.lists(element, min_size=shape[0] * shape[1], max_size=shape[0] * shape[1])),
        np.float32,
    )
    values = values.reshape(shape)
    metres = depth_metres(depth_message(values, "32FC1", big, pad))
    assert metres.dtype == np.float32 and metres.shape == shape and metres.flags.writeable
    valid = np.isfinite(values) & (values > 0)
    np.testing.assert_array_equal(metres[valid], values[valid])
    assert np.isnan(metres[~valid]).all()


@settings(max_examples=200, deadline=None)
@given(shape=SHAPES, big=st.booleans(), pad=PADDING, data=st.data())
def test_property_16uc1_is_millimetres_with_zero_invalid(
    shape: tuple[int, int], big: bool, pad: bytes, data: st.DataObject
) -> None:
    n = shape[0] * shape[1]
    values = np.array(
        data.draw(st.lists(st.integers(0, 65535), min_size=n, max_size=n)), np.uint16
    ).reshape(shape)
    metres = depth_metres(depth_message(values, "16UC1", big, pad))
    assert metres.dtype == np.float32 and metres.shape == shape
    valid = values > 0
    np.testing.assert_allclose(metres[valid], values[valid] / 1000.0, rtol=1e-6)
    assert np.isnan(metres[~valid]).all()


@settings(max_examples=300, deadline=None)
@given(
    encoding=st.sampled_from(["32FC1", "16UC1", "mono8", "", "32FC3"]),
    width=st.integers(-2, 12),
    height=st.integers(-2, 12),
    step=st.integers(-2, 60),
    big=st.booleans(),
    data=st.binary(max_size=300),
)
def test_property_any_depth_message_decodes_or_says_why(
    encoding: str, width: int, height: int, step: int, big: bool, data: bytes
) -> None:
    message = ImageMessage(DEPTH, 0, None, "raw", encoding, width, height, step, big, data)
    try:
        metres = depth_metres(message, max_pixels=64)
    except ImageDecodeError as error:
        assert error.problem
        return
    assert metres.shape == (height, width) and width * height <= 64


# -- the generator's option ----------------------------------------------------------------------


def test_the_option_is_recorded_only_when_on(tmp_path: Path) -> None:
    """Logs without depth keep their bytes: no depth field in their metadata or .json."""
    assert "depth" not in gen.Config().recorded()
    assert gen.Config(depth=True).recorded()["depth_encoding"] == "32FC1"
    config = replace(DRIVE, depth_encoding="16UC1")
    line = gen.command_line(config, str(tmp_path))
    assert line.endswith("--depth --depth-encoding 16UC1")
    args = gen._parser().parse_args(line.removeprefix(gen.COMMAND).split())
    assert gen._config(args) == config
    assert "--depth" not in gen.command_line(replace(DRIVE, depth=False))
    with pytest.raises(SystemExit):
        gen.main(["--out", str(tmp_path), "--depth-encoding", "16UC1"])
    # The samples' README lists the depth topics only for a sample set that has them.
    rows = gen._depth_rows([SimpleNamespace(config=config)])  # type: ignore[list-item]
    assert len(rows) == 2 and "`16UC1`" in rows[0]
    assert gen._depth_rows([SimpleNamespace(config=gen.Config())]) == []  # type: ignore[list-item]


def test_depth_logs_are_the_same_bytes_with_worker_processes(tmp_path: Path) -> None:
    config = replace(DRIVE, duration=2.0, width=64, height=48, formats=("ros2mcap",))
    one = gen.generate(config, tmp_path / "one", jobs=1, progress=False)
    two = gen.generate(config, tmp_path / "two", jobs=2, progress=False)
    assert one.files["ros2mcap"].read_bytes() == two.files["ros2mcap"].read_bytes()
