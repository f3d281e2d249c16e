"""jsonl: one JSON object per loop closure and line, the keys of `loops.COLUMNS` (null = none)."""

from __future__ import annotations

import json
from collections.abc import Iterator

from ..annotations.reader import AnnotatedLog
from .base import Exporter, ExportOptions, ExportResult
from .loops import loop_closure_row, loops_summary, selected_loop_closures


def _lines(log: AnnotatedLog, options: ExportOptions) -> Iterator[str]:
    for loop_closure in selected_loop_closures(log, options.include_rejected):
        yield json.dumps(loop_closure_row(log, loop_closure), allow_nan=False) + "\n"


def export(log: AnnotatedLog, options: ExportOptions) -> ExportResult:
    count = len(selected_loop_closures(log, options.include_rejected))
    return ExportResult(_lines(log, options), loops_summary(log, count, options.include_rejected))


EXPORTER = Exporter("jsonl", "loop closures, one JSON object per line", False, export)
