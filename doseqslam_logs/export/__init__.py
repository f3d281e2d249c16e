"""Exports of an annotated log for other tools: loop closures as csv or jsonl, the odometry at
camera times as a TUM trajectory, and a g2o pose graph with loop edges.

A new format is one module with an `EXPORTER` (see `base.Exporter`) plus one entry in
`FORMATS`; the command line lists whatever is registered here.
"""

from __future__ import annotations

from pathlib import Path

from ..annotations.reader import read_annotations
from ..errors import OutputError, UsageError
from ..sinks.atomic import atomic_output, check_output_path
from . import csv_format, g2o_format, jsonl_format, tum_format
from .base import Exporter, ExportOptions, ExportResult

__all__ = ["FORMATS", "ExportOptions", "ExportResult", "Exporter", "export_log"]

FORMATS: dict[str, Exporter] = {
    exporter.name: exporter
    for exporter in (
        csv_format.EXPORTER,
        jsonl_format.EXPORTER,
        tum_format.EXPORTER,
        g2o_format.EXPORTER,
    )
}


def export_log(
    log: str | Path,
    format: str,
    options: ExportOptions | None = None,
    output: str | Path | None = None,
) -> ExportResult:
    """Export an annotated log (or sidecar) in `format`, a name of FORMATS, as the `export`
    command does. With `output`, the text is written there atomically and the result holds
    only the summary; without, the caller writes `result.chunks` (they are built lazily).

    Raises UsageError (unknown format, unusable input for the format), SourceError (not an
    annotated log), OutputError (output that would replace the input or cannot be written).
    """
    if format not in FORMATS:
        raise UsageError(f"unknown export format {format!r} (formats: {', '.join(FORMATS)})")
    log, options = Path(log), options or ExportOptions()
    if output is not None:
        check_output_path(output)
        for source in (log, options.poses_log):  # a sidecar's log is an input too
            if source is not None and Path(output).resolve() == Path(source).resolve():
                raise OutputError(f"{output}: the output would replace the input {source}")
    result = FORMATS[format].export(read_annotations(log), options)
    if output is None:
        return result
    with atomic_output(Path(output)) as stream:
        for chunk in result.chunks:
            stream.write(chunk.encode())
    return ExportResult((), result.summary)
