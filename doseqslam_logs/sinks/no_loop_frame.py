"""The "no loop" frame: what the match image topic shows between loop closures.

A viewer keeps the latest message of a topic, so without a message of its own between loop
closures the match panel would go on showing the last match. The frame is grey, of the
camera's size, labelled "no loop", and is one of the camera's own messages with its image
replaced: same schema, same message encoding, the same JPEG or PNG format, or the same raw
encoding, size and row step. It is built once per run, from one camera message.
"""

from __future__ import annotations

import base64
import json
import struct

import numpy as np

from ..sources.base import ImageMessage
from ..sources.image_header import DEFAULT_MAX_PIXELS, claimed_size
from ..sources.images import captured_stderr

NO_LOOP_TEXT = "no loop"
GREY = 0x80  # every byte: mid grey in 8-bit and 16-bit encodings, whatever the byte order
WHITE = 0xFF
# Raw encodings the label is drawn in: bytes per pixel of each channel, channels.
_LABELLED_RAW = {
    "mono8": (1, 1),
    "8UC1": (1, 1),
    "rgb8": (1, 3),
    "bgr8": (1, 3),
    "8UC3": (1, 3),
    "rgba8": (1, 4),
    "bgra8": (1, 4),
    "8UC4": (1, 4),
    "mono16": (2, 1),
    "16UC1": (2, 1),
}


def no_loop_message(sample: bytes, image: ImageMessage, message_encoding: str) -> bytes | None:
    """`sample` (one camera message, `image` its decoded fields) with its image replaced by
    the grey "no loop" frame; None when the image or the message is not understood (the
    match topic then gets no frame between loop closures)."""
    if image.decode_error is not None or not image.data:
        return None
    pixels = _compressed(image) if image.kind == "compressed" else _raw(image)
    if pixels is None:
        return None
    return _with_data(sample, image.data, pixels, message_encoding)


def _label(frame: np.ndarray, white: int) -> None:
    """ "no loop" in the middle of `frame` (height, width, channels), in place."""
    from ..sources.opencv_quiet import cv2

    height, width = frame.shape[:2]
    scale = max(width / 320.0, 0.3)
    thickness = max(1, round(scale * 2))
    font = cv2.FONT_HERSHEY_SIMPLEX
    (text_w, text_h), _ = cv2.getTextSize(NO_LOOP_TEXT, font, scale, thickness)
    origin = ((width - text_w) // 2, (height + text_h) // 2)
    color = (white,) * frame.shape[2]
    cv2.putText(frame, NO_LOOP_TEXT, origin, font, scale, color, thickness, cv2.LINE_AA)


def _compressed(image: ImageMessage) -> bytes | None:
    from ..sources.opencv_quiet import cv2

    # As the run's decoder does: an image whose header claims more than the cap is never
    # decoded (a decompression bomb), and libjpeg's or libpng's complaints about a damaged one
    # stay off stderr (one line per error); such an image is simply not the sample.
    size = claimed_size(image.data)
    if size is None or size[0] * size[1] > DEFAULT_MAX_PIXELS:
        return None
    with captured_stderr() as complaints:
        camera = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_UNCHANGED)
    if camera is None or "".join(complaints).strip():
        return None
    channels = 1 if camera.ndim == 2 else camera.shape[2]
    frame = np.full((*camera.shape[:2], channels), GREY, camera.dtype)
    _label(frame, 0xFFFF if camera.dtype == np.uint16 else WHITE)
    extension = ".png" if "png" in image.encoding.lower() else ".jpg"
    ok, encoded = cv2.imencode(extension, frame if channels > 1 else frame[:, :, 0])
    return encoded.tobytes() if ok else None


def _raw(image: ImageMessage) -> bytes | None:
    height, width, step = image.height, image.width, image.step
    if height <= 0 or step <= 0 or len(image.data) != height * step:
        return None
    rows = np.full((height, step), GREY, np.uint8)
    layout = _LABELLED_RAW.get(image.encoding)
    if layout is not None and width * layout[0] * layout[1] <= step:
        depth, channels = layout
        dtype = np.uint8 if depth == 1 else np.uint16
        frame = np.full((height, width, channels), GREY * (0x101 if depth == 2 else 1), dtype)
        _label(frame, int(np.iinfo(dtype).max))  # 0xFF.. reads the same in either byte order
        rows[:, : width * depth * channels] = frame.view(np.uint8).reshape(height, -1)
    return rows.tobytes()


def _with_data(sample: bytes, old: bytes, new: bytes, message_encoding: str) -> bytes | None:
    if message_encoding == "json":
        return _json_with_data(sample, old, new)
    if message_encoding == "protobuf":
        return _protobuf_with_data(sample, old, new)
    if message_encoding in ("cdr", "ros1"):
        return _ros_with_data(sample, old, new, message_encoding == "cdr")
    return None


def _json_with_data(sample: bytes, old: bytes, new: bytes) -> bytes | None:
    try:
        message = json.loads(sample)
    except ValueError:
        return None
    if not isinstance(message, dict) or message.get("data") != base64.b64encode(old).decode():
        return None
    message["data"] = base64.b64encode(new).decode()
    return json.dumps(message, separators=(",", ":")).encode()


def _ros_with_data(sample: bytes, old: bytes, new: bytes, cdr: bool) -> bytes | None:
    """The uint8[] field holding `old` (a 4-byte length, then the bytes) holds `new`; in CDR
    the fields after it (the format string of foxglove_msgs/CompressedImage) are realigned."""
    order = "<" if not cdr or sample[1:2] in (b"\x01", b"\x03") else ">"
    prefix = struct.pack(order + "I", len(old))
    start = sample.rfind(prefix + old)
    if start < (4 if cdr else 0):
        return None
    begin, end = start + 4, start + 4 + len(old)
    rest = sample[end:]
    if cdr and rest:
        rest = rest[(-(end - 4)) % 4 :]  # CDR aligns from the end of its 4-byte header
        padding = b"\0" * ((-(begin + len(new) - 4)) % 4)
    else:
        padding = b""
    return sample[:start] + struct.pack(order + "I", len(new)) + new + padding + rest


def _protobuf_with_data(sample: bytes, old: bytes, new: bytes) -> bytes | None:
    """The top-level length-delimited field holding `old` holds `new`."""
    position = 0
    while position < len(sample):
        tag, after_tag = _varint(sample, position)
        if tag is None:
            return None
        wire = tag & 7
        if wire == 0:
            _, position = _varint(sample, after_tag)
        elif wire == 1:
            position = after_tag + 8
        elif wire == 5:
            position = after_tag + 4
        elif wire == 2:
            length, begin = _varint(sample, after_tag)
            if length is None:
                return None
            end = begin + length
            if sample[begin:end] == old:
                return sample[:after_tag] + _encode_varint(len(new)) + new + sample[end:]
            position = end
        else:
            return None
    return None


def _varint(data: bytes, position: int) -> tuple[int | None, int]:
    value, shift = 0, 0
    while position < len(data) and shift < 64:
        byte = data[position]
        value |= (byte & 0x7F) << shift
        position += 1
        if not byte & 0x80:
            return value, position
        shift += 7
    return None, position


def _encode_varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte, value = value & 0x7F, value >> 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)
