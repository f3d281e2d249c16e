"""CPU seconds of reading a log's camera topic and its side topics (the pose topic and the
CameraInfo a run reads): one pass for them all (`Source.image_and_side_messages`, what annotate
does) against the camera's pass plus a pass per side topic (what it did before). Images are
read, not decoded; side messages are decoded as the run decodes them (every pose, the first
usable CameraInfo). Rounds alternate the two ways; the machine's speed moves, so compare the
rounds' medians.

    PYTHONPATH=tools python -m bench.side_topics_pass /tmp/hour/hour.ros2.mcap --rounds 3
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from doseqslam_logs.pipeline.side_topics import SideTopics
from doseqslam_logs.sources import open_source, pick_image_topic
from doseqslam_logs.sources.camera_info import find_camera_info
from doseqslam_logs.sources.poses import read_poses


def one_pass(log: Path) -> float:
    """CPU seconds of the camera topic and the side topics in one pass."""
    start = time.process_time()
    with open_source(log) as source:
        topic = pick_image_topic(source, None)
        side = SideTopics.for_run(source, topic, None, camera_info=True)
        frames = sum(1 for _ in side.split(source.image_and_side_messages(topic, side.topics)))
        side.pose_track(), side.camera_info_search()
    assert frames > 0
    return time.process_time() - start


def separate_passes(log: Path) -> float:
    """CPU seconds of the camera topic, then each side topic in a pass of its own."""
    start = time.process_time()
    with open_source(log) as source:
        topic = pick_image_topic(source, None)
        frames = sum(1 for _ in source.image_messages(topic))
        side = SideTopics.for_run(source, topic, None, camera_info=True)
        if side.poses is not None:
            read_poses(source, side.poses.topic)
        find_camera_info(source, topic)
    assert frames > 0
    return time.process_time() - start


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", type=Path)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args(argv)
    times: dict[str, list[float]] = {"separate passes": [], "one pass": []}
    for _ in range(args.rounds):
        times["separate passes"].append(separate_passes(args.log))
        times["one pass"].append(one_pass(args.log))
    for name, values in times.items():
        rounds = ", ".join(f"{v:.2f}" for v in values)
        print(f"{name}: median {statistics.median(values):.2f} CPU s ({rounds})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
