"""Issue #21, the last gaps: a cap on what one MCAP chunk decompresses to, and a message record
inside a chunk that is shorter than its header, counted. Issue #40 item 4: `--recover` reads a
chunk whose uncompressed size field is wrong (over the cap, too large, too small) as a
streaming decoder does, within the cap.

The bombs are real: a chunk of a few kB of zstd (or lz4) that claims, and decompresses to,
4 MiB, against a cap the tests lower to 1 MiB; nothing here allocates more than that.
"""

from __future__ import annotations

import io
import json
import struct
import tracemalloc
import zlib
from pathlib import Path

import make_bad_inputs as bad
import pytest
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, IndexType, Writer

from doseqslam_logs.cli.main import main
from doseqslam_logs.errors import ExitCode
from doseqslam_logs.sources import chunk_limits
from doseqslam_logs.sources.mcap_source import McapSource
from doseqslam_logs.sources.salvage import SalvageReport, salvage_mcap

TEST_CAP = 1 << 20
BOMB_BYTES = 4 << 20  # what the bomb chunk really decompresses to: 4 x the test cap
TOPIC = "/camera/image/compressed"


@pytest.fixture(autouse=True)
def small_cap(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(chunk_limits, "MAX_CHUNK_BYTES", TEST_CAP)


@pytest.fixture(scope="module")
def good_log(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("good") / "good.mcap"
    return bad.write_log(path, bad.good_items(bad.rtabmap_jpegs(shared_data)))


def rewrite(
    good: Path,
    *,
    bomb_after: int | None = None,
    alone: bool = True,
    compression: CompressionType = CompressionType.ZSTD,
    chunk_size: int = 64 * 1024,
    index_types: IndexType = IndexType.ALL,
) -> bytes:
    """The good log copied by mcap's Writer; with `bomb_after`, a message of BOMB_BYTES zeros
    on the topic /padding follows that camera message, alone in its chunk (a few hundred bytes of
    zstd) or, not `alone`, in the chunk of the camera messages around it."""
    out = io.BytesIO()
    writer = Writer(out, chunk_size=chunk_size, compression=compression, index_types=index_types)
    writer.start("ros2", "test")
    for number, message in bad.copied_messages(good, writer):
        if number == bomb_after:
            if alone:
                writer.flush()
            padding = writer.register_channel("/padding", "raw", 0)
            writer.add_message(padding, message.log_time, bytes(BOMB_BYTES), message.log_time)
            if alone:
                writer.flush()
    writer.finish()
    return out.getvalue()


def unindexed(tmp_path: Path, data: bytes) -> Path:
    """The log without its summary section (chunk indexes, Statistics), as `bad` writes it."""
    indexed = tmp_path / "indexed.mcap"
    indexed.write_bytes(data)
    return bad.without_summary(indexed, tmp_path / "unindexed.mcap")


def chunks(data: bytes) -> list[tuple[int, Chunk]]:
    """(record offset, chunk) of every chunk record, walked record by record."""
    found, position = [], 8
    while position + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, position)
        if opcode == 0x06:
            found.append(
                (position, Chunk.read(_stream(data[position + 9 : position + 9 + length])))
            )
        if opcode == 0x02:
            break
        position += 9 + length
    return found


def _stream(body: bytes) -> ReadDataStream:
    return ReadDataStream(io.BytesIO(body))


def run(capsys: pytest.CaptureFixture[str], *args: str | Path) -> tuple[int, str, str]:
    try:
        status = main([str(a) for a in args])
    except SystemExit as exc:
        status = int(exc.code or 0)
    out, err = capsys.readouterr()
    return status, out, err


def one_error(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("doseqslam-logs: error: "), err
    assert "Traceback" not in err
    return lines[0]


@pytest.fixture
def decompressions(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The output limit of every chunk decompression."""
    limits: list[int] = []
    real = chunk_limits.decompress_at_most

    def spy(compression: str, data: bytes, limit: int) -> bytes:
        limits.append(limit)
        return real(compression, data, limit)

    monkeypatch.setattr(chunk_limits, "decompress_at_most", spy)
    return limits


CLAIM = (
    f"a chunk claims {BOMB_BYTES + 67} bytes uncompressed, more than the cap of {TEST_CAP} bytes"
)


def bomb_log(good_log: Path, tmp_path: Path, kind: str) -> Path:
    """The bomb (zstd or lz4) in an indexed log or, "unindexed", in one without summary."""
    compression = CompressionType.LZ4 if kind == "lz4" else CompressionType.ZSTD
    data = rewrite(good_log, bomb_after=4, compression=compression)
    if kind == "unindexed":
        return unindexed(tmp_path, data)
    path = tmp_path / "bomb.mcap"
    path.write_bytes(data)
    return path


@pytest.mark.parametrize("kind", ["zstd", "lz4", "unindexed"])
def test_a_chunk_over_the_cap_is_refused_before_it_is_decompressed(
    kind: str,
    good_log: Path,
    tmp_path: Path,
    decompressions: list[int],
    capsys: pytest.CaptureFixture[str],
) -> None:
    log = bomb_log(good_log, tmp_path, kind)
    bomb = next(
        chunk for _, chunk in chunks(log.read_bytes()) if chunk.uncompressed_size > TEST_CAP
    )
    assert len(bomb.data) < 20_000  # a few hundred bytes (zstd) or kB (lz4) claim 4 MiB
    before = log.read_bytes()
    out = tmp_path / "out.mcap"
    for args in (("info", log), ("annotate", log, "-o", out, "--no-verify")):
        status, _, err = run(capsys, *args)
        assert status == ExitCode.UNREADABLE_INPUT
        assert CLAIM in one_error(err)
    assert not out.exists() and log.read_bytes() == before
    assert all(limit <= TEST_CAP + 1 for limit in decompressions), decompressions


@pytest.mark.parametrize("kind", ["zstd", "unindexed"])
@pytest.mark.parametrize("alone", [True, False], ids=["own chunk", "camera chunk"])
def test_recover_drops_a_chunk_over_the_cap_and_counts_it(
    kind: str,
    alone: bool,
    good_log: Path,
    tmp_path: Path,
    decompressions: list[int],
    capsys: pytest.CaptureFixture[str],
) -> None:
    data = rewrite(good_log, bomb_after=7, alone=alone)  # after chunk 1 (the channel records)
    log = unindexed(tmp_path, data) if kind == "unindexed" else tmp_path / "bomb.mcap"
    if kind != "unindexed":
        log.write_bytes(data)
    out = tmp_path / "out.mcap"
    status, stdout, _ = run(
        capsys, "annotate", log, "-o", out, "--no-verify", "--recover", "--json"
    )
    assert status == ExitCode.OK
    summary = json.loads(stdout)
    recovered = summary["recovered"]
    assert recovered["oversized_chunks"] == recovered["corrupt_chunks"] == 1
    lost_by_topic = recovered["lost_by_topic"]
    lost = lost_by_topic.pop(TOPIC, 0)
    # The padding message, by its index ("?" without a summary: its channel was in the chunk).
    assert sum(lost_by_topic.values()) == 1
    assert (lost > 0) == (not alone)  # the camera messages of the bomb's chunk, by its index
    assert summary["frames_used"] == 12 - lost
    assert summary["frames_skipped_by_reason"].get("lost in a corrupt chunk", 0) == lost
    assert all(limit <= TEST_CAP + 1 for limit in decompressions), decompressions


def test_a_chunk_that_holds_more_than_it_claims_is_not_decompressed_past_its_claim(
    good_log: Path, tmp_path: Path, decompressions: list[int], capsys: pytest.CaptureFixture[str]
) -> None:
    """The bomb chunk says 1000 bytes uncompressed; its zstd frame says (and holds) 4 MiB, which
    the mcap library's zstd call would allocate whole."""
    data = bytearray(rewrite(good_log, bomb_after=4))
    offset, _ = next((at, c) for at, c in chunks(bytes(data)) if c.uncompressed_size > TEST_CAP)
    struct.pack_into("<Q", data, offset + 9 + 16, 1000)  # after start and end times
    log = unindexed(tmp_path, bytes(data))
    status, _, err = run(capsys, "annotate", log, "-o", tmp_path / "out.mcap", "--no-verify")
    assert status == ExitCode.UNREADABLE_INPUT
    assert "a chunk decompresses to more than the 1000 bytes it claims" in one_error(err)
    assert max(decompressions) <= TEST_CAP + 1


@pytest.mark.parametrize("compression", ["zstd", "lz4", ""])
def test_decompression_stops_at_its_limit(compression: str) -> None:
    import lz4.frame
    import zstandard

    packed = {
        "zstd": zstandard.ZstdCompressor().compress(bytes(BOMB_BYTES)),
        "lz4": lz4.frame.compress(bytes(BOMB_BYTES)),
        "": bytes(BOMB_BYTES),
    }[compression]
    assert chunk_limits.decompress_at_most(compression, packed, 1001) == bytes(1001)


def test_the_default_cap_is_far_above_real_chunks(shared_data: Path) -> None:
    """Every MCAP among the real data has chunks of a few MiB at most."""
    assert chunk_limits.MAX_CHUNK_BYTES == TEST_CAP  # the fixture
    largest = 0
    for path in sorted(shared_data.rglob("*.mcap")):
        with McapSource(path) as source:
            if source.summary is not None:
                largest = max(
                    [largest, *(c.uncompressed_size for c in source.summary.chunk_indexes)]
                )
    assert 0 < largest < 64 << 20


# --- a message record inside a chunk shorter than its header -------------------------------


def message_shorter_than_its_header(good: Path, tmp_path: Path) -> Path:
    """Uncompressed chunks without summary; in chunk 2 the first message record says it is 10
    bytes long, less than a message's 22-byte header, and the chunk's CRC is made to fit."""
    data = bytearray(rewrite(good, compression=CompressionType.NONE))
    offset, chunk = chunks(bytes(data))[1]
    records = offset + 9 + 8 + 8 + 8 + 4 + 4 + 8  # times, size, CRC, "" compression, length
    position = records
    while data[position] != 0x05:  # the chunk's schema or channel records come first
        position += 9 + struct.unpack_from("<Q", data, position + 1)[0]
    struct.pack_into("<Q", data, position + 1, 10)
    body = bytes(data[records : records + len(chunk.data)])
    struct.pack_into("<I", data, offset + 9 + 24, zlib.crc32(body))
    return unindexed(tmp_path, bytes(data))


@pytest.mark.parametrize("recover", [False, True], ids=["plain", "--recover"])
def test_messages_a_short_message_record_swallows_are_counted(
    recover: bool, good_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The damaged record is read with the rest of its chunk as its data (the mcap library's
    reading of a length under its header): the messages after it are not in the data, and the
    message index records that follow the chunk say how many there were."""
    log = message_shorter_than_its_header(good_log, tmp_path)
    out = tmp_path / "out.mcap"
    args = ["annotate", log, "-o", out, "--no-verify", "--json"] + ["--recover"] * recover
    status, stdout, err = run(capsys, *args)
    assert status == ExitCode.OK, err
    summary = json.loads(stdout)
    assert summary["image_messages_promised"] == 12
    assert summary["image_messages_promised_by"] == "the message index"
    missing = summary["frames_skipped_by_reason"]["missing from the data"]
    assert missing > 0 and summary["frames_used"] + missing == 12
    assert "the message index of unindexed.mcap promises 12 messages" in err
    with out.open("rb") as file:
        meta = next(m for m in make_reader(file).iter_metadata() if m.name == "doseqslam")
    assert json.loads(meta.metadata["frames_skipped_by_reason"])["missing from the data"] == missing
    assert meta.metadata["image_messages_promised_by"] == "the message index"


def without_first_chunk_indexes(data: bytes) -> bytes:
    """The message index records that follow the first chunk removed (no summary points at
    them)."""
    out, position, chunks_seen = bytearray(data[:8]), 8, 0
    while position < len(data) - 8:
        opcode, length = struct.unpack_from("<BQ", data, position)
        end = position + 9 + length
        chunks_seen += opcode == 0x06
        if not (opcode == 0x07 and chunks_seen == 1):
            out += data[position:end]
        position = end
    return bytes(out + data[position:])


@pytest.mark.parametrize("which", ["no chunk", "all but the first"])
def test_an_unindexed_log_without_a_message_index_for_every_chunk_promises_nothing(
    which: str, good_log: Path, tmp_path: Path
) -> None:
    if which == "no chunk":
        log = unindexed(tmp_path, rewrite(good_log, index_types=IndexType.NONE))
    else:
        whole = unindexed(tmp_path, rewrite(good_log))
        log = tmp_path / "partly.mcap"
        log.write_bytes(without_first_chunk_indexes(whole.read_bytes()))
        assert len(log.read_bytes()) < len(whole.read_bytes())
    with McapSource(log) as source:
        assert source.promised_messages(TOPIC) is None
        assert next(c for c in source.channels() if c.topic == TOPIC).message_count == 12


def test_an_unindexed_whole_log_keeps_its_promise(good_log: Path, tmp_path: Path) -> None:
    log = unindexed(tmp_path, good_log.read_bytes())
    with McapSource(log) as source:
        promise = source.promised_messages(TOPIC)
    assert promise is not None and (promise.count, promise.origin) == (12, "the message index")


def test_the_recovery_line_names_the_chunks_over_the_cap() -> None:
    report = SalvageReport(file_size=100, bytes_used=100, complete=True, messages=10)
    report.corrupt_chunks = report.oversized_chunks = 1
    report.lost_by_topic[TOPIC] = 2
    report.known_messages, report.known_from = 12, "the Statistics record"
    assert report.describe() == (
        "1 corrupt chunk(s) dropped (2 messages), 1 of these chunk(s) over the cap of "
        f"{TEST_CAP} bytes uncompressed; recovered 10 of 12 known messages "
        "(known from the Statistics record)"
    )
    assert report.as_metadata()["oversized_chunks"] == 1


def test_a_zstd_frame_cut_short_gives_what_decompresses_before_the_cut() -> None:
    """The one-call path (a frame that states its size) cannot do it: the stream takes over."""
    import random

    import zstandard

    raw = random.Random(0).randbytes(1 << 20)  # incompressible: 8 blocks of 128 KiB
    packed = zstandard.ZstdCompressor(level=1).compress(raw)
    assert zstandard.frame_content_size(packed) == len(raw)
    prefix = chunk_limits.decompress_at_most("zstd", packed[: len(packed) // 2], len(raw) + 1)
    assert 0 < len(prefix) < len(raw) and raw.startswith(prefix)
    assert chunk_limits.decompress_at_most("zstd", packed, len(raw) + 1) == raw


# --- --recover reads a chunk whose size field is wrong, as a streaming decoder does ----------

COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "": CompressionType.NONE}
SIZE_FIELD = 9 + 16  # a chunk record's uncompressed_size: after its header and two times
CRC_FIELD = SIZE_FIELD + 8
CLAIMS = ["over the cap", "too large", "too small"]


def with_size_field(data: bytes, number: int, claim: str | int) -> tuple[bytes, Chunk]:
    """The log with chunk `number`'s uncompressed_size field made wrong: "over the cap", "too
    large" (twice its records, under the cap), "too small" (half) or a number; the chunk as
    it was written."""
    offset, chunk = chunks(data)[number]
    real = chunk.uncompressed_size
    wrong = {"over the cap": TEST_CAP + 1, "too large": 2 * real, "too small": real // 2}
    lying = bytearray(data)
    struct.pack_into("<Q", lying, offset + SIZE_FIELD, wrong.get(str(claim), claim))
    return bytes(lying), chunk


def messages_in(chunk: Chunk) -> int:
    return sum(isinstance(r, Message) for r in breakup_chunk(chunk, validate_crc=True))


def recovered(capsys: pytest.CaptureFixture[str], log: Path, out: Path) -> dict[str, object]:
    status, stdout, err = run(
        capsys, "annotate", log, "-o", out, "--no-verify", "--recover", "--json"
    )
    assert status == ExitCode.OK, err
    summary: dict[str, object] = json.loads(stdout)
    return summary


@pytest.mark.parametrize("claim", CLAIMS)
@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_recover_keeps_every_frame_of_a_chunk_whose_size_field_is_wrong(
    compression: str,
    claim: str,
    good_log: Path,
    tmp_path: Path,
    decompressions: list[int],
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Its records decompress to what its CRC says: all are kept, the wrong field reported. A
    plain run refuses the chunk (its readers could not report the lie), except one that claims
    more than it holds, which the mcap library reads too."""
    data, chunk = with_size_field(
        rewrite(good_log, compression=COMPRESSIONS[compression]), 1, claim
    )
    assert chunk.compression == compression and chunk.uncompressed_crc != 0
    assert 0 < messages_in(chunk) < 12
    log, out = tmp_path / "lying.mcap", tmp_path / "out.mcap"
    log.write_bytes(data)
    status, line, err = run(capsys, "annotate", log, "-o", out, "--no-verify", "--recover")
    assert status == ExitCode.OK, err
    assert "recovered: 1 chunk(s) with a wrong size field read whole; recovered 12 of 12" in line
    summary = recovered(capsys, log, out)
    assert summary["frames_used"] == 12 and summary["frames_skipped"] == 0
    report = summary["recovered"]
    assert isinstance(report, dict) and report["wrong_size_chunks"] == 1
    assert report["corrupt_chunks"] == report["oversized_chunks"] == 0
    assert all(limit <= TEST_CAP + 1 for limit in decompressions), decompressions
    assert log.read_bytes() == data
    status, _, err = run(capsys, "annotate", log, "-o", tmp_path / "plain.mcap", "--no-verify")
    if claim == "too large":
        assert status == ExitCode.OK
    else:
        assert status == ExitCode.UNREADABLE_INPUT
        assert "annotate --recover uses every complete message" in one_error(err)


@pytest.mark.parametrize("claim", ["over the cap", "too small"])
@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_recover_drops_a_chunk_with_a_wrong_size_field_that_fails_its_crc(
    compression: str,
    claim: str,
    good_log: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Its messages are counted from the chunk itself, as for any chunk failing its CRC check
    (the log has no message index to count them)."""
    whole = rewrite(good_log, compression=COMPRESSIONS[compression], index_types=IndexType.NONE)
    data, chunk = with_size_field(whole, 1, claim)
    damaged = bytearray(data)
    offset, _ = chunks(data)[1]
    damaged[offset + CRC_FIELD] ^= 0xFF
    log = unindexed(tmp_path, bytes(damaged))
    lost = messages_in(chunk)
    summary = recovered(capsys, log, tmp_path / "out.mcap")
    assert summary["frames_used"] == 12 - lost
    assert summary["frames_skipped_by_reason"] == {"lost in a corrupt chunk": lost}
    report = summary["recovered"]
    assert isinstance(report, dict) and report["corrupt_chunks"] == 1
    assert report["lost_by_topic"] == {TOPIC: lost} and report["uncountable_chunks"] == 0
    assert report["oversized_chunks"] == report["wrong_size_chunks"] == 0


def salvaged(log: Path, tmp_path: Path) -> tuple[SalvageReport, int]:
    """salvage_mcap's report on `log`, and the peak of Python's allocations while it ran."""
    with (tmp_path / "copy.mcap").open("wb") as target:
        tracemalloc.start()
        try:
            report = salvage_mcap(log, target)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
    return report, peak


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_recover_drops_a_chunk_that_holds_more_than_the_cap_whatever_it_claims(
    compression: str,
    good_log: Path,
    tmp_path: Path,
    decompressions: list[int],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The bomb's chunk says 1000 bytes and holds 4 x the cap: measured a block at a time, it
    costs a few blocks more than the log without it; its padding message is counted by its
    index."""
    block = 64 * 1024
    monkeypatch.setattr(chunk_limits, "_BLOCK_BYTES", block)
    without = tmp_path / "without.mcap"
    without.write_bytes(rewrite(good_log, compression=COMPRESSIONS[compression]))
    whole = rewrite(good_log, bomb_after=4, compression=COMPRESSIONS[compression])
    number = next(n for n, (_, c) in enumerate(chunks(whole)) if c.uncompressed_size > TEST_CAP)
    data, _ = with_size_field(whole, number, 1000)
    log = tmp_path / "bomb.mcap"
    log.write_bytes(data)
    report, peak = salvaged(log, tmp_path)
    assert peak < salvaged(without, tmp_path)[1] + 4 * block
    assert report.oversized_chunks == report.corrupt_chunks == 1
    assert report.wrong_size_chunks == 0 and report.messages == 12
    assert report.lost_by_topic == {"/padding": 1}
    assert all(limit <= TEST_CAP + 1 for limit in decompressions), decompressions


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_streaming_reads_past_any_claim_up_to_the_cap(compression: str) -> None:
    import lz4.frame
    import zstandard

    raw = bytes(range(256)) * 4096  # 1 MiB: the test cap exactly
    pack = {"zstd": zstandard.ZstdCompressor().compress, "lz4": lz4.frame.compress}[compression]
    crc = zlib.crc32(raw)
    chunk = Chunk(compression, pack(raw), 0, 0, crc, uncompressed_size=1)
    assert chunk_limits.stream_chunk_records(chunk, validate_crc=True) == raw
    over = Chunk(compression, pack(raw + b"x"), 0, 0, 0, uncompressed_size=1)
    with pytest.raises(chunk_limits.ChunkTooLargeError, match="holds more than the cap"):
        chunk_limits.stream_chunk_records(over)
