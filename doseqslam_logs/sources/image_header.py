"""The width and height an encoded image claims, read from its header without decoding it.

A decoder allocates what the header claims before it reads a single pixel: a 389 kB PNG that
says 20000x20000 took 2 GB, a JPEG header saying 30000x30000 1.85 GB before the decode failed.
`claimed_size` reads the claim (PNG IHDR, JPEG SOF markers, BMP, TIFF, WebP, PNM) so that an
image over the pixel cap is refused before any decoder runs. This OpenCV has no header-only
query in Python, hence the parsers; each is a few fixed offsets of the format's specification.
"""

from __future__ import annotations

import re
import struct

# The default pixel cap (`--max-pixels`): 64 megapixels (8192 x 8192). A gray image of that
# size is 64 MB; with the decoder's own buffers a decode stays well under 1 GB.
DEFAULT_MAX_PIXELS = 8192 * 8192

# JPEG start-of-frame markers: C0-CF except DHT (C4), JPG (C8) and DAC (CC).
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# Markers without a length field: TEM, RST0-7, SOI, EOI.
_JPEG_STANDALONE = frozenset({0x01, *range(0xD0, 0xD9)})
_PNM = re.compile(rb"^P[1-6](?:\s+|#[^\n]*\n)+(\d+)(?:\s+|#[^\n]*\n)+(\d+)")
_TIFF_WIDTH, _TIFF_HEIGHT = 256, 257


def claimed_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) the image header claims, or None when the format is not recognised or
    its header is cut short (the decoder then refuses it, without allocating anything large)."""
    for parse in (_png, _jpeg, _bmp, _tiff, _webp, _pnm):
        size = parse(data)
        if size is not None:
            return size
    return None


def _png(data: bytes) -> tuple[int, int] | None:
    if not data.startswith(b"\x89PNG\r\n\x1a\n") or data[12:16] != b"IHDR" or len(data) < 24:
        return None
    width, height = struct.unpack_from(">II", data, 16)
    return width, height


def _jpeg(data: bytes) -> tuple[int, int] | None:
    """The first SOF marker's size; markers are walked by their length fields."""
    if not data.startswith(b"\xff\xd8"):
        return None
    position = 2
    while position + 4 <= len(data):
        if data[position] != 0xFF:
            return None
        marker = data[position + 1]
        if marker == 0xFF:  # fill byte
            position += 1
            continue
        if marker in _JPEG_STANDALONE:
            position += 2
            continue
        if marker in _JPEG_SOF:
            if position + 9 > len(data):
                return None
            height, width = struct.unpack_from(">HH", data, position + 5)
            return width, height
        if marker == 0xDA:  # start of scan before any frame header
            return None
        (length,) = struct.unpack_from(">H", data, position + 2)
        position += 2 + length
    return None


def _bmp(data: bytes) -> tuple[int, int] | None:
    if not data.startswith(b"BM") or len(data) < 26:
        return None
    (header_size,) = struct.unpack_from("<I", data, 14)
    if header_size == 12:  # OS/2 BITMAPCOREHEADER: unsigned 16-bit sizes
        width, height = struct.unpack_from("<HH", data, 18)
        return width, height
    width, height = struct.unpack_from("<ii", data, 18)
    return abs(width), abs(height)  # a negative height means top-down rows


def _tiff(data: bytes) -> tuple[int, int] | None:
    """Width and height tags of the first IFD (SHORT or LONG)."""
    if data[:4] not in (b"II*\x00", b"MM\x00*") or len(data) < 8:
        return None
    order = "<" if data[:2] == b"II" else ">"
    (ifd,) = struct.unpack_from(order + "I", data, 4)
    if ifd + 2 > len(data):
        return None
    (entries,) = struct.unpack_from(order + "H", data, ifd)
    found: dict[int, int] = {}
    for index in range(entries):
        entry = ifd + 2 + 12 * index
        if entry + 12 > len(data):
            break
        tag, kind = struct.unpack_from(order + "HH", data, entry)
        if tag in (_TIFF_WIDTH, _TIFF_HEIGHT):
            form = order + ("H" if kind == 3 else "I")
            (found[tag],) = struct.unpack_from(form, data, entry + 8)
    if _TIFF_WIDTH in found and _TIFF_HEIGHT in found:
        return found[_TIFF_WIDTH], found[_TIFF_HEIGHT]
    return None


def _webp(data: bytes) -> tuple[int, int] | None:
    if not (data.startswith(b"RIFF") and data[8:12] == b"WEBP") or len(data) < 30:
        return None
    kind = data[12:16]
    if kind == b"VP8X":  # 24-bit width-1 and height-1
        width = int.from_bytes(data[24:27], "little") + 1
        height = int.from_bytes(data[27:30], "little") + 1
        return width, height
    if kind == b"VP8L":  # 14 bits each, minus one, after the 0x2f signature
        (bits,) = struct.unpack_from("<I", data, 21)
        return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    if kind == b"VP8 ":  # key frame: 14-bit sizes after the start code
        width, height = struct.unpack_from("<HH", data, 26)
        return width & 0x3FFF, height & 0x3FFF
    return None


def _pnm(data: bytes) -> tuple[int, int] | None:
    match = _PNM.match(data[:256])
    return (int(match[1]), int(match[2])) if match else None
