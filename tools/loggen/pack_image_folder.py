#!/usr/bin/env python3
"""Pack a folder of JPEG/PNG images into camera logs: ROS 2 MCAP, Foxglove MCAP, ROS 1 bag, db3.

Images are taken in natural file-name order (2.jpg before 10.jpg), frame i stamped
--start + i / --fps seconds, and stored byte for byte as compressed images (the file's own
JPEG or PNG bytes), so annotating the packed log must give what `evaluate --images` gives on
the folder:

    python -m loggen.pack_image_folder \\
        ../shared/data/rtabmap_samples_loop/images --fps 1 --out /tmp/packed --name rtabmap
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from doseqslam_logs.sources.image_folder import list_images
from loggen.camera_log_writers import (
    FORMATS,
    Format,
    ImageFrame,
    open_writer,
    output_path,
    parse_formats,
)

START_NS = 1_700_000_000 * 10**9  # a plausible epoch time, so logs look recorded, not at 1970
ENCODINGS = {".jpg": "jpeg", ".jpeg": "jpeg", ".png": "png"}


def image_frames(folder: Path, fps: float, start_ns: int = START_NS) -> list[ImageFrame]:
    """The folder's JPEG/PNG files as compressed frames, in natural order.

    Raises ValueError for a file that is not JPEG or PNG (they are stored as they are).
    """
    frames = []
    for index, path in enumerate(list_images(folder)):
        encoding = ENCODINGS.get(path.suffix.lower())
        if encoding is None:
            raise ValueError(f"{path}: only JPEG and PNG files can be packed as they are")
        data = path.read_bytes()
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError(f"{path}: cannot decode")
        stamp = start_ns + round(index * 1e9 / fps)
        frames.append(ImageFrame(stamp, data, encoding, image.shape[1], image.shape[0]))
    return frames


def pack(
    folder: Path, out_dir: Path, name: str, fps: float, formats: list[Format]
) -> dict[Format, Path]:
    """Write the folder's images in each format; returns the path written per format."""
    frames = image_frames(folder, fps)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = {}
    for fmt in formats:
        path = output_path(out_dir, name, fmt)
        with open_writer(fmt, path) as writer:
            for frame in frames:
                writer.write_image(frame)
        written[fmt] = path
    return written


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("folder", type=Path, help="folder of .jpg/.png images")
    parser.add_argument("--fps", type=float, default=1.0, help="frame rate (default 1)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--name", help="file name stem (default: the folder's name)")
    parser.add_argument("--formats", default=",".join(FORMATS), help="comma-separated")
    args = parser.parse_args()
    name = args.name or args.folder.resolve().name
    for fmt, path in pack(
        args.folder, args.out, name, args.fps, parse_formats(args.formats)
    ).items():
        print(f"{fmt:9s} {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
