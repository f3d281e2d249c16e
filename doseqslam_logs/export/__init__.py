"""Exports of an annotated log for other tools: loop closures as csv or jsonl, the odometry at
camera times as a TUM trajectory, and a g2o pose graph with loop edges.

A new format is one module with an `EXPORTER` (see `base.Exporter`) plus one entry in
`FORMATS`; the command line lists whatever is registered here.
"""

from __future__ import annotations

from . import csv_format, g2o_format, jsonl_format, tum_format
from .base import Exporter, ExportOptions, ExportResult

__all__ = ["FORMATS", "ExportOptions", "ExportResult", "Exporter"]

FORMATS: dict[str, Exporter] = {
    exporter.name: exporter
    for exporter in (
        csv_format.EXPORTER,
        jsonl_format.EXPORTER,
        tum_format.EXPORTER,
        g2o_format.EXPORTER,
    )
}
