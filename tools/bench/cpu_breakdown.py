#!/usr/bin/env python3
"""Where one `annotate` run's CPU goes: the thread CPU time of each costly function, summed
over the threads that ran it, beside the run's total and its decode-only cost.

Each function named in PROBES is wrapped, for this process only, by a counter of the calling
thread's CPU time (`time.thread_time`): a call's own thread, not the OpenCV or faiss threads it
may wake, and the time of the probes nested in it included (extract inside the metric
features, the essential fit inside verify_pair). The run is annotate's defaults
(`annotate_log`), its output written to --out. What is left over (total minus the top-level
probes) is reading and deserializing the log, the spills, thread hand-offs and Python glue.

    PYTHONPATH=tools python -m bench.cpu_breakdown LOG.mcap [--out /tmp/o.mcap] [--json F]

One run per call: the machine's speed moves between runs (bench.cpu_gauge), so compare
shares, not seconds, across days.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import json
import resource
import sys
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# (module, attribute or Class.attribute, label, top level: not nested in another probe)
PROBES = (
    ("doseqslam_logs.sources.images", "_decode_compressed", "decode JPEG/PNG", True),
    ("doseqslam_logs.verification.geometry", "extract_features", "features (ORB; SIFT)", False),
    ("doseqslam_logs.pipeline.feature_spill", "FeatureSpill.compute", "replay: features", True),
    ("doseqslam_logs.detector.doseqslam", "DOSeqSLAM.prepare", "replay: frame vector", True),
    ("doseqslam_logs.detector.doseqslam", "DOSeqSLAM.push_prepared", "replay: detector", True),
    ("doseqslam_logs.detector.place_index", "PlaceIndex.add", "  place index add", False),
    ("doseqslam_logs.detector.place_index", "PlaceIndex.query", "  place index query", False),
    ("doseqslam_logs.verification.geometry", "verify_pair", "verify: frame pairs", True),
    ("doseqslam_logs.verification.geometry", "_essential_verdict", "  robust fit + pose", False),
    ("doseqslam_logs.pipeline.metric_edges", "_Fitter.fit", "metric: fits", True),
    ("doseqslam_logs.pipeline.metric_edges", "_Features.__call__", "  frames and SIFT", False),
    ("doseqslam_logs.sinks.mcap_writer", "write_annotated_mcap", "write", True),
)
# Modules that imported a probed function by name: their name is rebound to the probe.
REBIND = (
    ("doseqslam_logs.pipeline.feature_spill", "extract_features"),
    ("doseqslam_logs.pipeline.metric_edges", "extract_features"),
    ("doseqslam_logs.verification.stage", "verify_pair"),
    ("doseqslam_logs.pipeline.annotate", "write_annotated_mcap"),
)


@dataclass
class Tally:
    """CPU seconds and calls per label."""

    seconds: defaultdict[str, float]
    calls: Counter[str]

    def probe(self, function: Callable[..., Any], label: str) -> Callable[..., Any]:
        @functools.wraps(function)
        def probed(*args: Any, **kwargs: Any) -> Any:
            start = time.thread_time()
            try:
                return function(*args, **kwargs)
            finally:
                self.seconds[label] += time.thread_time() - start
                self.calls[label] += 1

        return probed


def install(tally: Tally) -> dict[str, Callable[..., Any]]:
    """Wrap every probe; returns the probed functions by their module's dotted name."""
    probed: dict[str, Callable[..., Any]] = {}
    for module_name, attribute, label, _ in PROBES:
        owner: Any = importlib.import_module(module_name)
        name = attribute
        if "." in attribute:
            class_name, name = attribute.split(".")
            owner = getattr(owner, class_name)
        wrapped = tally.probe(getattr(owner, name), label)
        setattr(owner, name, wrapped)
        probed[name] = wrapped
    for module_name, name in REBIND:
        setattr(importlib.import_module(module_name), name, probed[name])
    return probed


def decode_only(log: Path) -> float:
    """CPU seconds of reading and decoding the camera topic alone (the ratio's denominator):
    bench.annotate's decode measurement, in this process."""
    from bench.annotate import measure_decode

    start = time.process_time()
    measure_decode(log, None)
    return time.process_time() - start


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("log", type=Path)
    parser.add_argument("--out", type=Path, default=Path("/tmp/cpu_breakdown.mcap"))
    parser.add_argument("--json", type=Path, help="write the figures here too")
    args = parser.parse_args(argv)
    decode_s = decode_only(args.log)
    tally = Tally(defaultdict(float), Counter())
    install(tally)
    from doseqslam_logs.pipeline.annotate import annotate_log

    wall, cpu = time.perf_counter(), time.process_time()
    annotate_log(args.log, args.out)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    top = sum(tally.seconds[label] for _, _, label, top in PROBES if top)
    rows = [(label, tally.seconds[label], tally.calls[label]) for _, _, label, _ in PROBES]
    rows.append(("other (reading, spills, glue)", cpu - top, 0))
    print(f"{args.log.name}: annotate {cpu:.1f} CPU s, {wall:.1f} s wall")
    print(f"decode alone {decode_s:.2f} CPU s: annotate / decode = {cpu / decode_s:.1f}x")
    print("| what | CPU s | share | calls | ms a call |\n|---|---:|---:|---:|---:|")
    for label, seconds, calls in rows:
        each = f"{seconds / calls * 1e3:.2f}" if calls else ""
        print(f"| {label} | {seconds:.2f} | {seconds / cpu:.0%} | {calls} | {each} |")
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak RSS {peak_mb:.0f} MB")
    if args.json:
        figures = {"cpu_s": cpu, "wall_s": wall, "decode_cpu_s": decode_s, "rows": rows}
        args.json.write_text(json.dumps(figures, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
