#!/usr/bin/env python3
"""How fast this (shared) machine is right now: a fixed SIFT loop, in CPU ms per frame.

The segmentation's SIFT is two thirds of the hour's annotate time, and the machine's speed
varies during a day (docs/performance.md: 10.4 to 15.0 ms a frame within two hours). Run this
next to a benchmark to tell a slower machine from slower code. The frames: the first 400 of a
log's camera topic, shrunk to 240 px as the segmentation does, SIFT (500 features) on 2 threads.

    python -m bench.cpu_gauge                     # the 1-hour log
    python -m bench.cpu_gauge sample_logs/drive_loops.ros2.mcap
"""

from __future__ import annotations

import argparse
import resource
import time
from concurrent.futures import ThreadPoolExecutor
from itertools import islice
from pathlib import Path

import cv2

from doseqslam_logs.detector.segmentation import shrink
from doseqslam_logs.pipeline.decode import FrameCounts, decoded_frames
from doseqslam_logs.sources import open_source, pick_image_topic

FRAMES = 400


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", type=Path, nargs="?", default=Path("/tmp/hour/hour.ros2.mcap"))
    args = parser.parse_args()
    with open_source(args.log) as source:
        topic = pick_image_topic(source, None)
        frames = decoded_frames(source.image_messages(topic), FrameCounts(), "header", "skip")
        images = [shrink(frame.image, 240) for frame in islice(frames, FRAMES)]
    sift = [cv2.SIFT.create(nfeatures=500) for _ in range(2)]

    def work(k: int) -> None:
        for image in images[k::2]:
            sift[k].detectAndCompute(image, None)

    before, start = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    with ThreadPoolExecutor(2) as pool:
        list(pool.map(work, [0, 1]))
    wall, after = time.perf_counter() - start, resource.getrusage(resource.RUSAGE_SELF)
    cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    print(
        f"{time.strftime('%H:%M:%S')} SIFT on {len(images)} frames: {wall:.2f} s wall, "
        f"{1e3 * cpu / len(images):.2f} ms CPU a frame"
    )


if __name__ == "__main__":
    main()
