"""Full vs indexed place search (issue #17), side by side: verified recall, revisit coverage, cost.

Datasets (tuning sets only; Lip6 Outdoor is held out and is not run here):

    python -m bench.place_search rtabmap                      # ~10 s
    python -m bench.place_search log sample_logs/drive_loops.ros2.mcap \\
        --gt sample_logs/drive_loops.gt.npz                        # ~1 minute
    python -m bench.place_search log /tmp/hour/hour.ros2.mcap --gt-topic /ground_truth/pose \\
        --radius 2 --max-heading 20 --min-travel 20 --minutes 20   # annotate + evaluate
    python -m bench.place_search cost --sizes 25000,250000    # detector alone, ~10 min

Each run annotates with the verified defaults (`verified_detector_parameters`) and
`place_search` set to each mode (plus any --set NAME=VALUE), then scores the accepted pairs.
The figures are `evaluate`'s verified ones (R@P100, and the revisit coverage: of the 1-s and
5-s windows holding a ground-truth revisit, the share holding a true accepted pair). `cost`
times the detector alone on a synthetic route driven lap after lap (the `Route` of
tools/bench/place_index.py), index mode only (full mode is quadratic), CPU time per frame over
the frames after each size.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from doseqslam_logs.detector import DOSeqSLAM, PreparedFrame
from doseqslam_logs.detector.params import Parameters
from doseqslam_logs.evaluation.folder_run import evaluate_folder
from doseqslam_logs.evaluation.log_run import LogEvaluationOptions, evaluate_log
from doseqslam_logs.evaluation.metrics import Evaluation
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.sources import open_source
from doseqslam_logs.verification.params import verified_detector_parameters

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[2]
RTABMAP = REPO.parent / "shared" / "data" / "rtabmap_samples_loop"
MODES = ("full", "index")


@dataclass(frozen=True)
class Row:
    """One run's verified figures (`evaluate`'s), and what it cost."""

    name: str
    mode: str
    verified: Evaluation
    pairs: int  # frame pairs checked by verification
    wall_s: float
    stage_seconds: dict[str, float]


def run_rtabmap(changes: dict[str, Any]) -> list[Row]:
    """`evaluate --images` (evaluate_folder) on the RTAB-Map samples, kappa 10 s, per mode."""
    rows = []
    for mode in MODES:
        params = verified_detector_parameters(kappa_s=10.0, place_search=mode, **changes)
        start = time.perf_counter()
        run = evaluate_folder(RTABMAP / "images", 1.0, RTABMAP / "samples_GT.bmp", params)
        wall = time.perf_counter() - start
        assert run.verified is not None and run.verification is not None
        pairs = run.verification.stats.pairs
        rows.append(Row("rtabmap", mode, run.verified, pairs, wall, run.result.stage_seconds))
    return rows


def run_log(args: argparse.Namespace, changes: dict[str, Any]) -> list[Row]:
    """`annotate` (annotate_log) then `evaluate OUT.mcap` (evaluate_log), per mode."""
    gt = LogEvaluationOptions(
        gt=Path(args.gt) if args.gt else None,
        gt_topic=args.gt_topic,
        radius=args.radius,
        max_heading=args.max_heading,
        min_travel=args.min_travel,
    )
    end_ns = None
    if args.minutes:
        with open_source(args.log) as source:
            first = min(c.first_log_time_ns or 0 for c in source.channels() if c.is_image)
        end_ns = first + round(args.minutes * 60e9)
    rows = []
    for mode in MODES:
        params = verified_detector_parameters(place_search=mode, **changes)
        out = Path(args.out) / f"{Path(args.log).stem}.{mode}.mcap"
        start = time.perf_counter()
        result = annotate_log(args.log, out, params, AnnotateOptions(end_ns=end_ns))
        wall = time.perf_counter() - start
        verified = evaluate_log(out, gt).result.verified
        assert verified is not None and result.verification is not None
        pairs = result.verification.stats.pairs
        seconds = result.replay.stage_seconds
        rows.append(Row(Path(args.log).name, mode, verified, pairs, wall, seconds))
        stages = ", ".join(f"{k} {v:.1f}" for k, v in sorted(seconds.items()))
        print(f"  {mode}: {result.replay.frames} frames, wall {wall:.1f} s ({stages})", flush=True)
    return rows


def print_rows(rows: list[Row]) -> None:
    windows = " | ".join(f"cov {c.window_s:g} s" for c in rows[0].verified.coverage)
    print(f"| set | mode | TP | FP | R@P100 | {windows} | pairs | wall s | sad s | places s |")
    print("|---" * (9 + len(rows[0].verified.coverage)) + "|")
    for r in rows:
        e = r.verified
        cov = " | ".join(f"{100 * c.share:.1f} %" for c in e.coverage)
        sad, places = r.stage_seconds.get("sad", 0.0), r.stage_seconds.get("places", 0.0)
        print(
            f"| {r.name} | {r.mode} | {e.tp} | {e.fp} | {100 * e.r_p100:.2f} % | {cov} "
            f"| {r.pairs} | {r.wall_s:.1f} | {sad:.1f} | {places:.1f} |"
        )


# -- cost: detector alone on a synthetic lapped route ------------------------------------------


class EveryN:
    """A segmenter that starts a sequence every `n` frames (no features needed)."""

    name = "orb"

    def __init__(self, n: int) -> None:
        self.n, self.count = n, 0

    def prepare(self, gray: Any) -> None:
        return None

    def update(self, prepared: Any) -> bool:
        self.count += 1
        return (self.count - 1) % self.n == 0

    def restart(self, prepared: Any) -> None:
        self.count = 1

    def starts_sequence(self, gray: Any) -> bool:
        return self.update(None)


def run_cost(sizes: list[int], measure: int, sequence: int) -> None:
    from bench.place_index import Route

    route = Route(places=5000)
    tables = route.tables()
    rng = np.random.default_rng(3)
    places = rng.standard_normal((route.places, 2048)).astype(np.float32)
    params = Parameters(place_search="index", alternatives=3, threshold=0.99)
    detector = DOSeqSLAM(params, segmenter=EveryN(sequence))
    frame_ns = 100_000_000  # 10 Hz
    t = 0
    print("| frames | index mode CPU ms/frame | sad+places ms/frame | memory MB |")
    print("|---|---|---|---|")
    for size in sorted(sizes):
        while t < size:
            push(detector, route, tables, places, rng, t, frame_ns)
            t += 1
        before = dict(detector.timings.seconds)
        start = time.process_time()
        for _ in range(measure):
            push(detector, route, tables, places, rng, t, frame_ns)
            t += 1
        cpu = (time.process_time() - start) / measure
        after = detector.timings.seconds
        search = sum(after.get(k, 0.0) - before.get(k, 0.0) for k in ("sad", "places"))
        mb = detector.memory_bytes / 2**20
        print(f"| {size} | {1e3 * cpu:.2f} | {1e3 * search / measure:.2f} | {mb:.0f} |", flush=True)


def push(
    detector: DOSeqSLAM,
    route: Any,
    tables: Any,
    places: np.ndarray,
    rng: np.random.Generator,
    t: int,
    frame_ns: int,
) -> None:
    vector = places[t % route.places] + 0.3 * rng.standard_normal(2048).astype(np.float32)
    frame = PreparedFrame(vector, None, route.frame(t, tables))
    detector.push_prepared(t * frame_ns, frame)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=("rtabmap", "log", "cost"))
    parser.add_argument("log", nargs="?")
    parser.add_argument("--gt")
    parser.add_argument("--gt-topic")
    parser.add_argument("--radius", type=float)
    parser.add_argument("--max-heading", type=float)
    parser.add_argument("--min-travel", type=float)
    parser.add_argument("--minutes", type=float, help="annotate only the first minutes")
    parser.add_argument("--out", default=tempfile.gettempdir())
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    parser.add_argument("--sizes", default="25000,250000")
    parser.add_argument("--measure", type=int, default=2000)
    parser.add_argument("--sequence", type=int, default=30, help="frames per sequence (cost)")
    args = parser.parse_args()
    changes: dict[str, Any] = {}
    for item in args.set:
        changes.update(tomllib.loads(item))
    if args.what == "rtabmap":
        print_rows(run_rtabmap(changes))
    elif args.what == "log":
        print_rows(run_log(args, changes))
    else:
        run_cost([int(s) for s in args.sizes.split(",")], args.measure, args.sequence)


if __name__ == "__main__":
    main()
