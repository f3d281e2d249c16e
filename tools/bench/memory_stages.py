#!/usr/bin/env python3
"""Where the memory of `annotate` goes: resident memory at each stage and what each stage holds.

Runs `annotate_log` with the command's defaults on a log (optionally its first --minutes) and
prints, as JSON lines:

* for each stage (replay, verify, metric, annotations, write): resident memory when it ends
  and its own peak (VmHWM, reset before the stage through /proc/self/clear_refs);
* the deep size of what is held between stages: the detector's frame vectors and place
  index (array by array), the replay's decisions, the verified decisions, the annotation
  messages (Python objects and NumPy buffers, each object counted once).

Divide two runs' figures (e.g. 10 and 20 minutes) by their frame counts' difference to get the
bytes per frame of each component.

    python -m bench.memory_stages /tmp/hour/hour.ros2.mcap --minutes 10 -o /tmp/o.mcap
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import sys
import time
from array import array
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.pipeline.stages import StageObserver
from doseqslam_logs.sources import open_source, pick_image_topic


def _status(field: str) -> int:
    """A /proc/self/status field in bytes (VmRSS, VmHWM)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    return 0


def _reset_peak() -> None:
    with contextlib.suppress(OSError):
        Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM to the current RSS


def deep_size(root: object) -> int:
    """Bytes of `root` and everything it references (each object once; NumPy buffers by
    nbytes; classes, functions and modules not followed)."""
    seen: set[int] = set()
    stack = [root]
    total = 0
    while stack:
        item = stack.pop()
        if id(item) in seen or isinstance(item, type | Callable):
            continue
        seen.add(id(item))
        total += sys.getsizeof(item)
        if isinstance(item, np.ndarray):  # getsizeof counts an owned buffer
            continue
        if isinstance(item, str | bytes | bytearray | int | float | array | memoryview):
            continue
        if isinstance(item, dict):
            stack.extend(item.keys())
            stack.extend(item.values())
        elif isinstance(item, list | tuple | set | frozenset):
            stack.extend(item)
        else:
            if hasattr(item, "__dict__"):
                stack.append(vars(item))
            for name in getattr(type(item), "__slots__", ()):
                if hasattr(item, name):
                    stack.append(getattr(item, name))
    return total


def _mb(value: int) -> float:
    return round(value / 2**20, 2)


class Probe(StageObserver):
    """Hears the run's stages (pipeline.annotate.StageObserver) and records memory after each."""

    def __init__(self) -> None:
        self.rows: list[dict[str, Any]] = []
        self.detector: Any = None
        self.started_at = time.perf_counter()

    def record(self, stage: str, sizes: Callable[[], dict[str, int]] = dict) -> None:
        """Memory now and the stage's peak, then the deep sizes (measured after, so that
        their own traversal is not in the figures)."""
        row: dict[str, Any] = {
            "stage": stage,
            "rss_mb": _mb(_status("VmRSS")),
            "stage_peak_mb": _mb(_status("VmHWM")),
            "t_s": round(time.perf_counter() - self.started_at, 1),
        }
        row.update(  # MB, counts as they are
            {k: v if k.endswith("_count") else _mb(v) for k, v in sizes().items()}
        )
        self.rows.append(row)
        print(json.dumps(row), flush=True)
        _reset_peak()

    def detector_made(self, detector: Any) -> None:
        self.detector = detector

    def finished(self, stage: str, product: object) -> None:
        if stage == "replay":
            self.record("replay", lambda: {**self.detector_parts(), **decisions_of(product)})
            self.detector = None  # the run frees its detector now: so does the probe
        elif stage == "verify":
            self.record("verify_decisions", lambda: verified_of(product))
        elif stage == "metric":
            self.record("metric_edges", lambda: {"metric_edges": deep_size(product)})
        elif stage == "annotations":
            self.record("annotations", lambda: messages_of(getattr(product, "messages", ())))
        elif stage == "write":
            self.record("write_annotated_mcap")

    def detector_parts(self) -> dict[str, int]:
        d = self.detector
        parts = {"detector_memory_bytes": int(d.memory_bytes)}
        store = getattr(d, "_store", None)
        if store is not None:
            parts["frame_store"] = int(store.nbytes)
            parts["frame_store_spilled"] = int(getattr(store, "spilled_bytes", 0))
        places = getattr(d, "_places", None)
        if places is not None:
            index = places.index
            parts["index_postings"] = sum(c.nbytes for c in index._postings.columns)
            parts["index_vocabulary"] = sum(c.nbytes for c in index._vocabulary.columns) + int(
                index._vocabulary.slots.nbytes
            )
            parts["places_waiting"] = deep_size(places._waiting)
            print(json.dumps(posting_use(index)), flush=True)
        return parts


def posting_use(index: Any) -> dict[str, int]:
    """Postings held against those a query can still read: within posting_cap of the head
    of a live word's list."""
    postings, vocabulary = index._postings, index._vocabulary
    entries = vocabulary.head.view.astype(np.int64)
    readable = np.zeros(postings.next.size, dtype=bool)
    for _ in range(index.params.posting_cap):
        readable[entries] = True
        entries = np.take(postings.next.data, entries).astype(np.int64)
    readable[0] = False
    return {
        "frames": index.frame_count,
        "postings": index.posting_count,
        "postings_capacity": len(postings.next.data),
        "postings_readable": int(readable.sum()),
        "live_words": index.word_count,
        "word_capacity": len(vocabulary.head.data),
    }


def decisions_of(result: Any) -> dict[str, int]:
    decisions = result.decisions
    candidates = [c for d in decisions for c in d.candidates]
    alternatives = [a for d in decisions for a in d.alternatives]
    return {
        "decisions": deep_size(decisions),
        "decisions_candidates": deep_size(candidates),
        "decisions_alternatives": deep_size(alternatives),
        "feature_counts": deep_size(result.feature_counts),
    }


def messages_of(messages: Any) -> dict[str, int]:
    """The messages' size in memory, and in their spool's file when they are spooled."""
    sizes = {"messages": deep_size(messages), "message_count": len(messages)}
    spool = getattr(messages, "_file", None)
    if spool is not None:
        sizes["messages_spool_file"] = os.fstat(spool.fileno()).st_size
    return sizes


def verified_of(verification: Any) -> dict[str, int]:
    if verification is None:
        return {}
    checks = [c for v in verification.decisions.values() for c in v.checks]
    verdicts = [c.verdict for c in checks]
    return {
        "verified_total": deep_size(verification.decisions),
        "verified_checks": deep_size(checks),
        "verified_verdicts": deep_size(verdicts),
    }


def _end_ns(log: Path, minutes: float | None) -> tuple[str, int | None]:
    with open_source(log) as source:
        topic = pick_image_topic(source, None)
        if minutes is None:
            return topic, None
        first = next(iter(source.image_messages(topic, None, None))).log_time_ns
    return topic, first + round(minutes * 60e9)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("log", type=Path)
    parser.add_argument("-o", "--output", type=Path, required=True)
    parser.add_argument("--minutes", type=float, default=None)
    args = parser.parse_args(argv)
    topic, end_ns = _end_ns(args.log, args.minutes)
    probe = Probe()
    probe.record("start")
    options = AnnotateOptions(topic=topic, end_ns=end_ns)
    result = annotate_log(args.log, args.output, options=options, observer=probe)
    summary = {
        "frames": result.replay.frames,
        "sequences": len(result.replay.decisions),
        "loop_closures": result.loop_closures,
        "peak_rss_mb": _mb(max(int(r["stage_peak_mb"] * 2**20) for r in probe.rows)),
    }
    print(json.dumps({"summary": summary, **dataclasses.asdict(result.counts)}, default=str))


if __name__ == "__main__":
    main()
