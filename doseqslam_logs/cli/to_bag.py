"""`doseqslam-logs to-bag OUT.mcap -o OUT.bag`: a ROS 1-profile output as a ROS 1 .bag.

rosbags, rosbags-convert and evo refuse a ROS 1-profile MCAP ("Profile is not ros2"); the
.bag this writes keeps every message's bytes, topic and log time (sinks/ros1_bag.py,
docs/viewers.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "to-bag",
        help="write a ROS 1-profile MCAP (annotate's output of a .bag) as a ROS 1 .bag",
        description="Write a ROS 1-profile MCAP (what annotate makes of a ROS 1 .bag) as a "
        "ROS 1 .bag for rosbag, rosbags and evo: every message's bytes, topic and log time, "
        "every channel's type, definition and md5sum. docs/viewers.md.",
    )
    parser.add_argument("log", type=Path, metavar="OUT.mcap", help="a ROS 1-profile MCAP")
    parser.add_argument(
        "-o", "--output", type=Path, required=True, metavar="OUT.bag", help="written atomically"
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ..sinks.ros1_bag import mcap_to_bag

    result = mcap_to_bag(args.log, args.output)
    print(f"{args.output}: {result.summary}")
    return 0
