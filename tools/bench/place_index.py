"""Benchmark the place index (doseqslam_logs/detector/place_index.py): cost and recall.

Cost: per-query and per-add time at several database sizes, on a synthetic route driven lap
after lap. Each frame sees the landmarks of its place (each visible from a few consecutive
places) with bit noise, plus clutter seen once: words recur as they do for a robot driving
the same route. The index is built once, frame by frame with `add`; a copy is kept at each
size, and the copies are then timed in turns (round robin), so that a change of the machine's
load during the run shifts every size alike. Times are CPU time of this process (less
disturbed than wall time by other processes; both are printed).

Recall: on the committed sample logs (and with --rtabmap the RTAB-Map corridor images), ORB
descriptors as the pipeline extracts them (`DescriptorSegmenter("orb").prepare`), frames
added online, each frame queried against frames at least --min-age-s seconds older before it
is added. A query is a hit at k when one of its k results is within --tolerance frames of a
ground-truth cell. Only queries with a ground-truth cell in their database count.

    python -m bench.place_index --rtabmap          # about 9 minutes on 2 shared cores
    python -m bench.place_index --sizes 2500,25000   # about 1.5 minutes
"""

from __future__ import annotations

import argparse
import copy
import resource
import statistics
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from doseqslam_logs.detector.params import Parameters
from doseqslam_logs.detector.place_index import PlaceIndex, PlaceIndexParams, memory_bound
from doseqslam_logs.detector.segmentation import DescriptorSegmenter

REPO = Path(__file__).resolve().parents[2]
SAMPLES = REPO / "sample_logs"
SAMPLE_LOGS = ("drive_loops.ros2.mcap", "drive_parked.ros2.mcap", "drive_varrate.bag")
RTABMAP = REPO.parent / "shared" / "data" / "rtabmap_samples_loop"
RTABMAP_RATE_HZ = 1.0  # the images have no stamps; its README suggests 1 Hz
RATE_HZ = 2.0  # synthetic frames per second, for the minimum age
KS = (1, 3, 5)
NOISE_POOL = 1 << 16  # noise masks drawn from (a pool: drawing bits per frame is slower)

Descriptors = npt.NDArray[np.uint8]


# -- synthetic route ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Route:
    """A closed route of `places` places, one frame per place, driven lap after lap.

    Each place introduces `landmarks` landmarks, each visible from `persist` consecutive
    places; a frame sees each visible landmark with probability `seen`, as its descriptor
    with `noise_bits` random bits flipped, plus `clutter` random descriptors seen once.
    The total per frame is cut to a count drawn in [min_descriptors, max_descriptors].
    """

    places: int = 2000
    landmarks: int = 80
    persist: int = 5
    seen: float = 0.85
    noise_bits: int = 16
    clutter: int = 60
    min_descriptors: int = 300
    max_descriptors: int = 500
    seed: int = 7

    def tables(self) -> tuple[Descriptors, Descriptors]:
        """The landmarks' descriptors, and a pool of noise masks of `noise_bits` bits each."""
        rng = np.random.default_rng([self.seed, 0])
        landmarks = rng.integers(0, 256, (self.places * self.landmarks, 32), dtype=np.uint8)
        bits = np.argsort(rng.random((NOISE_POOL, 256)), axis=1)[:, : self.noise_bits]
        masks = np.zeros((NOISE_POOL, 256), dtype=np.uint8)
        np.put_along_axis(masks, bits, 1, axis=1)
        return landmarks, np.packbits(masks, axis=1)

    def frame(self, t: int, tables: tuple[Descriptors, Descriptors]) -> Descriptors:
        """Frame t's descriptors (a pure function of the seed and t)."""
        landmarks, noise = tables
        rng = np.random.default_rng([self.seed, 1, t])
        place = t % self.places
        visible = np.arange(place - self.persist + 1, place + 1) % self.places
        ids = (visible[:, None] * self.landmarks + np.arange(self.landmarks)).ravel()
        ids = ids[rng.random(len(ids)) < self.seen]
        observed = landmarks[ids] ^ noise[rng.integers(0, NOISE_POOL, len(ids))]
        clutter = rng.integers(0, 256, (self.clutter, 32), dtype=np.uint8)
        frame = np.concatenate([observed, clutter])[rng.permutation(len(ids) + self.clutter)]
        return frame[: rng.integers(self.min_descriptors, self.max_descriptors + 1)]

    def is_hit(self, query: int, result: int, tolerance: int = 2) -> bool:
        """Whether a result frame is at the query's place (within tolerance places)."""
        offset = (result - query) % self.places
        return min(offset, self.places - offset) <= tolerance


@dataclass
class Timing:
    query_cpu: list[float]
    add_cpu: list[float]
    query_wall: list[float]
    add_wall: list[float]
    hits: dict[int, int]
    queries: int = 0


def time_round(
    index: PlaceIndex,
    route: Route,
    tables: tuple[Descriptors, Descriptors],
    count: int,
    min_age: int,
    timing: Timing,
) -> None:
    """Query then add the next `count` frames of the route; per-frame times appended."""
    first = index.frame_count
    frames = [route.frame(t, tables) for t in range(first, first + count)]
    cpu, wall = time.process_time(), time.perf_counter()
    results = [index.query(f, first + i - min_age + 1, max(KS)) for i, f in enumerate(frames)]
    timing.query_cpu.append((time.process_time() - cpu) / count)
    timing.query_wall.append((time.perf_counter() - wall) / count)
    cpu, wall = time.process_time(), time.perf_counter()
    for i, f in enumerate(frames):
        index.add(first + i, f)
    timing.add_cpu.append((time.process_time() - cpu) / count)
    timing.add_wall.append((time.perf_counter() - wall) / count)
    for i, result in enumerate(results):
        timing.queries += 1
        for k in KS:
            timing.hits[k] += any(route.is_hit(first + i, j) for j, _ in result[:k])


def build(
    params: PlaceIndexParams, route: Route, sizes: list[int]
) -> Iterator[tuple[int, PlaceIndex, float]]:
    """Add frames up to each size in turn; yields (size, a copy of the index, seconds)."""
    tables = route.tables()
    index = PlaceIndex(params)
    start = time.perf_counter()
    for number, size in enumerate(sizes):
        for t in range(index.frame_count, size):
            index.add(t, route.frame(t, tables))
        last = number == len(sizes) - 1  # the largest is not copied: it is the biggest
        yield size, index if last else copy.deepcopy(index), time.perf_counter() - start


def peak_rss_mb() -> float:
    # ru_maxrss is in KiB on Linux, bytes on macOS.
    scale = 1 if sys.platform == "darwin" else 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale / 1e6


def bench_cost(args: argparse.Namespace, params: PlaceIndexParams) -> None:
    route = Route(places=args.places, seed=args.seed)
    min_age = round(args.min_age_s * RATE_HZ)
    print(
        f"synthetic route: {route.places} places a lap, {route.landmarks} landmarks per place "
        f"seen over {route.persist} places, {route.noise_bits} noisy bits, {route.clutter} "
        f"clutter, {route.min_descriptors}-{route.max_descriptors} descriptors a frame; "
        f"queries exclude the last {min_age} frames"
    )
    snapshots: list[tuple[int, PlaceIndex]] = []
    for size, snapshot, seconds in build(params, route, args.sizes):
        print(
            f"  built {size:,} frames in {seconds:.0f} s: {snapshot.word_count:,} words, "
            f"{snapshot.memory_bytes / 1e6:.1f} MB (bound {memory_bound(params, size) / 1e6:.0f}"
            f" MB), peak RSS so far {peak_rss_mb():.0f} MB",
            flush=True,
        )
        snapshots.append((size, snapshot))
    tables = route.tables()
    timings = {size: Timing([], [], [], [], dict.fromkeys(KS, 0)) for size, _ in snapshots}
    for _ in range(args.rounds):
        for size, index in snapshots:
            time_round(index, route, tables, args.frames, min_age, timings[size])
    print_cost_table(snapshots, timings)


def print_cost_table(snapshots: list[tuple[int, PlaceIndex]], timings: dict[int, Timing]) -> None:
    print()
    print(
        "| frames | query ms (cpu) | add ms (cpu) | query ms (wall) | add ms (wall) | words "
        "| postings | memory MB | recall@1 | recall@5 |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    medians: dict[int, tuple[float, float]] = {}
    for size, index in snapshots:
        t = timings[size]
        q, a = statistics.median(t.query_cpu) * 1e3, statistics.median(t.add_cpu) * 1e3
        medians[size] = (q, a)
        qw, aw = statistics.median(t.query_wall) * 1e3, statistics.median(t.add_wall) * 1e3
        print(
            f"| {size:,} | {q:.2f} | {a:.2f} | {qw:.2f} | {aw:.2f} | {index.word_count:,} | "
            f"{index.posting_count:,} | {index.memory_bytes / 1e6:.1f} | "
            f"{t.hits[1] / t.queries:.3f} | {t.hits[5] / t.queries:.3f} |"
        )
    memory = {size: index.memory_bytes for size, index in snapshots}
    for small, large in pairwise(sorted(medians)):
        q, a = (medians[large][c] / medians[small][c] for c in (0, 1))
        growth = (memory[large] - memory[small]) / (large - small)
        print(
            f"{large:,} / {small:,} frames: cost ratio query {q:.2f}, add {a:.2f}; "
            f"memory grew {growth:,.0f} bytes a frame (allocated)"
        )
    print(f"peak RSS of this process: {peak_rss_mb():.0f} MB (all copies of the index included)")


# -- recall on real images ----------------------------------------------------------------------


@dataclass(frozen=True)
class Sequence:
    name: str
    descriptors: list[Descriptors]
    stamps_s: npt.NDArray[np.float64]
    gt: npt.NDArray[np.uint8]


def orb_descriptors(gray: npt.NDArray[np.uint8], segmenter: DescriptorSegmenter) -> Descriptors:
    """The pipeline's ORB descriptors of a frame (none: an empty (0, 32) array)."""
    found = segmenter.prepare(gray).descriptors
    return np.zeros((0, 32), np.uint8) if found is None else np.asarray(found, dtype=np.uint8)


def load_log(path: Path, segmenter: DescriptorSegmenter) -> Sequence:
    from doseqslam_logs.sources import decode_gray, open_source, pick_image_topic

    descriptors, stamps = [], []
    with open_source(path) as source:
        for message in source.image_messages(pick_image_topic(source)):
            descriptors.append(orb_descriptors(decode_gray(message), segmenter))
            stamp = message.header_stamp_ns or message.log_time_ns
            stamps.append(stamp / 1e9)
    gt = np.load(path.parent / (path.name.split(".")[0] + ".gt.npz"))["gt"]
    return Sequence(path.name, descriptors, np.asarray(stamps), gt)


def read_gray(path: Path) -> npt.NDArray[np.uint8]:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise SystemExit(f"{path}: cannot read the image")
    return np.asarray(image, dtype=np.uint8)


def load_rtabmap(root: Path, segmenter: DescriptorSegmenter) -> Sequence:
    gt = (read_gray(root / "samples_GT.bmp") > 0).astype(np.uint8)
    descriptors = []
    for number in range(1, len(gt) + 1):
        descriptors.append(orb_descriptors(read_gray(root / "images" / f"{number}.jpg"), segmenter))
    stamps = np.arange(len(gt)) / RTABMAP_RATE_HZ
    return Sequence("rtabmap_samples_loop", descriptors, stamps, gt)


def recall(
    sequence: Sequence, params: PlaceIndexParams, min_age_s: float, tolerance: int
) -> dict[str, float]:
    """Recall@k over the ground-truth loop queries, and the median top score of loop and
    non-loop queries."""
    index = PlaceIndex(params)
    hits, queries = dict.fromkeys(KS, 0), 0
    loop_scores, other_scores = [], []
    gt = sequence.gt
    for i, desc in enumerate(sequence.descriptors):
        before = int(np.searchsorted(sequence.stamps_s, sequence.stamps_s[i] - min_age_s, "right"))
        if before > 0:
            result = index.query(desc, before, max(KS))
            top = result[0][1] if result else 0.0
            if gt[i, :before].any():
                queries += 1
                loop_scores.append(top)
                for k in KS:
                    near = [
                        gt[i, max(0, j - tolerance) : j + tolerance + 1].any()
                        for j, _ in result[:k]
                    ]
                    hits[k] += any(near)
            elif not gt[i].any():
                other_scores.append(top)
        index.add(i, desc)
    summary = {f"recall@{k}": hits[k] / max(queries, 1) for k in KS}
    summary["queries"] = queries
    summary["loop score"] = statistics.median(loop_scores) if loop_scores else float("nan")
    summary["other score"] = statistics.median(other_scores) if other_scores else float("nan")
    summary["words"] = index.word_count
    return summary


def bench_recall(args: argparse.Namespace, params: PlaceIndexParams) -> None:
    segmenter = DescriptorSegmenter(Parameters(feature_detector="orb"), "orb")
    sequences = [load_log(args.samples / name, segmenter) for name in SAMPLE_LOGS]
    ages = [args.min_age_s] * len(sequences)
    if args.rtabmap:
        sequences.append(load_rtabmap(args.rtabmap_dir, segmenter))
        ages.append(args.rtabmap_min_age_s)
    print()
    print(
        "| sequence | frames | min age s | loop queries | recall@1 | recall@3 | recall@5 | "
        "median top score, loop / other | words |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for sequence, age in zip(sequences, ages, strict=True):
        r = recall(sequence, params, age, args.tolerance)
        print(
            f"| {sequence.name} | {len(sequence.descriptors)} | {age:g} | {r['queries']:.0f} | "
            f"{r['recall@1']:.3f} | {r['recall@3']:.3f} | {r['recall@5']:.3f} | "
            f"{r['loop score']:.3f} / {r['other score']:.3f} | {r['words']:,.0f} |"
        )


def sizes(text: str) -> list[int]:
    values = sorted({int(v.replace("_", "")) for v in text.split(",") if v})
    if not values or values[0] < 1:
        raise argparse.ArgumentTypeError("sizes must be positive integers")
    return values


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sizes",
        type=sizes,
        default=[2500, 25000, 250000],
        help="database sizes to time, comma separated (default 2500,25000,250000: "
        "building 250,000 frames takes about 8 minutes)",
    )
    parser.add_argument("--frames", type=int, default=100, help="frames timed per round")
    parser.add_argument("--rounds", type=int, default=5, help="rounds of timing per size")
    parser.add_argument("--places", type=int, default=2000, help="places per synthetic lap")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument(
        "--min-age-s",
        type=float,
        default=40.0,
        help="database frames are at least this much older (default 40 s)",
    )
    parser.add_argument("--tolerance", type=int, default=2, help="frames off a GT cell for a hit")
    parser.add_argument("--samples", type=Path, default=SAMPLES, help="sample_logs directory")
    parser.add_argument("--rtabmap", action="store_true", help="also the RTAB-Map images")
    parser.add_argument("--rtabmap-dir", type=Path, default=RTABMAP)
    parser.add_argument(
        "--rtabmap-min-age-s",
        type=float,
        default=20.0,
        help="minimum age on the RTAB-Map images at 1 Hz (its revisits are "
        "about 40 frames old; default 20 s)",
    )
    parser.add_argument("--no-cost", action="store_true", help="skip the synthetic timing")
    parser.add_argument("--no-recall", action="store_true", help="skip the recall on images")
    args = parser.parse_args(argv)
    params = PlaceIndexParams()
    print(f"parameters: {params}")
    if not args.no_recall:
        bench_recall(args, params)
    if not args.no_cost:
        print()
        bench_cost(args, params)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
