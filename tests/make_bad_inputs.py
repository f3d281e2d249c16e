"""Build the corpus of bad inputs that docs/robustness.md describes (issue #8).

    PYTHONPATH=tools python tests/make_bad_inputs.py OUT_DIR [--shared-data DIR]

Every case is made from real data: RTAB-Map camera frames (real JPEGs) written into small logs
with tools/loggen/camera_log_writers.py, or copies of the real bags and MCAP files in
../shared/data, then damaged the way fleet logs get damaged (cut short, bit rot, clocks that
jump, ...). Nothing here is committed as a binary: the corpus is rebuilt in a second or two,
byte for byte the same each time (fixed stamps, fixed damage offsets, deterministic writers).

`make_corpus(out_dir)` returns {case name: path}; `CASES` says in one line what each one is.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import struct
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from mcap.reader import make_reader

from loggen import camera_log_writers as clw

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent


SHARED_DATA = Path(os.environ.get("DOSEQSLAM_SHARED_DATA", REPO.parent / "shared" / "data"))
RTABMAP_IMAGES = "rtabmap_samples_loop/images"
RERUN_MCAP = "rosbag2_mcap_rerun_sensor_msgs/rosbag2_2025_09_10-13_03_56_0.mcap"
TURTLESIM = "ros1_bags_rosbagjs_turtlesim"
TALKER_MCAP = "ros2_bags_rosbag2_talker/mcap_talker/talker.mcap"
ARUCO_BAG = "ros1_bags_fiducials_raspicam/aruco_marker.bag"

FRAMES = 12  # frames per generated log: RTAB-Map 1.jpg .. 12.jpg
FRAMES_PER_CHUNK = 3  # so that a generated MCAP has 4 chunks
T0_NS = 1_700_000_000 * 10**9  # first header stamp
PERIOD_NS = 500_000_000  # 2 Hz camera
LATENCY_NS = 5_000_000  # log time = header stamp + 5 ms
HOURS_3_NS = 3 * 3600 * 10**9
JUMP_AT = 6  # clock jumps happen between frame 5 and frame 6
MCAP_MAGIC = b"\x89MCAP0\r\n"
FOOTER_OPCODE = 0x02
FOOTER_LENGTH = 20  # summary_start u64, summary_offset_start u64, summary_crc u32

# case -> one line: what it is. docs/robustness.md has the behaviour of each.
CASES: dict[str, str] = {
    "good": "12 RTAB-Map JPEG frames, ROS 2 MCAP (zstd, 4 chunks): the control",
    "truncated_footer": "the good MCAP without its last 20 bytes (cut inside the footer)",
    "truncated_chunk": "the good MCAP cut in the middle of its third chunk",
    "rerun_truncated": "the real rerun ros2 MCAP cut in the middle of its second chunk",
    "bad_crc": "uncompressed MCAP, one byte of an image in chunk 2 flipped: CRC mismatch",
    "unindexed": "the good MCAP without summary section (footer says: no summary)",
    "empty": "an empty file named .mcap",
    "not_mcap": "a JPEG file named .mcap",
    "no_camera_mcap": "the real rosbag2 talker MCAP: strings, no camera",
    "no_camera_bag_bz2": "the real turtlesim ROS 1 bag with bz2 chunks: no camera",
    "no_camera_bag_lz4": "the real turtlesim ROS 1 bag with lz4 chunks: no camera",
    "zero_length": "frames 2 and 9 are CompressedImage messages with no data",
    "corrupt_jpeg": "frame 3 has a zeroed JPEG header, frame 7 flipped bytes in its scan data",
    "bad_step": "raw mono8 128x96 frames; frames 4 and 10 say step 130 for 128-byte rows",
    "unknown_encoding": "raw frames labelled with the unknown encoding 'yuv420_888'",
    "resolution_change": "frames 0-5 at 512x384, frames 6-11 at 256x192",
    "log_out_of_order": "messages written out of log-time order (pairs swapped)",
    "stamps_out_of_order": "log times in order, header stamps of frames 3/4 and 8/9 swapped",
    "duplicate_messages": "frames 4 and 8 recorded twice (identical records)",
    "duplicate_stamps": "frames 5 and 10 carry the header stamp of the frame before",
    "clock_jump_back": "header stamps jump back 3 h at frame 6 (log times do not)",
    "clock_jump_forward": "header stamps jump forward 3 h at frame 6 (log times do not)",
    "clock_jump_back_both": "header stamps and log times jump back 3 h at frame 6",
    "zero_stamps": "every header stamp is 0",
    "bag_bz2": "12 RTAB-Map frames in a ROS 1 bag with bz2 chunks",
    "bag_lz4": "12 RTAB-Map frames in a ROS 1 bag with lz4 chunks",
    "bag_unindexed": "the ROS 1 bag of a recording that never finished (index_pos 0, no index)",
    "bag_truncated": "the real aruco_marker ROS 1 bag cut at 60 %",
}


# --- frames -----------------------------------------------------------------------------------


def rtabmap_jpegs(shared_data: Path, count: int = FRAMES) -> list[bytes]:
    folder = shared_data / RTABMAP_IMAGES
    return [(folder / f"{i}.jpg").read_bytes() for i in range(1, count + 1)]


def stamp(i: int) -> int:
    return T0_NS + i * PERIOD_NS


def jpeg_frame(data: bytes, stamp_ns: int) -> clw.ImageFrame:
    return clw.ImageFrame(stamp_ns, data, "jpeg")


def resized_jpeg(data: bytes, width: int, height: int) -> bytes:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    small = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    ok, encoded = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    return bytes(encoded.tobytes())


def mono8_frame(data: bytes, stamp_ns: int, width: int = 128, height: int = 96) -> clw.ImageFrame:
    gray = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    small = cv2.resize(gray, (width, height), interpolation=cv2.INTER_AREA)
    return clw.ImageFrame(stamp_ns, small.tobytes(), "mono8", width, height)


def corrupt_header(jpeg: bytes) -> bytes:
    """SOI kept, the next segments zeroed: no decoder can read it."""
    return jpeg[:3] + bytes(400) + jpeg[403:]


def corrupt_scan(jpeg: bytes) -> bytes:
    """50 bytes of entropy-coded data inverted: libjpeg decodes it with a warning."""
    data = bytearray(jpeg)
    for k in range(50):
        data[600 + k * 97] ^= 0xFF
    return bytes(data)


# --- writing logs with camera_log_writers ----------------------------------------------------

# One message to write: (frame, log time) or, for messages that ImageFrame refuses to describe
# (bad step, unknown encoding), (frame, log time, field overrides of the ROS Image message).
Item = tuple[clw.ImageFrame, int] | tuple[clw.ImageFrame, int, dict[str, Any]]


def write_log(
    path: Path,
    items: Sequence[Item],
    fmt: clw.Format = "ros2mcap",
    *,
    mcap_compression: clw.McapCompression = "zstd",
    bag_compression: clw.BagCompression = "none",
) -> Path:
    """Write the items in the given order; an MCAP gets a new chunk every FRAMES_PER_CHUNK."""
    writer = clw.open_writer(
        fmt, path, mcap_compression=mcap_compression, bag_compression=bag_compression
    )
    with writer:
        for number, item in enumerate(items):
            frame, log_ns = item[0], item[1]
            overrides = item[2] if len(item) == 3 else None
            if overrides:
                _write_overridden(writer, frame, log_ns, overrides)
            else:
                writer.write_image(frame, log_ns)
            if fmt in ("ros2mcap", "foxglove") and (number + 1) % FRAMES_PER_CHUNK == 0:
                # mcap's public Writer.flush ends the chunk in progress; camera_log_writers
                # keeps the default 1 MiB chunks, which would hold the whole small log.
                writer._out.mcap.flush()  # type: ignore[attr-defined]
    return path


def _write_overridden(
    writer: clw.CameraLogWriter, frame: clw.ImageFrame, log_ns: int, overrides: dict[str, Any]
) -> None:
    """A ROS Image message built by camera_log_writers, with some fields replaced."""
    ros: Any = writer
    topic = writer.topics.raw_image
    typename, message = ros._msgs.image(topic, frame, writer.topics.camera_frame)
    message = dataclasses.replace(message, **overrides)
    ros._emit(topic, typename, message, frame.stamp_ns, log_ns)


def good_items(jpegs: list[bytes]) -> list[Item]:
    return [(jpeg_frame(data, stamp(i)), stamp(i) + LATENCY_NS) for i, data in enumerate(jpegs)]


# --- byte-level damage ------------------------------------------------------------------------


def copied_messages(source: Path, writer: Any) -> Iterator[tuple[int, Any]]:
    """Copy every message of the MCAP `source` into the started mcap `writer`, registering
    its schemas and channels as they come; yields (number, message) after each copy, so that
    a caller can add records of its own between them."""
    channels: dict[int, int] = {}
    with source.open("rb") as stream:
        for number, (schema, channel, message) in enumerate(make_reader(stream).iter_messages()):
            if channel.id not in channels:
                assert schema is not None
                schema_id = writer.register_schema(schema.name, schema.encoding, schema.data)
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_id
                )
            writer.add_message(
                channels[channel.id], message.log_time, message.data, message.publish_time
            )
            yield number, message


def chunk_spans(path: Path) -> list[tuple[int, int]]:
    """(start offset, length) of every chunk record, from the summary's chunk indexes."""
    with path.open("rb") as file:
        summary = make_reader(file).get_summary()
    assert summary is not None
    return sorted((c.chunk_start_offset, c.chunk_length) for c in summary.chunk_indexes)


def cut(source: Path, target: Path, size: int) -> Path:
    target.write_bytes(source.read_bytes()[:size])
    return target


def without_summary(source: Path, target: Path) -> Path:
    """Drop the summary section and write a footer that says there is none (summary_start 0):
    what a recorder with the summary switched off writes."""
    blob = source.read_bytes()
    footer = blob[-(len(MCAP_MAGIC) + 1 + 8 + FOOTER_LENGTH) : -len(MCAP_MAGIC)]
    opcode, length, summary_start = struct.unpack_from("<BQQ", footer)
    assert opcode == FOOTER_OPCODE and length == FOOTER_LENGTH and summary_start > 0
    new_footer = struct.pack("<BQQQI", FOOTER_OPCODE, FOOTER_LENGTH, 0, 0, 0)
    target.write_bytes(blob[:summary_start] + new_footer + MCAP_MAGIC)
    return target


def flip_byte(source: Path, target: Path, offset: int) -> Path:
    data = bytearray(source.read_bytes())
    data[offset] ^= 0xFF
    target.write_bytes(bytes(data))
    return target


def _bag_header_fields(blob: bytes) -> tuple[int, dict[str, tuple[int, int]]]:
    """Offset of the bag header record and {field: (value offset, value length)}."""
    magic = b"#ROSBAG V2.0\n"
    assert blob.startswith(magic)
    start = len(magic)
    (header_len,) = struct.unpack_from("<I", blob, start)
    fields: dict[str, tuple[int, int]] = {}
    pos = start + 4
    while pos < start + 4 + header_len:
        (field_len,) = struct.unpack_from("<I", blob, pos)
        name, _, _ = blob[pos + 4 : pos + 4 + field_len].partition(b"=")
        value_at = pos + 4 + len(name) + 1
        fields[name.decode()] = (value_at, field_len - len(name) - 1)
        pos += 4 + field_len
    return start, fields


def unfinished_bag(source: Path, target: Path) -> Path:
    """A ROS 1 bag as a killed recorder leaves it: the header still says index_pos 0 and no
    connection or chunk info records follow the last chunk."""
    blob = bytearray(source.read_bytes())
    _, fields = _bag_header_fields(bytes(blob))
    at, size = fields["index_pos"]
    (index_pos,) = struct.unpack_from("<Q", blob, at)
    assert size == 8 and 0 < index_pos < len(blob)
    struct.pack_into("<Q", blob, at, 0)
    for name in ("conn_count", "chunk_count"):
        at, size = fields[name]
        struct.pack_into("<I", blob, at, 0)
    target.write_bytes(bytes(blob[:index_pos]))
    return target


# --- the corpus -------------------------------------------------------------------------------


def make_corpus(out_dir: str | Path, shared_data: str | Path | None = None) -> dict[str, Path]:
    """Write every case of `CASES` into `out_dir` (created; existing files replaced)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = Path(shared_data) if shared_data is not None else SHARED_DATA
    jpegs = rtabmap_jpegs(data)
    good = good_items(jpegs)
    paths: dict[str, Path] = {}

    def add(name: str, build: Callable[[Path], Path], suffix: str = ".mcap") -> None:
        target = out / f"{name}{suffix}"
        if target.exists():
            target.unlink()
        paths[name] = build(target)

    add("good", lambda p: write_log(p, good))
    spans = chunk_spans(paths["good"])
    size = paths["good"].stat().st_size
    add("truncated_footer", lambda p: cut(paths["good"], p, size - 20))
    third_start, third_length = spans[2]
    add("truncated_chunk", lambda p: cut(paths["good"], p, third_start + third_length // 2))
    rerun = data / RERUN_MCAP
    rerun_spans = chunk_spans(rerun)
    add("rerun_truncated", lambda p: cut(rerun, p, rerun_spans[1][0] + rerun_spans[1][1] // 2))

    def bad_crc(target: Path) -> Path:
        plain = write_log(out / ".bad_crc_source.mcap", good, mcap_compression="none")
        start, length = chunk_spans(plain)[1]
        flip_byte(plain, target, start + length // 2)
        plain.unlink()
        return target

    add("bad_crc", bad_crc)
    add("unindexed", lambda p: without_summary(paths["good"], p))
    add("empty", lambda p: (p.write_bytes(b""), p)[1])
    add("not_mcap", lambda p: (p.write_bytes(jpegs[0]), p)[1])
    add("no_camera_mcap", lambda p: Path(shutil.copyfile(data / TALKER_MCAP, p)))
    turtles = data / TURTLESIM
    add(
        "no_camera_bag_bz2", lambda p: Path(shutil.copyfile(turtles / "example-bz2.bag", p)), ".bag"
    )
    add(
        "no_camera_bag_lz4", lambda p: Path(shutil.copyfile(turtles / "example-lz4.bag", p)), ".bag"
    )

    empty_at = {2, 9}
    add(
        "zero_length",
        lambda p: write_log(
            p,
            [
                (jpeg_frame(b"" if i in empty_at else d, stamp(i)), stamp(i) + LATENCY_NS)
                for i, d in enumerate(jpegs)
            ],
        ),
    )
    damage = {3: corrupt_header, 7: corrupt_scan}
    add(
        "corrupt_jpeg",
        lambda p: write_log(
            p,
            [
                (jpeg_frame(damage[i](d) if i in damage else d, stamp(i)), stamp(i) + LATENCY_NS)
                for i, d in enumerate(jpegs)
            ],
        ),
    )
    raw = [mono8_frame(d, stamp(i)) for i, d in enumerate(jpegs)]
    add(
        "bad_step",
        lambda p: write_log(
            p,
            [
                (f, f.stamp_ns + LATENCY_NS, {"step": 130} if i in (4, 10) else {})
                for i, f in enumerate(raw)
            ],
        ),
    )
    add(
        "unknown_encoding",
        lambda p: write_log(
            p, [(f, f.stamp_ns + LATENCY_NS, {"encoding": "yuv420_888"}) for f in raw]
        ),
    )
    add(
        "resolution_change",
        lambda p: write_log(
            p,
            [
                (
                    jpeg_frame(d if i < JUMP_AT else resized_jpeg(d, 256, 192), stamp(i)),
                    stamp(i) + LATENCY_NS,
                )
                for i, d in enumerate(jpegs)
            ],
        ),
    )
    swapped = [1, 0, 2, 4, 3, 5, 7, 6, 8, 10, 9, 11]
    add("log_out_of_order", lambda p: write_log(p, [good[i] for i in swapped]))
    stamp_of = [0, 1, 2, 4, 3, 5, 6, 7, 9, 8, 10, 11]
    add(
        "stamps_out_of_order",
        lambda p: write_log(
            p,
            [
                (jpeg_frame(d, stamp(stamp_of[i])), stamp(i) + LATENCY_NS)
                for i, d in enumerate(jpegs)
            ],
        ),
    )
    add(
        "duplicate_messages",
        lambda p: write_log(
            p, [item for i, g in enumerate(good) for item in [g] * (1 + (i in (4, 8)))]
        ),
    )
    add(
        "duplicate_stamps",
        lambda p: write_log(
            p,
            [
                (jpeg_frame(d, stamp(i - 1 if i in (5, 10) else i)), stamp(i) + LATENCY_NS)
                for i, d in enumerate(jpegs)
            ],
        ),
    )

    def jumped(header_shift: int, log_shift: int) -> list[Item]:
        return [
            (
                jpeg_frame(d, stamp(i) + (header_shift if i >= JUMP_AT else 0)),
                stamp(i) + LATENCY_NS + (log_shift if i >= JUMP_AT else 0),
            )
            for i, d in enumerate(jpegs)
        ]

    add("clock_jump_back", lambda p: write_log(p, jumped(-HOURS_3_NS, 0)))
    add("clock_jump_forward", lambda p: write_log(p, jumped(HOURS_3_NS, 0)))
    add("clock_jump_back_both", lambda p: write_log(p, jumped(-HOURS_3_NS, -HOURS_3_NS)))
    add(
        "zero_stamps",
        lambda p: write_log(
            p, [(jpeg_frame(d, 0), stamp(i) + LATENCY_NS) for i, d in enumerate(jpegs)]
        ),
    )
    add("bag_bz2", lambda p: write_log(p, good, "bag", bag_compression="bz2"), ".bag")
    add("bag_lz4", lambda p: write_log(p, good, "bag", bag_compression="lz4"), ".bag")

    def bag_unindexed(target: Path) -> Path:
        whole = write_log(out / ".bag_unindexed_source.bag", good, "bag")
        unfinished_bag(whole, target)
        whole.unlink()
        return target

    add("bag_unindexed", bag_unindexed, ".bag")
    aruco = data / ARUCO_BAG
    add("bag_truncated", lambda p: cut(aruco, p, aruco.stat().st_size * 6 // 10), ".bag")
    assert set(paths) == set(CASES), set(CASES) ^ set(paths)
    return paths


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--shared-data", type=Path, default=SHARED_DATA)
    args = parser.parse_args(argv)
    for name, path in make_corpus(args.out_dir, args.shared_data).items():
        print(f"{path}  {CASES[name]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
