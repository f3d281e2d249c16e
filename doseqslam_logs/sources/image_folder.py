"""A folder of images as a camera stream at a fixed rate (how the paper's datasets ship)."""

from __future__ import annotations

import bisect
import math
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..errors import SourceError, UsageError
from .base import ChannelInfo, DecodedMessage, ImageMessage, SourceDefaults
from .frame import Frame
from .image_header import DEFAULT_MAX_PIXELS, claimed_size
from .images import Gray, captured_stderr, check_pixel_cap

# Frame rates a folder can be stamped at: from one frame every 11.6 days (10,000 frames then
# span 3,000 years, still an int64 of ns) to one frame per nanosecond.
FPS_MIN, FPS_MAX = 1e-6, 1e9
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".ppm", ".pgm", ".tif", ".tiff"}


def natural_key(path: Path) -> tuple[tuple[int, int | str], ...]:
    """Sort key that orders `2.jpg` before `10.jpg` (numbers compare as numbers)."""
    parts = re.split(r"(\d+)", path.name)
    return tuple((0, int(p)) if p.isdigit() else (1, p) for p in parts if p)


def list_images(folder: Path) -> list[Path]:
    """The image files of a folder in natural order.

    Raises SourceError when the folder is missing or holds no image.
    """
    if not folder.is_dir():
        raise SourceError(f"{folder}: not a folder of images")
    images = sorted(
        (p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=natural_key
    )
    if not images:
        raise SourceError(f"{folder}: no image files ({', '.join(sorted(IMAGE_SUFFIXES))})")
    return images


def folder_time_ns(index: int, fps: float) -> int:
    """The stamp `folder_frames` gives frame `index`: index / fps seconds."""
    return round(index * 1e9 / fps)


def check_fps(fps: float) -> float:
    """`fps` if a folder can be stamped at it; UsageError otherwise (NaN, inf, out of range)."""
    if not (math.isfinite(fps) and FPS_MIN <= fps <= FPS_MAX):
        raise UsageError(f"--fps must be a frame rate from {FPS_MIN:g} to {FPS_MAX:g}, got {fps}")
    return fps


def read_gray_file(path: Path, max_pixels: int = DEFAULT_MAX_PIXELS) -> Gray:
    """One image file as a gray image, its size checked from its header before decoding.

    Raises SourceError when it cannot be read or decoded, or its header cannot be read;
    ImageDecodeError ("too large") when it claims more than `max_pixels` pixels. A folder's
    frames are numbered by position, so an image cannot be skipped: either refuses the run.
    """
    from .opencv_quiet import cv2

    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SourceError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    size = claimed_size(data)
    if size is None:
        raise SourceError(
            f"{path}: cannot decode image (no PNG, JPEG, BMP, TIFF, WebP or PNM header)"
        )
    check_pixel_cap(size, max_pixels, str(path))
    with captured_stderr():  # OpenCV's own "[ERROR:0@...]" lines, e.g. for a truncated BMP
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise SourceError(f"{path}: cannot decode image")
    return np.ascontiguousarray(image, dtype=np.uint8)


def folder_frames(
    folder: Path, fps: float, max_pixels: int = DEFAULT_MAX_PIXELS
) -> Iterator[Frame]:
    """Frames of the folder's images, frame i stamped i / fps seconds.

    Raises UsageError for a rate check_fps refuses, SourceError for an image that cannot be
    read, ImageDecodeError for one over `max_pixels`.
    """
    check_fps(fps)
    for index, path in enumerate(list_images(folder)):
        stamp = folder_time_ns(index, fps)
        yield Frame(index, stamp, stamp, None, read_gray_file(path, max_pixels))


FOLDER_TOPIC = "/image_folder"
FOLDER_MESSAGE_TYPE = "image file"


class ImageFolderSource(SourceDefaults):
    """An image folder as a `Source`: one camera topic whose frame i is the folder's i-th image
    in natural order, at log time i / fps seconds (no header stamp: run it on log time).

    Each image is decoded as it is read (gray, its size checked from its header first) and
    handed on as a raw mono8 message. A folder's frames are numbered by position, so an image
    cannot be skipped: one that cannot be read or decoded raises SourceError, one over
    `max_pixels` ImageDecodeError, and the run stops.
    """

    def __init__(self, folder: Path, fps: float, max_pixels: int = DEFAULT_MAX_PIXELS) -> None:
        self.path = folder
        self.fps = check_fps(fps)
        self.max_pixels = max_pixels
        self.files = list_images(folder)
        self.times_ns = [folder_time_ns(index, self.fps) for index in range(len(self.files))]

    def channels(self) -> list[ChannelInfo]:
        count, last = len(self.files), self.times_ns[-1]
        return [
            ChannelInfo(FOLDER_TOPIC, FOLDER_MESSAGE_TYPE, "file", count, 0, last, is_image=True)
        ]

    def _indices(self, topic: str, start_ns: int | None, end_ns: int | None) -> range:
        if topic != FOLDER_TOPIC:
            return range(0)
        first = 0 if start_ns is None else bisect.bisect_left(self.times_ns, start_ns)
        last = len(self.times_ns) if end_ns is None else bisect.bisect_left(self.times_ns, end_ns)
        return range(first, max(first, last))

    def image_messages(
        self, topic: str, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[ImageMessage]:
        for index in self._indices(topic, start_ns, end_ns):
            gray = read_gray_file(self.files[index], self.max_pixels)
            height, width = gray.shape
            stamp, data = self.times_ns[index], gray.tobytes()
            yield ImageMessage(
                topic, stamp, None, "raw", "mono8", width, height, width, False, data
            )

    def messages(self, topic: str) -> Iterator[DecodedMessage]:
        return iter(())  # a folder holds images only

    def raw_messages(
        self, topic: str, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[tuple[int, bytes]]:
        for index in self._indices(topic, start_ns, end_ns):
            path = self.files[index]
            try:
                data = path.read_bytes()
            except OSError as exc:
                raise SourceError(f"{path}: cannot read ({exc.strerror or exc})") from exc
            yield self.times_ns[index], data
