"""csv: one row per loop closure, the columns of `loops.COLUMNS` (empty cell = no value)."""

from __future__ import annotations

import csv
import io
from collections.abc import Iterator

from ..annotations.reader import AnnotatedLog
from .base import Exporter, ExportOptions, ExportResult
from .loops import COLUMNS, loop_closure_row, loops_summary, selected_loop_closures


def _lines(log: AnnotatedLog, options: ExportOptions) -> Iterator[str]:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    for loop_closure in selected_loop_closures(log, options.include_rejected):
        writer.writerow(loop_closure_row(log, loop_closure))  # None becomes an empty cell
        yield buffer.getvalue()
        buffer.seek(0)
        buffer.truncate()
    yield buffer.getvalue()


def export(log: AnnotatedLog, options: ExportOptions) -> ExportResult:
    count = len(selected_loop_closures(log, options.include_rejected))
    return ExportResult(_lines(log, options), loops_summary(log, count, options.include_rejected))


EXPORTER = Exporter("csv", "loop closures, one row each, with a header", False, export)
