"""Issue #21, items 2-4: no silent loss, `--recover` past damaged chunks, the pixel cap.

Every hostile input is built here, in tmp_path, from a few good RTAB-Map frames: bombs are
headers that claim huge sizes over a few bytes of data, so nothing here allocates much.
"""

from __future__ import annotations

import json
import re
import struct
import zlib
from pathlib import Path

import cv2
import make_bad_inputs as bad
import numpy as np
import pytest
from mcap.reader import make_reader

from doseqslam_logs.cli.main import main
from doseqslam_logs.errors import ExitCode, ImageDecodeError
from doseqslam_logs.sources.base import ImageMessage
from doseqslam_logs.sources.image_header import DEFAULT_MAX_PIXELS, claimed_size
from doseqslam_logs.sources.images import TOO_LARGE, decode_gray

# --- inputs -----------------------------------------------------------------------------------


def png_chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def png_bomb(width: int, height: int) -> bytes:
    """A PNG whose IHDR claims width x height (8-bit gray) over one tiny IDAT."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    idat = zlib.compress(bytes(width + 1))  # one row: a decoder would want them all
    return (
        b"\x89PNG\r\n\x1a\n"
        + png_chunk(b"IHDR", ihdr)
        + png_chunk(b"IDAT", idat)
        + png_chunk(b"IEND", b"")
    )


def jpeg_claiming(jpeg: bytes, width: int, height: int) -> bytes:
    """A real JPEG whose SOF marker is rewritten to claim width x height."""
    data = bytearray(jpeg)
    sof = next(i for i in range(2, len(data) - 9) if data[i] == 0xFF and data[i + 1] == 0xC0)
    struct.pack_into(">HH", data, sof + 5, height, width)
    return bytes(data)


def compressed(data: bytes, log_ns: int = 1) -> ImageMessage:
    return ImageMessage("/cam", log_ns, log_ns, "compressed", "png", 0, 0, 0, False, data)


@pytest.fixture
def jpegs(shared_data: Path) -> list[bytes]:
    return bad.rtabmap_jpegs(shared_data, 6)


def log_with(tmp_path: Path, jpegs: list[bytes], extra: dict[int, bytes]) -> Path:
    """A ROS 2 MCAP of the good frames, frame i replaced by extra[i]."""
    frames = [extra.get(i, data) for i, data in enumerate(jpegs)]
    return bad.write_log(tmp_path / "log.mcap", bad.good_items(frames))


def run_cli(*args: str | Path) -> int:
    try:
        return main([str(a) for a in args])
    except SystemExit as exc:
        return int(exc.code or 0)


def metadata(path: Path) -> dict[str, str]:
    with path.open("rb") as file:
        for record in make_reader(file).iter_metadata():
            if record.name == "doseqslam":
                return dict(record.metadata)
    raise AssertionError(f"{path}: no doseqslam metadata")


# --- item 4: the pixel cap --------------------------------------------------------------------


def test_png_claiming_20000_squared_is_refused_from_its_header() -> None:
    bomb = png_bomb(20000, 20000)
    assert len(bomb) < 100_000 and claimed_size(bomb) == (20000, 20000)
    with pytest.raises(ImageDecodeError) as caught:
        decode_gray(compressed(bomb))
    assert caught.value.problem == TOO_LARGE
    assert "20000x20000" in str(caught.value)


def test_jpeg_sof_claim_is_refused(jpegs: list[bytes]) -> None:
    bomb = jpeg_claiming(jpegs[0], 30000, 30000)
    assert claimed_size(bomb) == (30000, 30000)
    with pytest.raises(ImageDecodeError) as caught:
        decode_gray(compressed(bomb))
    assert caught.value.problem == TOO_LARGE


def test_the_cap_is_an_option(jpegs: list[bytes]) -> None:
    height, width = decode_gray(compressed(jpegs[0])).shape
    assert claimed_size(jpegs[0]) == (width, height)
    with pytest.raises(ImageDecodeError, match="more than --max-pixels"):
        decode_gray(compressed(jpegs[0]), max_pixels=width * height - 1)
    ok, png = cv2.imencode(".png", np.zeros((100, 100), np.uint8))
    assert ok and decode_gray(compressed(png.tobytes()), max_pixels=10_000).shape == (100, 100)


def test_raw_image_claiming_too_many_pixels() -> None:
    raw = ImageMessage("/cam", 1, 1, "raw", "mono8", 9000, 9000, 9000, False, b"\0" * 10)
    with pytest.raises(ImageDecodeError) as caught:
        decode_gray(raw)
    assert caught.value.problem == TOO_LARGE
    assert DEFAULT_MAX_PIXELS < 9000 * 9000


@pytest.mark.parametrize("ext", [".bmp", ".tiff", ".webp", ".pgm", ".png", ".jpg"])
def test_header_sizes_match_what_opencv_decodes(ext: str) -> None:
    image = np.zeros((37, 53, 3), np.uint8)
    ok, encoded = cv2.imencode(ext, image if ext != ".pgm" else image[:, :, 0])
    assert ok
    assert claimed_size(encoded.tobytes()) == (53, 37)


def test_webp_lossless_and_extended_headers() -> None:
    image = np.zeros((37, 53, 3), np.uint8)
    ok, lossless = cv2.imencode(".webp", image, [cv2.IMWRITE_WEBP_QUALITY, 101])
    assert ok and lossless.tobytes()[12:16] == b"VP8L"
    assert claimed_size(lossless.tobytes()) == (53, 37)
    vp8x = b"RIFF" + bytes(4) + b"WEBPVP8X" + bytes(8) + (29999).to_bytes(3, "little") * 2
    assert claimed_size(vp8x) == (30000, 30000)


def test_annotate_skips_an_over_cap_frame_and_counts_it(
    tmp_path: Path, jpegs: list[bytes], capsys: pytest.CaptureFixture[str]
) -> None:
    log = log_with(tmp_path, jpegs, {2: png_bomb(20000, 20000)})
    out = tmp_path / "out.mcap"
    assert run_cli("annotate", log, "-o", out, "--no-verify") == 0
    line = capsys.readouterr().out
    assert "5 frames" in line and "1 skipped frames (1 too large)" in line
    assert json.loads(metadata(out)["frames_skipped_by_reason"]) == {TOO_LARGE: 1}


def test_annotate_on_error_fail_exits_5_for_an_over_cap_frame(
    tmp_path: Path, jpegs: list[bytes], capsys: pytest.CaptureFixture[str]
) -> None:
    log = log_with(tmp_path, jpegs, {1: jpeg_claiming(jpegs[1], 30000, 30000)})
    out = tmp_path / "out.mcap"
    code = run_cli("annotate", log, "-o", out, "--no-verify", "--on-error", "fail")
    assert code == ExitCode.BAD_IMAGE and not out.exists()
    assert "30000x30000" in capsys.readouterr().err


def test_max_pixels_option_lets_a_large_frame_through_or_refuses_all(
    tmp_path: Path, jpegs: list[bytes], capsys: pytest.CaptureFixture[str]
) -> None:
    log = log_with(tmp_path, jpegs, {})
    out = tmp_path / "out.mcap"
    code = run_cli("annotate", log, "-o", out, "--no-verify", "--max-pixels", "1000")
    assert code == ExitCode.BAD_IMAGE  # not one frame under the cap: as for any unusable log
    assert "6 too large" in capsys.readouterr().err


def test_evaluate_images_refuses_a_folder_bomb(tmp_path: Path, jpegs: list[bytes]) -> None:
    folder = tmp_path / "images"
    folder.mkdir()
    for i, data in enumerate(jpegs):
        (folder / f"{i}.jpg").write_bytes(data)
    (folder / "3.jpg").write_bytes(png_bomb(20000, 20000))  # formats are told by content
    np.save(tmp_path / "gt.npy", np.zeros((6, 6), np.uint8))
    args = ("evaluate", "--images", folder, "--fps", "1", "--gt", tmp_path / "gt.npy")
    assert run_cli(*args, "--no-verify") == ExitCode.BAD_IMAGE


# --- item 2: no silent loss -------------------------------------------------------------------

RECORD_HEADER = struct.Struct("<BQ")  # opcode, length
MESSAGE_OPCODE = 0x05


def unchunked_copy(source: Path, target: Path) -> Path:
    """The same records without chunks (mcap's writer adds Statistics and indexes)."""
    from mcap.writer import Writer

    with source.open("rb") as file, target.open("wb") as out:
        reader = make_reader(file)
        writer = Writer(out, use_chunking=False)
        writer.start("ros2", "test")
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages():
            if schema is not None and schema.id not in schema_ids:
                schema_ids[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            if channel.id not in channel_ids:
                channel_ids[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_ids.get(channel.schema_id, 0)
                )
            writer.add_message(
                channel_ids[channel.id], message.log_time, message.data, message.publish_time
            )
        writer.finish()
    return target


def record_offsets(data: bytes, opcode: int) -> list[int]:
    """Offsets of the top-level records with `opcode` (after the leading magic)."""
    offsets, position = [], len(bad.MCAP_MAGIC)
    while position + RECORD_HEADER.size <= len(data):
        op, length = RECORD_HEADER.unpack_from(data, position)
        if op == opcode:
            offsets.append(position)
        if op == bad.FOOTER_OPCODE:
            break
        position += RECORD_HEADER.size + length
    return offsets


def annotate_json(*args: str | Path, capsys: pytest.CaptureFixture[str]) -> dict[str, object]:
    assert run_cli("annotate", *args, "--no-verify", "--json") == 0
    result: dict[str, object] = json.loads(capsys.readouterr().out)
    return result


def test_a_message_record_with_a_flipped_opcode_is_counted_missing(
    tmp_path: Path, jpegs: list[bytes], capsys: pytest.CaptureFixture[str]
) -> None:
    flat = unchunked_copy(log_with(tmp_path, jpegs, {}), tmp_path / "flat.mcap")
    data = bytearray(flat.read_bytes())
    data[record_offsets(bytes(data), MESSAGE_OPCODE)[2]] = 0x80  # now an unknown record
    flat.write_bytes(bytes(data))
    out = tmp_path / "out.mcap"
    result = annotate_json(flat, "-o", out, capsys=capsys)
    assert result["frames"] == 5 and result["image_messages"] == 6
    assert result["image_messages_promised"] == 6
    assert result["frames_skipped_by_reason"] == {"missing from the data": 1}
    entries = metadata(out)
    assert entries["image_messages_promised"] == "6"
    assert entries["image_messages_promised_by"] == "the Statistics record"
    assert json.loads(entries["frames_skipped_by_reason"]) == {"missing from the data": 1}
    assert run_cli("annotate", flat, "-o", tmp_path / "b.mcap", "--no-verify") == 0
    line = capsys.readouterr().out
    assert "1 skipped frames (1 missing from the data)" in line
    assert "6 image messages promised by the Statistics record" in line
    recovered = annotate_json(flat, "-o", tmp_path / "c.mcap", "--recover", capsys=capsys)
    assert recovered["frames_skipped_by_reason"] == {"missing from the data": 1}
    report = recovered["recovered"]
    assert isinstance(report, dict) and (report["messages"], report["known_messages"]) == (5, 6)


def test_db3_rows_of_an_unknown_topic_id_are_counted(
    tmp_path: Path, jpegs: list[bytes], capsys: pytest.CaptureFixture[str]
) -> None:
    import sqlite3

    folder = bad.write_log(tmp_path / "bag", bad.good_items(jpegs), "db3")
    (inner,) = folder.glob("*.db3")
    with sqlite3.connect(inner) as db:
        camera = db.execute("SELECT id FROM topics WHERE name LIKE '%compressed'").fetchone()[0]
        db.execute(
            f"UPDATE messages SET topic_id = 999 WHERE id IN (SELECT id FROM messages "
            f"WHERE topic_id = {camera} LIMIT 2)"
        )
    db.close()
    bare = tmp_path / "bare.db3"
    bare.write_bytes(inner.read_bytes())
    result = annotate_json(bare, "-o", tmp_path / "out.mcap", capsys=capsys)
    assert result["unattributed_messages"] == 2 and result["frames"] == 4
    assert metadata(tmp_path / "out.mcap")["unattributed_messages"] == "2"
    assert run_cli("annotate", bare, "-o", tmp_path / "b.mcap", "--no-verify") == 0
    assert "2 messages of undeclared topics (never readable)" in capsys.readouterr().out
    # In the bag folder, metadata.yaml promised them to the camera topic: missing from the data.
    result = annotate_json(folder, "-o", tmp_path / "c.mcap", capsys=capsys)
    assert result["image_messages_promised"] == 6
    assert result["frames_skipped_by_reason"] == {"missing from the data": 2}


def test_a_whole_log_promises_what_it_holds(
    tmp_path: Path, jpegs: list[bytes], capsys: pytest.CaptureFixture[str]
) -> None:
    result = annotate_json(log_with(tmp_path, jpegs, {}), "-o", tmp_path / "o.mcap", capsys=capsys)
    assert result["image_messages_promised"] == result["image_messages"] == 6
    assert result["frames_skipped"] == 0 and result["unattributed_messages"] == 0


# --- item 3: --recover past damaged chunks, and chunks cut short ------------------------------

CHUNK_FIELDS = 8 + 8 + 8 + 4  # start time, end time, uncompressed size, CRC


@pytest.fixture
def twelve(shared_data: Path) -> list[bytes]:
    return bad.rtabmap_jpegs(shared_data, 12)


def chunked_log(path: Path, jpegs: list[bytes], compression: str = "zstd") -> Path:
    return bad.write_log(path, bad.good_items(jpegs), mcap_compression=compression)  # type: ignore[arg-type]


def patched(source: Path, target: Path, offset: int, value: bytes) -> Path:
    data = bytearray(source.read_bytes())
    data[offset : offset + len(value)] = value
    target.write_bytes(bytes(data))
    return target


def records_length_offset(path: Path, chunk_start: int) -> int:
    data = path.read_bytes()
    name_at = chunk_start + 9 + CHUNK_FIELDS
    (name_length,) = struct.unpack_from("<I", data, name_at)
    return name_at + 4 + name_length


def recover(log: Path, out: Path, capsys: pytest.CaptureFixture[str]) -> dict[str, object]:
    result = annotate_json(log, "-o", out, "--recover", capsys=capsys)
    recovered = result["recovered"]
    assert isinstance(recovered, dict)
    return {**result, **{f"r_{k}": v for k, v in recovered.items()}}


def test_a_chunk_with_a_huge_records_length_is_dropped_and_the_rest_read(
    tmp_path: Path, twelve: list[bytes], capsys: pytest.CaptureFixture[str]
) -> None:
    good = chunked_log(tmp_path / "good.mcap", twelve)
    start = bad.chunk_spans(good)[1][0]
    huge = struct.pack("<Q", 2**40)
    log = patched(good, tmp_path / "bad.mcap", records_length_offset(good, start), huge)
    result = recover(log, tmp_path / "out.mcap", capsys)
    assert result["frames"] == 9  # chunks 1, 3 and 4; the old salvage stopped at chunk 2: 3
    assert result["frames_skipped_by_reason"] == {"lost in a corrupt chunk": 3}
    assert result["r_corrupt_chunks"] == 1 and result["r_uncountable_chunks"] == 0
    assert result["r_known_from"] == "the Statistics record"
    assert result["r_messages"] == int(str(result["r_known_messages"])) - 3


def test_a_corrupt_chunk_record_length_is_taken_from_the_chunk_index(
    tmp_path: Path, twelve: list[bytes], capsys: pytest.CaptureFixture[str]
) -> None:
    good = chunked_log(tmp_path / "good.mcap", twelve)
    start = bad.chunk_spans(good)[1][0]
    log = patched(good, tmp_path / "bad.mcap", start + 1, struct.pack("<Q", 2**50))
    result = recover(log, tmp_path / "out.mcap", capsys)
    assert result["frames"] == 12 and result["frames_skipped"] == 0
    assert result["r_repaired_lengths"] == 1
    assert result["r_messages"] == result["r_known_messages"]
    assert run_cli("annotate", log, "-o", tmp_path / "b.mcap", "--recover", "--no-verify") == 0
    assert "1 chunk length(s) taken from the chunk index" in capsys.readouterr().out


def test_without_an_index_a_scan_finds_the_next_chunk(
    tmp_path: Path, twelve: list[bytes], capsys: pytest.CaptureFixture[str]
) -> None:
    good = bad.without_summary(chunked_log(tmp_path / "g.mcap", twelve), tmp_path / "u.mcap")
    start = next(  # the second chunk record, found by walking the records
        offset for n, offset in enumerate(record_offsets(good.read_bytes(), 0x06)) if n == 1
    )
    log = patched(good, tmp_path / "bad.mcap", start + 1, struct.pack("<Q", 2**50))
    result = recover(log, tmp_path / "out.mcap", capsys)
    assert result["frames"] == 9 and result["r_skipped_regions"] == 1
    assert result["r_complete"] is True
    # The message indexes at the end of the skipped region count the chunk's messages.
    assert result["frames_skipped_by_reason"] == {"lost in a corrupt chunk": 3}
    assert result["r_known_messages"] == 12 and result["r_uncountable_chunks"] == 0


def cut_in_last_chunk(good: Path, target: Path, fraction: float) -> tuple[Path, int]:
    """The log cut `fraction` into its last chunk; for an uncompressed chunk, how many of its
    message records lie whole before the cut."""
    start, length = bad.chunk_spans(good)[-1]
    cut_at = start + int(length * fraction)
    bad.cut(good, target, cut_at)
    data = good.read_bytes()
    whole, position = 0, records_length_offset(good, start) + 8
    while position + 9 <= start + length:
        opcode, size = RECORD_HEADER.unpack_from(data, position)
        position += 9 + size
        whole += opcode == MESSAGE_OPCODE and position <= cut_at
    return target, whole


@pytest.mark.parametrize("compression", ["none", "lz4", "zstd"])
def test_a_chunk_cut_short_gives_its_whole_messages(
    tmp_path: Path,
    twelve: list[bytes],
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    compression: str,
) -> None:
    monkeypatch.setattr(bad, "FRAMES_PER_CHUNK", 6)
    # Frames of ~100 kB: a chunk spans several lz4 (64 kB) and zstd (128 kB) blocks.
    large = [bad.resized_jpeg(data, 1280, 960) for data in twelve]
    good = chunked_log(tmp_path / "good.mcap", large, compression)
    log, whole = cut_in_last_chunk(good, tmp_path / "cut.mcap", 0.8)
    result = recover(log, tmp_path / "out.mcap", capsys)
    partial = int(str(result["r_partial_chunk_messages"]))
    assert result["frames"] == 6 + partial and result["r_complete"] is False
    assert "truncated" in str(result["r_stop_reason"])
    if compression == "none":
        assert partial == whole >= 4  # every whole message before the cut
    else:  # up to the last whole block the decompressor could finish
        assert 2 <= partial < 6


def test_a_cut_inside_the_first_chunk_is_called_truncated(
    tmp_path: Path, twelve: list[bytes], capsys: pytest.CaptureFixture[str]
) -> None:
    good = chunked_log(tmp_path / "good.mcap", twelve[:3])
    start, _ = bad.chunk_spans(good)[0]
    log = bad.cut(good, tmp_path / "cut.mcap", start + 200)
    code = run_cli("annotate", log, "-o", tmp_path / "out.mcap", "--recover", "--no-verify")
    err = capsys.readouterr().err
    assert code == ExitCode.UNREADABLE_INPUT and "truncated" in err and "corrupt" not in err
    assert err.count("\n") == 1 and err.startswith("doseqslam-logs: error: ")


def test_recovered_of_known_is_on_the_summary_line(
    tmp_path: Path, twelve: list[bytes], capsys: pytest.CaptureFixture[str]
) -> None:
    good = chunked_log(tmp_path / "good.mcap", twelve)
    start = bad.chunk_spans(good)[2][0]
    log = patched(good, tmp_path / "bad.mcap", records_length_offset(good, start), b"\xff" * 8)
    assert run_cli("annotate", log, "-o", tmp_path / "out.mcap", "--recover", "--no-verify") == 0
    line = capsys.readouterr().out
    assert re.search(r"recovered (\d+) of (\d+) known messages \(known from the Stat", line)
