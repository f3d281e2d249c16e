#!/usr/bin/env python3
"""Shrink the frames of a camera log or an image folder to small grey frames and pack them as
a ROS 2 MCAP of raw mono8 images (sensor_msgs/msg/Image), the way thumbnail cameras and
SeqSLAM's classic 64x32 benchmarks record them:

    python -m loggen.shrink_log sample_logs/drive_loops.ros2.mcap \\
        --size 64x32 -o /tmp/dl64.mcap
    python -m loggen.shrink_log ../shared/data/rtabmap_samples_loop/images \\
        --fps 1 --size 128x64 -o /tmp/rtab128.mcap

A log keeps its frames' header stamps; a folder's frame i is stamped START + i / fps. Frame
indices are kept, so the source's ground-truth matrix scores the small log; a log's CameraInfo
is kept, scaled to the new size. `--dark F`
multiplies the pixels by F (0 < F <= 1) after shrinking: a night or low-contrast version.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from doseqslam_logs.sources import open_source, pick_image_topic
from doseqslam_logs.sources.camera_info import read_camera_info
from doseqslam_logs.sources.image_folder import list_images
from doseqslam_logs.sources.images import decode_gray
from loggen.camera_log_writers import CameraIntrinsics, ImageFrame, open_writer

START_NS = 1_700_000_000 * 10**9
Gray = npt.NDArray[np.uint8]


def log_frames(log: Path) -> Iterator[tuple[int, Gray]]:
    """(header stamp or log time, grey image) of every frame of the log's camera topic."""
    with open_source(log) as source:
        topic = pick_image_topic(source, None)
        for message in source.image_messages(topic):
            stamp = message.header_stamp_ns or message.log_time_ns
            yield stamp, decode_gray(message)


def folder_frames(folder: Path, fps: float) -> Iterator[tuple[int, Gray]]:
    for index, path in enumerate(list_images(folder)):
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            raise ValueError(f"{path}: cannot decode")
        yield START_NS + round(index * 1e9 / fps), np.asarray(gray, dtype=np.uint8)


def shrink_gray(gray: Gray, width: int, height: int, dark: float = 1.0) -> Gray:
    """Area-averaged to width x height (the paper's own reduction), then scaled by `dark`."""
    small = cv2.resize(gray, (width, height), interpolation=cv2.INTER_AREA)
    if dark != 1.0:
        small = np.clip(np.rint(small.astype(np.float64) * dark), 0, 255)
    return np.ascontiguousarray(small, dtype=np.uint8)


def write_small_log(
    frames: Iterator[tuple[int, Gray]],
    out: Path,
    size: tuple[int, int] | None,
    dark: float = 1.0,
    camera: CameraIntrinsics | None = None,
) -> int:
    """Writes the frames shrunk to `size` (None: their own) and times `dark` as mono8 images on
    /camera/image_raw, with `camera` as a CameraInfo beside each; returns the count."""
    count = 0
    with open_writer("ros2mcap", out) as writer:
        for stamp, gray in frames:
            width, height = size or (gray.shape[1], gray.shape[0])
            small = gray if size is None and dark == 1.0 else shrink_gray(gray, width, height, dark)
            height, width = small.shape
            writer.write_image(ImageFrame(stamp, small.tobytes(), "mono8", width, height))
            if camera is not None:
                writer.write_camera_info(camera, stamp)
            count += 1
    return count


def scaled_camera(log: Path, size: tuple[int, int] | None) -> CameraIntrinsics | None:
    """The log's CameraInfo scaled to `size` (None: as it is); None when it has none, so that
    the small log is verified with the essential matrix exactly when the source is."""
    with open_source(log) as source:
        topic = pick_image_topic(source, None)
    info = read_camera_info(log, topic)
    if info is None:
        return None
    width, height = size or (info.width, info.height)
    sx, sy = width / info.width, height / info.height
    # Pixel centres scale about the corner: x' = (x + 0.5) * s - 0.5 (cv2.resize's convention).
    cx, cy = (info.cx + 0.5) * sx - 0.5, (info.cy + 0.5) * sy - 0.5
    return CameraIntrinsics(width, height, info.fx * sx, info.fy * sy, cx, cy)


def parse_size(text: str) -> tuple[int, int]:
    width, _, height = text.lower().partition("x")
    return int(width), int(height)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source", type=Path, help="a camera log, or a folder of images")
    parser.add_argument("--size", type=parse_size, default=(64, 32), help="WxH (default 64x32)")
    parser.add_argument("--fps", type=float, default=1.0, help="frame rate of a folder")
    parser.add_argument("--dark", type=float, default=1.0, help="pixel factor, 0 < F <= 1")
    parser.add_argument("-o", "--output", type=Path, required=True)
    args = parser.parse_args()
    width, height = args.size
    is_folder = args.source.is_dir() and not (args.source / "metadata.yaml").exists()
    if is_folder:
        frames, camera = folder_frames(args.source, args.fps), None
    else:
        frames, camera = log_frames(args.source), scaled_camera(args.source, args.size)
    count = write_small_log(frames, args.output, args.size, args.dark, camera)
    with_info = ", with its CameraInfo scaled" if camera else ""
    print(f"{args.output}: {count} frames of {width}x{height} mono8{with_info}")


if __name__ == "__main__":
    main()
