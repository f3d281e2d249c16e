"""`doseqslam-logs layout OUT.mcap -o LAYOUT.json`: a Foxglove Studio layout naming the
annotated log's own topics (camera, match image, markers, paths, ground truth, current pose);
the file appears whole (atomic write)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..export.layout import SCENE_PANEL, write_layout


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "layout",
        help="write a Foxglove/Lichtblick layout for an annotated log",
        description=__doc__,
    )
    parser.add_argument(
        "log", type=Path, metavar="OUT.mcap", help="an annotated (or optimized) MCAP"
    )
    parser.add_argument(
        "-o", "--output", type=Path, required=True, metavar="LAYOUT.json", help="write here"
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    layout = write_layout(args.log, args.output)
    scene = layout["configById"][SCENE_PANEL]
    topics = len(scene["topics"])
    print(
        f"{args.output}: layout for {args.log}: {topics} 3-D topics in frame {scene['followTf']}",
        file=sys.stderr,
    )
    return 0
