"""Annotate one log: source -> frames -> detector -> decisions -> annotated MCAP.

`annotate_log` is the library entry point; the `annotate` and `batch` commands call it.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from . import __version__
from .detector import Parameters, make_detector
from .frames import Frame
from .log_frames import FrameCounts, OnError, TimeSource, decoded_frames
from .replay import ReplayResult, replay
from .sinks.mcap_writer import Annotations, WriteSummary, write_annotated_mcap
from .sinks.messages import FrameTimes
from .sources import open_source, pick_image_topic

HASH_BLOCK = 1 << 20


@dataclass(frozen=True)
class AnnotateOptions:
    """Everything about a run except the detector parameters."""

    topic: str | None = None
    time_source: TimeSource = "header"
    start_ns: int | None = None
    end_ns: int | None = None
    on_error: OnError = "skip"
    sidecar: bool = False


@dataclass(frozen=True)
class AnnotateResult:
    input_path: Path
    output_path: Path
    topic: str
    replay: ReplayResult
    counts: FrameCounts
    written: WriteSummary
    source_sha256: str


def source_sha256(path: Path) -> str:
    """sha256 of a log file; of a rosbag2 folder, of its files' names and bytes in name order."""
    digest = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for file in files:
        if path.is_dir():
            digest.update(file.relative_to(path).as_posix().encode() + b"\0")
        with file.open("rb") as stream:
            while block := stream.read(HASH_BLOCK):
                digest.update(block)
    return digest.hexdigest()


class _TimesRecorder:
    """Passes frames through and keeps each one's log time and header stamp by index."""

    def __init__(self) -> None:
        self.pairs: list[tuple[int, int | None]] = []

    def __call__(self, frames: Iterable[Frame]) -> Iterator[Frame]:
        for frame in frames:
            self.pairs.append((frame.log_time_ns, frame.header_stamp_ns))
            yield frame

    def frame_times(self) -> FrameTimes:
        return FrameTimes.from_pairs(self.pairs)


def run_metadata(
    params: Parameters,
    result: ReplayResult,
    counts: FrameCounts,
    log: Path,
    sha256: str,
    topic: str,
    options: AnnotateOptions,
) -> dict[str, str]:
    """The `doseqslam` metadata record: strings only, nothing that varies between runs."""
    return {
        "tool": "doseqslam-logs",
        "tool_version": __version__,
        "method": params.method,
        "parameters": params.canonical_json(),
        "parameters_hash": params.hash,
        "feature_detector": result.feature_detector,
        "source_file": log.name,
        "source_sha256": sha256,
        "image_topic": topic,
        "time_source": options.time_source,
        "start_ns": "" if options.start_ns is None else str(options.start_ns),
        "end_ns": "" if options.end_ns is None else str(options.end_ns),
        "frames_used": str(counts.used),
        "frames_skipped": str(counts.skipped_total),
        "frames_skipped_by_reason": json.dumps(dict(sorted(counts.skipped.items()))),
        "log_time_fallbacks": str(counts.log_time_fallbacks),
        "sequences": str(len(result.decisions)),
        "loop_closures": str(result.loop_closures),
    }


def annotate_log(
    log: str | Path,
    output: str | Path,
    params: Parameters,
    options: AnnotateOptions | None = None,
    progress: Callable[[int], None] | None = None,
) -> AnnotateResult:
    """Replay the detector over the log's camera topic and write the annotated MCAP.

    Raises SourceError / NoCameraError (input), ImageDecodeError (on_error="fail"),
    OutputError (output), ParameterError.
    """
    log, output = Path(log), Path(output)
    options = options or AnnotateOptions()
    counts = FrameCounts()
    recorder = _TimesRecorder()
    with open_source(log) as source:
        topic = pick_image_topic(source, options.topic)
        messages = source.image_messages(topic, options.start_ns, options.end_ns)
        frames = decoded_frames(messages, counts, options.time_source, options.on_error)
        result = replay(recorder(frames), make_detector(params), progress)
    sha256 = source_sha256(log)
    metadata = run_metadata(params, result, counts, log, sha256, topic, options)
    annotations = Annotations.from_decisions(
        result.decisions, recorder.frame_times(), params.method, params.hash, metadata
    )
    written = write_annotated_mcap(log, output, annotations, sidecar=options.sidecar)
    return AnnotateResult(log, output, topic, result, counts, written, sha256)


def expected_frames(log: str | Path, topic: str | None) -> int | None:
    """The image message count of the topic (for a progress bar), or None if unknown."""
    with open_source(log) as source:
        name = pick_image_topic(source, topic)
        counts = [c.message_count for c in source.channels() if c.topic == name]
    return counts[0] if counts else None
