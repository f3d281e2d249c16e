"""Image messages: from decoded ROS / Foxglove messages to `ImageMessage`, and on to pixels.

`decode_gray` turns an `ImageMessage` into a 2-D uint8 gray image. Raw encodings are looked up in
`RAW_ENCODINGS` (one entry per encoding); compressed data is recognised by its magic bytes, not by
the free-form format string, which publishers fill inconsistently ("jpg", "jpeg",
"rgb8; jpeg compressed bgr8", ...).

`IMAGE_TYPES` maps every recognised message type name to the function that builds an
`ImageMessage` from one decoded message; the MCAP and rosbags sources share it so that the field
mapping lives in one place.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from doseqslam_logs.errors import ImageDecodeError
from doseqslam_logs.sources.base import MAX_TIME_NS, ImageKind, ImageMessage
from doseqslam_logs.sources.image_header import DEFAULT_MAX_PIXELS, claimed_size

Gray = npt.NDArray[np.uint8]

# Pixel bytes with the row padding cut off: shape (height, width * bytes_per_pixel), uint8.
Rows = npt.NDArray[np.uint8]

# What went wrong with an image, in a few words: runs count skipped frames by it
# (`ImageDecodeError.problem`).
UNDESERIALIZABLE = "undeserializable message"
UNKNOWN_ENCODING = "unknown encoding"
EMPTY_IMAGE = "empty image"
RAW_SIZE_MISMATCH = "raw size mismatch"
CONVERSION_FAILED = "conversion failed"
NOT_JPEG_OR_PNG = "not JPEG or PNG"
CORRUPT_COMPRESSED = "corrupt compressed image"
TOO_LARGE = "too large"


# ---------------------------------------------------------------------------------------------
# Raw encodings


@dataclass(frozen=True)
class RawEncoding:
    """How one raw `sensor_msgs/Image` encoding is laid out and turned into gray."""

    bytes_per_pixel: int
    to_gray: Callable[[Rows, ImageMessage], Gray]


def _mono8(rows: Rows, msg: ImageMessage) -> Gray:
    return rows


def _mono16(rows: Rows, msg: ImageMessage) -> Gray:
    words = np.ascontiguousarray(rows).view(">u2" if msg.is_bigendian else "<u2")
    return (words >> 8).astype(np.uint8)


# The conversions name OpenCV's codes (cv2.COLOR_...): OpenCV is imported at the first
# conversion (opencv_quiet), not with RAW_ENCODINGS.


def _cvt_color(code: str, channels: int) -> Callable[[Rows, ImageMessage], Gray]:
    def convert(rows: Rows, msg: ImageMessage) -> Gray:
        from doseqslam_logs.sources.opencv_quiet import cv2

        pixels = np.ascontiguousarray(rows).reshape(rows.shape[0], -1, channels)
        return np.asarray(cv2.cvtColor(pixels, getattr(cv2, code)), dtype=np.uint8)

    return convert


def _demosaic(code: str) -> Callable[[Rows, ImageMessage], Gray]:
    def convert(rows: Rows, msg: ImageMessage) -> Gray:
        from doseqslam_logs.sources.opencv_quiet import cv2

        pixels = np.ascontiguousarray(rows)
        return np.asarray(cv2.cvtColor(pixels, getattr(cv2, code)), dtype=np.uint8)

    return convert


def _luma_at(offset: int) -> Callable[[Rows, ImageMessage], Gray]:
    """4:2:2 packed YUV: every second byte is a Y sample, starting at `offset`."""

    def convert(rows: Rows, msg: ImageMessage) -> Gray:
        return rows[:, offset::2]

    return convert


def _float32(rows: Rows, msg: ImageMessage) -> Gray:
    """Depth-like float images: finite values stretched to 0..255, NaN and inf become 0."""
    values = np.ascontiguousarray(rows).view(">f4" if msg.is_bigendian else "<f4")
    values = values.astype(np.float64)  # float64 so that max - min cannot overflow
    finite = np.isfinite(values)
    out = np.zeros(values.shape, dtype=np.uint8)
    if finite.any():
        low, high = values[finite].min(), values[finite].max()
        if high > low:
            scaled = np.rint((values[finite] - low) * (255.0 / (high - low)))
            out[finite] = np.clip(scaled, 0, 255).astype(np.uint8)
    return out


_BGR8 = RawEncoding(3, _cvt_color("COLOR_BGR2GRAY", 3))
_MONO8 = RawEncoding(1, _mono8)
_MONO16 = RawEncoding(2, _mono16)
_UYVY = RawEncoding(2, _luma_at(1))  # U Y0 V Y1
_YUYV = RawEncoding(2, _luma_at(0))  # Y0 U Y1 V

RAW_ENCODINGS: dict[str, RawEncoding] = {
    "mono8": _MONO8,
    "8UC1": _MONO8,
    "mono16": _MONO16,
    "16UC1": _MONO16,
    "rgb8": RawEncoding(3, _cvt_color("COLOR_RGB2GRAY", 3)),
    "bgr8": _BGR8,
    "8UC3": _BGR8,  # cv_bridge treats an untyped 3-channel image as BGR
    "rgba8": RawEncoding(4, _cvt_color("COLOR_RGBA2GRAY", 4)),
    "bgra8": RawEncoding(4, _cvt_color("COLOR_BGRA2GRAY", 4)),
    # The explicit 4-letter OpenCV names: the older 2-letter ones (BayerBG, ...) are shifted by
    # one pixel relative to the ROS names and easy to get wrong.
    "bayer_rggb8": RawEncoding(1, _demosaic("COLOR_BayerRGGB2GRAY")),
    "bayer_bggr8": RawEncoding(1, _demosaic("COLOR_BayerBGGR2GRAY")),
    "bayer_gbrg8": RawEncoding(1, _demosaic("COLOR_BayerGBRG2GRAY")),
    "bayer_grbg8": RawEncoding(1, _demosaic("COLOR_BayerGRBG2GRAY")),
    "yuv422": _UYVY,  # the ROS name for UYVY
    "uyvy": _UYVY,
    "UYVY": _UYVY,
    "yuyv": _YUYV,
    "yuv422_yuy2": _YUYV,
    "YUYV": _YUYV,
    "32FC1": RawEncoding(4, _float32),
}


# ---------------------------------------------------------------------------------------------
# Decoding


def decode_gray(msg: ImageMessage, max_pixels: int = DEFAULT_MAX_PIXELS) -> Gray:
    """The message's pixels as a C-contiguous, writable 2-D uint8 gray image.

    An image whose header (raw: width and height; compressed: `claimed_size`) claims more
    than `max_pixels` pixels is refused before anything is decoded or allocated.

    Raises:
        ImageDecodeError: the message could not be deserialized (`msg.decode_error`), the raw
            encoding is unknown, width/height/step/data length do not fit together, or the
            compressed data is empty, neither JPEG nor PNG, or fails to decode; problem
            TOO_LARGE when the header claims more than `max_pixels`.
    """
    if msg.decode_error is not None:
        raise ImageDecodeError(msg.decode_error, UNDESERIALIZABLE)
    check_pixel_cap(_claimed(msg), max_pixels, _where(msg))
    gray = _decode_compressed(msg) if msg.kind == "compressed" else _decode_raw(msg)
    out = np.ascontiguousarray(gray, dtype=np.uint8)
    # A view on the message bytes is read-only; callers may want to modify the image in place.
    return out if out.flags.writeable else out.copy()


def check_pixel_cap(size: tuple[int, int] | None, max_pixels: int, where: str) -> None:
    """Raises ImageDecodeError (TOO_LARGE) when `size` (width, height) exceeds the cap."""
    if size is not None and size[0] * size[1] > max_pixels:
        raise ImageDecodeError(
            f"{where}: its header claims {size[0]}x{size[1]} = {size[0] * size[1]} pixels, "
            f"more than --max-pixels {max_pixels}; refused without decoding",
            TOO_LARGE,
        )


def _claimed(msg: ImageMessage) -> tuple[int, int] | None:
    if msg.kind == "compressed":
        return claimed_size(msg.data)
    return max(msg.width, 0), max(msg.height, 0)


def _where(msg: ImageMessage) -> str:
    return f"image on {msg.topic} at log time {msg.log_time_ns}"


def _decode_raw(msg: ImageMessage) -> Gray:
    from doseqslam_logs.sources.opencv_quiet import cv2

    layout = RAW_ENCODINGS.get(msg.encoding)
    if layout is None:
        raise ImageDecodeError(
            f"{_where(msg)}: unknown raw image encoding {msg.encoding!r}", UNKNOWN_ENCODING
        )
    rows = pixel_rows(msg, layout.bytes_per_pixel)
    try:
        return layout.to_gray(rows, msg)
    except cv2.error as exc:
        first_line = str(exc).strip().splitlines()[-1] if str(exc).strip() else "cv2.error"
        raise ImageDecodeError(
            f"{_where(msg)}: cannot convert {msg.encoding} {msg.width}x{msg.height} ({first_line})",
            CONVERSION_FAILED,
        ) from exc


def pixel_rows(msg: ImageMessage, bytes_per_pixel: int) -> Rows:
    """The pixel bytes as (height, width * bytes_per_pixel), row padding (`step`) removed."""
    width, height, step = msg.width, msg.height, msg.step
    if not msg.data:
        raise ImageDecodeError(
            f"{_where(msg)}: {msg.encoding} image ({width}x{height}) has no data", EMPTY_IMAGE
        )
    if width <= 0 or height <= 0:
        raise ImageDecodeError(
            f"{_where(msg)}: empty {msg.encoding} image ({width}x{height})", EMPTY_IMAGE
        )
    row_bytes = width * bytes_per_pixel
    if step < row_bytes:
        raise ImageDecodeError(
            f"{_where(msg)}: step {step} is less than width {width} x {bytes_per_pixel} bytes "
            f"per pixel = {row_bytes} for {msg.encoding}",
            RAW_SIZE_MISMATCH,
        )
    # The ROS definition is exactly step * rows bytes; any other size means the header and the
    # data disagree (e.g. a mono16 image labelled mono8), so guessing would give garbage pixels.
    if len(msg.data) != height * step:
        raise ImageDecodeError(
            f"{_where(msg)}: {len(msg.data)} data bytes, expected height {height} x step {step} "
            f"= {height * step} for {msg.encoding}",
            RAW_SIZE_MISMATCH,
        )
    rows: Rows = np.frombuffer(msg.data, dtype=np.uint8).reshape(height, step)
    return rows[:, :row_bytes]


_COMPRESSED_MAGIC = (b"\xff\xd8\xff", b"\x89PNG")  # JPEG, PNG

# libjpeg and libpng report damage they decode around ("Corrupt JPEG data: premature end of
# data segment", "bad Huffman code", "libpng error: IDAT: CRC error") by printing to the
# process's stderr, and OpenCV then returns an image with gray or garbled rows. The text below,
# captured while decoding, marks such an image as corrupt; any other output (benign warnings
# such as "Invalid SOS parameters for sequential JPEG") is dropped, never printed.
_CORRUPTION_SIGNS = ("corrupt", "premature end", "error", "bad huffman")
# OpenCV's own log lines start "[ERROR:0@0.849] global grfmt_png.cpp:297 readHeader ": the
# time and the source line vary, the rest says what is wrong.
_OPENCV_LOG_PREFIX = re.compile(r"^\[\s*\w+:\d+@[\d.]+\]\s*(global\s+\S+\s+\w+\s+)?")
_STDERR_LOCK = threading.Lock()  # fd 2 is process-wide: one capture at a time


_sink: Any = None  # an unnamed temporary file that receives fd 2 while decoding


def _stderr_sink() -> Any:
    global _sink
    if _sink is None or _sink.closed:
        _sink = tempfile.TemporaryFile(buffering=0)  # noqa: SIM115 - lives with the process
    return _sink


@contextlib.contextmanager
def captured_stderr() -> Iterator[list[str]]:
    """Redirect file descriptor 2 into a temporary file; yields a list that receives the text
    written meanwhile. Output of other threads in that window is captured too (the decode
    is short, and nothing else of ours writes to stderr while it runs). Without a usable fd 2
    (a daemon), nothing is captured."""
    text: list[str] = []
    with _STDERR_LOCK:
        try:
            sink = _stderr_sink()
            sink.seek(0)
            sink.truncate()
            with contextlib.suppress(AttributeError, ValueError, OSError):
                sys.stderr.flush()
            saved = os.dup(2)
        except OSError:
            yield text
            return
        try:
            os.dup2(sink.fileno(), 2)
            try:
                yield text
            finally:
                os.dup2(saved, 2)
        finally:
            os.close(saved)
        sink.seek(0)
        text.append(sink.read(4096).decode("utf-8", "replace"))


def _decode_compressed(msg: ImageMessage) -> Gray:
    from doseqslam_logs.sources.opencv_quiet import cv2

    what = f"{_where(msg)}: compressed image (format {msg.encoding!r})"
    if not msg.data:
        raise ImageDecodeError(f"{what} has no data", EMPTY_IMAGE)
    if not msg.data.startswith(_COMPRESSED_MAGIC):
        raise ImageDecodeError(
            f"{what} is neither JPEG nor PNG (starts with {msg.data[:8].hex(' ')})",
            NOT_JPEG_OR_PNG,
        )
    with captured_stderr() as output:
        try:
            gray = cv2.imdecode(np.frombuffer(msg.data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
        except cv2.error as exc:
            raise ImageDecodeError(f"{what} could not be decoded", CORRUPT_COMPRESSED) from exc
    complaint = next(
        (
            _OPENCV_LOG_PREFIX.sub("", line).strip()
            for line in "".join(output).splitlines()
            if any(sign in line.lower() for sign in _CORRUPTION_SIGNS)
        ),
        None,
    )
    because = f" ({complaint})" if complaint else ""
    if gray is None or gray.ndim != 2 or gray.size == 0:
        raise ImageDecodeError(f"{what} could not be decoded{because}", CORRUPT_COMPRESSED)
    if complaint is not None:  # decoded around the damage: gray or garbled rows
        raise ImageDecodeError(f"{what} is corrupt{because}", CORRUPT_COMPRESSED)
    return np.asarray(gray, dtype=np.uint8)


# ---------------------------------------------------------------------------------------------
# Decoded messages -> ImageMessage


@dataclass(frozen=True)
class RecordInfo:
    """What the container says about one message (as opposed to what the message says)."""

    topic: str
    log_time_ns: int
    publish_time_ns: int | None = None
    sequence: int | None = None


def _stamp_ns(stamp: Any) -> int | None:
    """Nanoseconds of a ROS time (sec/nanosec), protobuf Timestamp (seconds/nanos) or JSON
    foxglove time (sec/nsec); None when the message carries none of these, or an invalid one
    (negative seconds, nanoseconds outside [0, 1e9), later than MAX_TIME_NS): the frame then
    falls back to its log time, counted, as for a missing stamp."""
    for sec_name, nsec_name in (("sec", "nanosec"), ("seconds", "nanos"), ("sec", "nsec")):
        sec, nsec = getattr(stamp, sec_name, None), getattr(stamp, nsec_name, None)
        if sec is not None and nsec is not None:
            if int(sec) < 0 or not 0 <= int(nsec) < 1_000_000_000:
                return None
            total = int(sec) * 1_000_000_000 + int(nsec)
            return total if total <= MAX_TIME_NS else None
    return None


def _as_bytes(data: Any) -> bytes:
    if isinstance(data, bytes):
        return data
    if isinstance(data, np.ndarray):  # rosbags gives uint8[] fields as numpy arrays
        return data.tobytes()
    return bytes(data)


def _message(
    rec: RecordInfo,
    stamp: Any,
    kind: ImageKind,
    encoding: Any,
    data: Any,
    size: tuple[Any, Any, Any] = (0, 0, 0),
    big_endian: Any = False,
) -> ImageMessage:
    """One ImageMessage; `size` is (width, height, step) of a raw image."""
    width, height, step = size
    return ImageMessage(
        topic=rec.topic,
        log_time_ns=rec.log_time_ns,
        header_stamp_ns=_stamp_ns(stamp),
        kind=kind,
        encoding=str(encoding),
        width=int(width),
        height=int(height),
        step=int(step),
        is_bigendian=bool(big_endian),
        data=_as_bytes(data),
        publish_time_ns=rec.publish_time_ns,
        sequence=rec.sequence,
    )


def _ros_raw(msg: Any, rec: RecordInfo) -> ImageMessage:
    size = (msg.width, msg.height, msg.step)
    return _message(rec, msg.header.stamp, "raw", msg.encoding, msg.data, size, msg.is_bigendian)


def _ros_compressed(msg: Any, rec: RecordInfo) -> ImageMessage:
    return _message(rec, msg.header.stamp, "compressed", msg.format, msg.data)


def _foxglove_raw(msg: Any, rec: RecordInfo) -> ImageMessage:
    # Foxglove RawImage has no endianness field; its 16-bit encodings are little-endian.
    size = (msg.width, msg.height, msg.step)
    return _message(rec, msg.timestamp, "raw", msg.encoding, msg.data, size)


def _foxglove_compressed(msg: Any, rec: RecordInfo) -> ImageMessage:
    return _message(rec, msg.timestamp, "compressed", msg.format, msg.data)


@dataclass(frozen=True)
class ImageType:
    """One recognised image message type."""

    kind: ImageKind
    build: Callable[[Any, RecordInfo], ImageMessage]


_ROS_RAW = ImageType("raw", _ros_raw)
_ROS_COMPRESSED = ImageType("compressed", _ros_compressed)
_FOXGLOVE_RAW = ImageType("raw", _foxglove_raw)
_FOXGLOVE_COMPRESSED = ImageType("compressed", _foxglove_compressed)

IMAGE_TYPES: dict[str, ImageType] = {
    "sensor_msgs/msg/Image": _ROS_RAW,
    "sensor_msgs/Image": _ROS_RAW,
    "sensor_msgs/msg/CompressedImage": _ROS_COMPRESSED,
    "sensor_msgs/CompressedImage": _ROS_COMPRESSED,
    "foxglove.RawImage": _FOXGLOVE_RAW,
    "foxglove.CompressedImage": _FOXGLOVE_COMPRESSED,
    "foxglove_msgs/msg/RawImage": _FOXGLOVE_RAW,
    "foxglove_msgs/msg/CompressedImage": _FOXGLOVE_COMPRESSED,
}


def is_image_type(type_name: str) -> bool:
    """Whether messages of this type name are camera images."""
    return type_name in IMAGE_TYPES


def image_from_payload(
    type_name: str, payload: bytes, deserialize: Callable[[bytes], Any], rec: RecordInfo
) -> ImageMessage:
    """Deserialize one image message and map its fields; never raises for a bad payload.

    A payload that does not deserialize, or lacks the expected fields, gives an ImageMessage with
    `decode_error` set, so that one corrupt message does not end the iteration.

    Raises:
        KeyError: `type_name` is not an image type (check with `is_image_type` first).
    """
    image_type = IMAGE_TYPES[type_name]
    try:
        return image_type.build(deserialize(payload), rec)
    # Any deserializer (CDR, ROS 1, protobuf, JSON) may raise any exception on a corrupt message.
    except Exception as exc:
        return ImageMessage(
            topic=rec.topic,
            log_time_ns=rec.log_time_ns,
            header_stamp_ns=None,
            kind=image_type.kind,
            encoding="",
            width=0,
            height=0,
            step=0,
            is_bigendian=False,
            data=b"",
            publish_time_ns=rec.publish_time_ns,
            sequence=rec.sequence,
            decode_error=(
                f"image on {rec.topic} at log time {rec.log_time_ns}: cannot deserialize "
                f"{type_name} message ({type(exc).__name__}: {exc})"
            ),
        )
