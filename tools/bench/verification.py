#!/usr/bin/env python3
"""The verification stage alone on a log's decisions, for this package and others side by side.

The detector's decisions (`annotate`'s: th = VERIFIED_THRESHOLD, alternatives on) and the frame
times are computed once and cached in a pickle in the temporary folder (--cache; minutes on
the 1-hour log); each measurement then runs `verify_in_threads` over them with the frame
re-reads of `annotate` (`LogFrameReader`, 2 threads, the default feature cache) in a fresh
process. With --compare,
each run of this package is followed by the same run of each other package, --repeat times.

    python -m bench.verification                                   # the 1-hour log
    git archive HEAD~1 doseqslam_logs schemas | tar -x -C /tmp/d_prev
    python -m bench.verification --compare /tmp/d_prev --repeat 2

Columns: wall and CPU seconds of the stage; frame pairs checked; frames re-read; load, features
and pairs: seconds summed over the threads (`VerificationStats`); accepted pairs and a hash of
the accepted (query, refined match) set, equal when two versions accept the same pairs.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import pickle
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
HOUR = Path("/tmp/hour/hour.ros2.mcap")
COLUMNS = (
    "version",
    "wall s",
    "CPU s",
    "frame pairs",
    "frames re-read",
    "load s",
    "features s",
    "pairs s",
    "accepted",
    "accepted set",
)


def cache_decisions(log: Path, cache: Path) -> None:
    """Replay the detector once (as annotate does, verification off) and pickle what the
    verification stage needs."""
    from doseqslam_logs.detector import make_detector
    from doseqslam_logs.pipeline.annotate import _TimesRecorder  # annotate's own frame-time record
    from doseqslam_logs.pipeline.decode import FrameCounts, decoded_frames
    from doseqslam_logs.pipeline.replay import replay
    from doseqslam_logs.sources import open_source, pick_image_topic
    from doseqslam_logs.verification import verified_detector_parameters

    recorder = _TimesRecorder()
    with open_source(log) as source:
        topic = pick_image_topic(source, None)
        frames = decoded_frames(source.image_messages(topic), FrameCounts(), "header", "skip")
        detector = make_detector(verified_detector_parameters())
        result = replay(recorder(frames), detector, None, 2)
    state = (result.decisions, recorder.frame_times(), str(log), topic)
    cache.write_bytes(pickle.dumps(state))


def child(cache: Path) -> None:
    """One measurement; prints one JSON line."""
    import doseqslam_logs
    from doseqslam_logs.pipeline.reread import LogFrameReader
    from doseqslam_logs.verification import DEFAULT_VERIFICATION
    from doseqslam_logs.verification.stage import verify_in_threads

    decisions, times, path, topic = pickle.loads(cache.read_bytes())
    before = resource.getrusage(resource.RUSAGE_SELF)
    start = time.perf_counter()
    checked, stats = verify_in_threads(
        decisions, lambda: LogFrameReader(path, topic, times), DEFAULT_VERIFICATION, None, 2
    )
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_SELF)
    accepted = sorted(
        (c.candidate.query_index, c.refined_match_index)
        for v in checked
        for c in v.checks
        if c.accepted
    )
    figures = {
        "version": Path(doseqslam_logs.__file__).resolve().parent.parent.name,
        "wall s": round(wall, 1),
        "CPU s": round(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, 1),
        "frame pairs": stats.pairs,
        "frames re-read": stats.frames_loaded,
        "load s": round(stats.load_s, 1),
        "features s": round(stats.features_s, 1),
        "pairs s": round(stats.pairs_s, 1),
        "accepted": stats.accepted,
        "accepted set": hashlib.sha256(repr(accepted).encode()).hexdigest()[:10],
    }
    print(json.dumps(figures))


def run(cache: Path, tree: Path | None) -> dict[str, Any]:
    env = dict(os.environ)
    if tree is not None:  # PYTHONPATH comes before the installed (editable) package
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(tree), env.get("PYTHONPATH")]))
    command = [sys.executable, __file__, "--child", str(cache)]
    done = subprocess.run(command, capture_output=True, text=True, check=False, env=env)
    if done.returncode != 0:
        raise SystemExit(f"verification with {tree or ROOT} failed:\n{done.stderr[-3000:]}")
    figures: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    if tree is not None:
        figures["version"] = str(tree)
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--log", type=Path, default=HOUR)
    parser.add_argument("--compare", type=Path, action="append", default=[])
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--cache", type=Path, help="decisions pickle (default: temp dir)")
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        child(args.child)
        return
    if not args.log.exists():
        raise SystemExit(f"{args.log} not found (tools/bench/annotate.py says how to make it)")
    cache = args.cache or Path(tempfile.gettempdir()) / f"{args.log.name}.decisions.pkl"
    if not cache.exists():
        print(f"caching the detector's decisions of {args.log} in {cache} ...", file=sys.stderr)
        cache_decisions(args.log, cache)
    rows = []
    for _ in range(args.repeat):
        for tree in [None, *args.compare]:
            rows.append(run(cache, tree))
            print(json.dumps(rows[-1]), file=sys.stderr)
    print(f"load average at the end: {' '.join(f'{x:.2f}' for x in os.getloadavg())}\n")
    print("| " + " | ".join(COLUMNS) + " |")
    print("|" + "---|" * len(COLUMNS))
    for row in rows:
        print("| " + " | ".join(str(row[c]) for c in COLUMNS) + " |")


if __name__ == "__main__":
    main()
