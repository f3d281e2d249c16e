"""tools/loggen/pack_image_folder.py: the RTAB-Map folder packed into every container, read
back raw.

The logs are read with the plain libraries (mcap + decoder factories, rosbags AnyReader), so the
check does not depend on the package's own readers.
"""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoders
from mcap_ros2.decoder import DecoderFactory as Ros2Decoders
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from loggen import camera_log_writers as clw
from loggen import pack_image_folder

TOOLS = Path(__file__).resolve().parents[1] / "tools"  # loggen's folder, for its command line


Image = tuple[int, int, str, bytes]  # header stamp ns, log time ns, format, data


def read_images(path: Path) -> list[Image]:
    if path.suffix == ".mcap":
        with path.open("rb") as f:
            reader = make_reader(f, decoder_factories=[Ros2Decoders(), ProtobufDecoders()])
            return [_from_mcap(m.log_time, d) for _, _, m, d in reader.iter_decoded_messages()]
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        return [
            _from_ros(log_time, reader.deserialize(raw, c.msgtype))
            for c, log_time, raw in reader.messages()
        ]


def _from_mcap(log_time: int, msg: Any) -> Image:
    if hasattr(msg, "header"):  # sensor_msgs/msg/CompressedImage
        return _from_ros(log_time, msg)
    stamp = msg.timestamp.seconds * 10**9 + msg.timestamp.nanos  # foxglove.CompressedImage
    return stamp, log_time, msg.format, bytes(msg.data)


def _from_ros(log_time: int, msg: Any) -> Image:
    stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
    return stamp, log_time, msg.format, bytes(msg.data)


@pytest.fixture(scope="module")
def folder(shared_data: Path) -> Path:
    return shared_data / "rtabmap_samples_loop" / "images"


@pytest.fixture(scope="module")
def packed(folder: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("packed")
    return dict(pack_image_folder.pack(folder, out, "rtabmap", 1.0, list(clw.FORMATS)))


def originals(folder: Path) -> list[bytes]:
    """1.jpg .. 84.jpg in numeric order."""
    return [(folder / f"{k}.jpg").read_bytes() for k in range(1, 85)]


@pytest.mark.parametrize("fmt", clw.FORMATS)
def test_each_container_holds_the_84_original_jpegs_one_second_apart(packed, folder, fmt) -> None:
    images = read_images(packed[fmt])
    assert [data for _, _, _, data in images] == originals(folder)
    assert {form for _, _, form, _ in images} == {"jpeg"}
    stamps = [stamp for stamp, _, _, _ in images]
    assert {b - a for a, b in itertools.pairwise(stamps)} == {10**9}
    assert [log for _, log, _, _ in images] == stamps  # log time = header stamp


def test_every_container_is_written_where_output_path_says(packed, tmp_path) -> None:
    assert {fmt: path.name for fmt, path in packed.items()} == {
        fmt: clw.output_path(tmp_path, "rtabmap", fmt).name for fmt in clw.FORMATS
    }
    assert (packed["db3"] / "metadata.yaml").is_file()


def test_packing_twice_gives_the_same_bytes(folder, packed, tmp_path) -> None:
    again = pack_image_folder.pack(folder, tmp_path, "rtabmap", 1.0, ["ros2mcap", "bag"])
    for fmt, path in again.items():
        assert path.read_bytes() == packed[fmt].read_bytes()


def test_command_line_packs_at_the_requested_rate(folder, tmp_path) -> None:
    command = [sys.executable, "-m", "loggen.pack_image_folder", str(folder)]
    command += ["--fps", "2", "--out", str(tmp_path), "--formats", "foxglove"]
    path = os.pathsep.join(filter(None, [str(TOOLS), os.environ.get("PYTHONPATH")]))
    # Not from the repository root: `-m` puts the working folder on sys.path.
    env = {**os.environ, "PYTHONPATH": path}
    subprocess.run(command, check=True, capture_output=True, timeout=120, env=env, cwd=tmp_path)
    images = read_images(clw.output_path(tmp_path, folder.name, "foxglove"))
    assert [data for _, _, _, data in images] == originals(folder)
    assert {b[0] - a[0] for a, b in itertools.pairwise(images)} == {500_000_000}
