"""decode_gray on small synthetic images, each checked against a result computed here."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from doseqslam_logs.errors import ImageDecodeError
from doseqslam_logs.sources.base import ImageMessage
from doseqslam_logs.sources.images import (
    RAW_ENCODINGS,
    RecordInfo,
    decode_gray,
    image_from_payload,
)

RNG = np.random.default_rng(1234)


def raw(encoding: str, pixels: np.ndarray, pad: int = 0, big_endian: bool = False) -> ImageMessage:
    """A raw ImageMessage whose rows are the bytes of `pixels` rows plus `pad` junk bytes."""
    height, width = pixels.shape[:2]
    rows = pixels.reshape(height, -1).view(np.uint8) if pixels.dtype != np.uint8 else pixels
    rows = rows.reshape(height, -1)
    junk = np.full((height, pad), 0xAB, dtype=np.uint8)
    data = np.hstack([rows, junk]).tobytes()
    return ImageMessage(
        topic="/cam",
        log_time_ns=1,
        header_stamp_ns=None,
        kind="raw",
        encoding=encoding,
        width=width,
        height=height,
        step=rows.shape[1] + pad,
        is_bigendian=big_endian,
        data=data,
    )


def compressed(data: bytes, fmt: str = "jpeg") -> ImageMessage:
    return ImageMessage(
        topic="/cam",
        log_time_ns=1,
        header_stamp_ns=None,
        kind="compressed",
        encoding=fmt,
        width=0,
        height=0,
        step=0,
        is_bigendian=False,
        data=data,
    )


def luma(red: np.ndarray, green: np.ndarray, blue: np.ndarray) -> np.ndarray:
    """ITU-R BT.601 luma, the weights OpenCV's RGB2GRAY uses, rounded to nearest."""
    value = 0.299 * red.astype(float) + 0.587 * green.astype(float) + 0.114 * blue.astype(float)
    return np.rint(value).astype(np.uint8)


def assert_gray(actual: np.ndarray, expected: np.ndarray, tolerance: int = 0) -> None:
    assert actual.dtype == np.uint8
    assert actual.ndim == 2
    assert actual.flags.c_contiguous
    assert actual.flags.writeable
    assert actual.shape == expected.shape
    difference = np.abs(actual.astype(int) - expected.astype(int))
    assert difference.max(initial=0) <= tolerance


# --- raw encodings --------------------------------------------------------------------------


@pytest.mark.parametrize("encoding", ["mono8", "8UC1"])
@pytest.mark.parametrize("pad", [0, 5])
def test_mono8(encoding: str, pad: int) -> None:
    image = RNG.integers(0, 256, (7, 9), dtype=np.uint8)
    assert_gray(decode_gray(raw(encoding, image, pad)), image)


@pytest.mark.parametrize("encoding", ["mono16", "16UC1"])
@pytest.mark.parametrize("big_endian", [False, True])
@pytest.mark.parametrize("pad", [0, 6])
def test_mono16_keeps_the_high_byte(encoding: str, big_endian: bool, pad: int) -> None:
    values = RNG.integers(0, 65536, (5, 6), dtype=np.uint16)
    stored = values.astype(">u2" if big_endian else "<u2")
    msg = raw(encoding, stored, pad, big_endian=big_endian)
    assert_gray(decode_gray(msg), (values // 256).astype(np.uint8))


def test_mono16_endianness_matters() -> None:
    values = np.array([[0x1234, 0xFF00]], dtype=np.uint16)
    little = decode_gray(raw("mono16", values.astype("<u2")))
    big = decode_gray(raw("mono16", values.astype(">u2"), big_endian=True))
    assert little.tolist() == big.tolist() == [[0x12, 0xFF]]
    wrong = decode_gray(raw("mono16", values.astype("<u2"), big_endian=True))
    assert wrong.tolist() == [[0x34, 0x00]]


@pytest.mark.parametrize(
    ("encoding", "order"),
    [
        ("rgb8", "rgb"),
        ("bgr8", "bgr"),
        ("8UC3", "bgr"),
        ("rgba8", "rgba"),
        ("bgra8", "bgra"),
    ],
)
@pytest.mark.parametrize("pad", [0, 3])
def test_colour(encoding: str, order: str, pad: int) -> None:
    red, green, blue, alpha = (RNG.integers(0, 256, (6, 11), dtype=np.uint8) for _ in range(4))
    planes = {"r": red, "g": green, "b": blue, "a": alpha}
    pixels = np.dstack([planes[c] for c in order])
    assert_gray(decode_gray(raw(encoding, pixels, pad)), luma(red, green, blue), tolerance=1)


def test_rgb_and_bgr_differ() -> None:
    pixels = np.zeros((2, 2, 3), dtype=np.uint8)
    pixels[..., 0] = 255  # red in rgb8, blue in bgr8
    assert decode_gray(raw("rgb8", pixels))[0, 0] == 76
    assert decode_gray(raw("bgr8", pixels))[0, 0] == 29


def mosaic(pattern: str, bgr: tuple[int, int, int], height: int = 8, width: int = 10) -> np.ndarray:
    """A uniformly coloured Bayer image; `pattern` names the 2x2 cell row by row, e.g. "rggb"."""
    value = {"b": bgr[0], "g": bgr[1], "r": bgr[2]}
    image = np.empty((height, width), dtype=np.uint8)
    for index, colour in enumerate(pattern):
        image[index // 2 :: 2, index % 2 :: 2] = value[colour]
    return image


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_bayer(pattern: str) -> None:
    # Red and blue far apart, so that a demosaic with the wrong pattern gives another gray.
    bgr = (220, 120, 10)
    expected = luma(np.array(bgr[2]), np.array(bgr[1]), np.array(bgr[0]))
    gray = decode_gray(raw(f"bayer_{pattern}8", mosaic(pattern, bgr)))
    assert gray.shape == (8, 10) and gray.flags.c_contiguous
    interior = np.ascontiguousarray(gray[2:-2, 2:-2])  # demosaicing extrapolates at the border
    assert_gray(interior, np.full(interior.shape, expected, dtype=np.uint8), tolerance=1)
    swapped = decode_gray(raw(f"bayer_{pattern}8", mosaic(pattern, (10, 120, 220))))
    assert abs(int(swapped[4, 4]) - int(expected)) > 20


@pytest.mark.parametrize("pad", [0, 4])
@pytest.mark.parametrize(
    ("encoding", "y_first"),
    [
        ("yuv422", False),
        ("uyvy", False),
        ("UYVY", False),
        ("yuyv", True),
        ("yuv422_yuy2", True),
        ("YUYV", True),
    ],
)
def test_packed_yuv_takes_y(encoding: str, y_first: bool, pad: int) -> None:
    height, width = 4, 6
    y = RNG.integers(0, 256, (height, width), dtype=np.uint8)
    chroma = RNG.integers(0, 256, (height, width), dtype=np.uint8)  # U, V alternating
    packed = np.empty((height, width * 2), dtype=np.uint8)
    packed[:, 0::2], packed[:, 1::2] = (y, chroma) if y_first else (chroma, y)
    msg = raw(encoding, packed, pad)
    msg = replace(msg, width=width)  # 2 bytes per pixel
    assert_gray(decode_gray(msg), y)


@pytest.mark.parametrize("big_endian", [False, True])
def test_float32_scaled_to_finite_range(big_endian: bool) -> None:
    values = np.array([[1.0, 2.0, 3.0], [np.nan, np.inf, -np.inf]], dtype=np.float32)
    stored = values.astype(">f4" if big_endian else "<f4")
    msg = raw("32FC1", stored.view(np.uint8).reshape(2, -1), pad=2, big_endian=big_endian)
    msg = replace(msg, width=3)
    assert decode_gray(msg).tolist() == [[0, 128, 255], [0, 0, 0]]


def test_float32_without_finite_values_is_black() -> None:
    values = np.full((2, 2), np.nan, dtype="<f4")
    msg = replace(raw("32FC1", values.view(np.uint8)), width=2)
    assert decode_gray(msg).tolist() == [[0, 0], [0, 0]]


def test_every_registered_encoding_is_tested() -> None:
    tested = {
        "mono8", "8UC1", "mono16", "16UC1", "rgb8", "bgr8", "8UC3", "rgba8", "bgra8",
        "bayer_rggb8", "bayer_bggr8", "bayer_gbrg8", "bayer_grbg8",
        "yuv422", "uyvy", "UYVY", "yuyv", "yuv422_yuy2", "YUYV", "32FC1",
    }  # fmt: skip
    assert set(RAW_ENCODINGS) == tested


def test_result_is_writable_and_independent_of_the_message() -> None:
    image = RNG.integers(0, 256, (3, 4), dtype=np.uint8)
    msg = raw("mono8", image)
    gray = decode_gray(msg)
    gray[:] = 0
    assert decode_gray(msg).tolist() == image.tolist()


# --- raw errors -----------------------------------------------------------------------------


def test_step_too_small() -> None:
    msg = ImageMessage(**{**raw("rgb8", np.zeros((2, 4, 3), np.uint8)).__dict__, "step": 11})
    with pytest.raises(ImageDecodeError, match=r"step 11 .*width 4 x 3 .* = 12"):
        decode_gray(msg)


@pytest.mark.parametrize("extra", [-1, 1, 40])
def test_data_length_must_be_height_times_step(extra: int) -> None:
    msg = raw("mono8", np.zeros((3, 4), np.uint8), pad=1)
    data = msg.data + b"\0" * extra if extra > 0 else msg.data[:extra]
    with pytest.raises(ImageDecodeError, match=rf"{len(data)} data bytes.*3 x step 5 = 15"):
        decode_gray(replace(msg, data=data))


def test_unknown_encoding() -> None:
    with pytest.raises(ImageDecodeError, match="unknown raw image encoding 'nv21'"):
        decode_gray(raw("nv21", np.zeros((2, 2), np.uint8)))


def test_empty_raw_image() -> None:
    msg = ImageMessage(**{**raw("mono8", np.zeros((1, 1), np.uint8)).__dict__, "width": 0})
    with pytest.raises(ImageDecodeError, match=r"empty mono8 image \(0x1\)"):
        decode_gray(msg)


# --- compressed -----------------------------------------------------------------------------


def test_png_is_lossless() -> None:
    image = RNG.integers(0, 256, (13, 17), dtype=np.uint8)
    ok, png = cv2.imencode(".png", image)
    assert ok
    # The format string is not trusted: a wrong one must not matter.
    msg = compressed(png.tobytes(), fmt="rgb8; jpeg compressed bgr8")
    assert_gray(decode_gray(msg), image)


def test_jpeg_colour_to_gray() -> None:
    colour = np.zeros((32, 32, 3), dtype=np.uint8)
    colour[:16] = (200, 30, 60)
    colour[16:] = (20, 240, 90)
    ok, jpeg = cv2.imencode(".jpg", colour, [cv2.IMWRITE_JPEG_QUALITY, 100])
    assert ok
    expected = luma(colour[..., 2], colour[..., 1], colour[..., 0])
    assert_gray(decode_gray(compressed(jpeg.tobytes(), "jpg")), expected, tolerance=4)


def test_empty_compressed() -> None:
    with pytest.raises(ImageDecodeError, match=r"format 'jpeg'.* has no data"):
        decode_gray(compressed(b""))


def test_compressed_neither_jpeg_nor_png() -> None:
    with pytest.raises(ImageDecodeError, match=r"format 'bmp'.*neither JPEG nor PNG"):
        decode_gray(compressed(b"BM\x00\x00\x00\x00", "bmp"))


@pytest.mark.parametrize("magic", [b"\xff\xd8\xff", b"\x89PNG\r\n\x1a\n"])
def test_corrupt_compressed(magic: bytes) -> None:
    with pytest.raises(ImageDecodeError, match=r"format 'jpeg'.*could not be decoded"):
        decode_gray(compressed(magic + b"\x00garbage" * 4))


def test_message_that_did_not_deserialize() -> None:
    def broken(payload: bytes) -> object:
        raise ValueError("short buffer")

    record = RecordInfo("/cam", 42, sequence=7)
    msg = image_from_payload("sensor_msgs/msg/Image", b"\x01", broken, record)
    assert (msg.topic, msg.log_time_ns, msg.sequence, msg.kind) == ("/cam", 42, 7, "raw")
    with pytest.raises(ImageDecodeError, match=r"/cam at log time 42.*short buffer"):
        decode_gray(msg)


# --- properties -----------------------------------------------------------------------------

CHANNEL_ORDER = {"mono8": "", "rgb8": "rgb", "bgr8": "bgr"}


@settings(max_examples=150, deadline=None)
@given(
    encoding=st.sampled_from(sorted(CHANNEL_ORDER)),
    height=st.integers(1, 24),
    width=st.integers(1, 24),
    pad=st.integers(0, 9),
    seed=st.integers(0, 2**32 - 1),
)
def test_property_round_trip(encoding: str, height: int, width: int, pad: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    if encoding == "mono8":
        pixels = rng.integers(0, 256, (height, width), dtype=np.uint8)
        expected, tolerance = pixels, 0
    else:
        planes = {c: rng.integers(0, 256, (height, width), dtype=np.uint8) for c in "rgb"}
        pixels = np.dstack([planes[c] for c in CHANNEL_ORDER[encoding]])
        expected, tolerance = luma(planes["r"], planes["g"], planes["b"]), 1
    assert_gray(decode_gray(raw(encoding, pixels, pad)), expected, tolerance)


ENCODINGS = st.sampled_from([*RAW_ENCODINGS, "", "nv12", "jpeg", "png"]) | st.text(max_size=8)
DATA = st.binary(max_size=600) | st.builds(
    bytes.__add__, st.sampled_from([b"\xff\xd8\xff", b"\x89PNG\r\n\x1a\n"]), st.binary()
)


@settings(max_examples=300, deadline=None)
@given(
    kind=st.sampled_from(["raw", "compressed"]),
    encoding=ENCODINGS,
    width=st.integers(-2, 20),
    height=st.integers(-2, 20),
    step=st.integers(-2, 90),
    big_endian=st.booleans(),
    data=DATA,
)
def test_property_only_image_decode_errors(
    kind: str, encoding: str, width: int, height: int, step: int, big_endian: bool, data: bytes
) -> None:
    fields = (kind, encoding, width, height, step, big_endian, data)
    msg = ImageMessage("/cam", 0, None, *fields)  # type: ignore[arg-type]
    try:
        gray = decode_gray(msg)
    except ImageDecodeError:
        return
    assert gray.dtype == np.uint8 and gray.ndim == 2 and gray.flags.c_contiguous
