#!/usr/bin/env python3
"""Issue #22 item 2, a measured design (not the tool's behaviour): find features on small
frames enlarged to the detectors' working size, and score the defaults on the small logs.

ORB needs a 31-pixel border and patch, so on a 64x32 frame it finds nothing and on 128x64
almost nothing (median 0 and 2 a frame). Enlarging a frame whose longer side is under
`SMALL` px to `feature_image_max_side` / `image_max_side` (bicubic) before detection gives
it 40 and 130. This script patches `shrink`, the one function the segmentation, the place
index and verification call before detecting (`--where all`), or only the segmentation's
(`--where segmentation`, whose ORB features the place index reuses), then runs
tools/feature_poor_table.py's defaults row. Frames of SMALL px or more are untouched, so the
full-size figures cannot change.

    python tools/feature_poor_enlarge.py --datasets rtabmap,samples --sizes 128x64,64x32
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import feature_poor_table as fpt
import numpy as np
import shrink_log

import doseqslam_logs.detector.place_search as place_search
import doseqslam_logs.detector.segmentation as segmentation
import doseqslam_logs.verification.geometry as geometry

SMALL = 160  # px: frames whose longer side is under this are enlarged for feature detection
_shrink = segmentation.shrink


def shrink_or_enlarge(gray: shrink_log.Gray, max_side: int) -> shrink_log.Gray:
    """`shrink`, except that a frame under SMALL px is enlarged to max_side."""
    if max(gray.shape) >= SMALL:
        return _shrink(gray, max_side)
    scale = max_side / max(gray.shape)
    size = (round(gray.shape[1] * scale), round(gray.shape[0] * scale))
    return np.asarray(cv2.resize(gray, size, interpolation=cv2.INTER_CUBIC), dtype=np.uint8)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=fpt.DATA)
    parser.add_argument("--datasets", default="rtabmap,samples")
    parser.add_argument("--sizes", default="128x64,64x32")
    parser.add_argument("--where", choices=["all", "segmentation"], default="all")
    args = parser.parse_args()
    segmentation.shrink = shrink_or_enlarge  # type: ignore[assignment]
    if args.where == "all":
        geometry.shrink = place_search.shrink = shrink_or_enlarge  # type: ignore[assignment]
    every = fpt.sources(args.data)
    label = f"defaults, enlarged ({args.where})"
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        for key in args.datasets.split(","):
            for source in every[key]:
                for size in args.sizes.split(","):
                    shape = shrink_log.parse_size(size)
                    camera = None
                    if not source.path.is_dir():
                        camera = shrink_log.scaled_camera(source.path, shape)
                    log = folder / "log.mcap"
                    shrink_log.write_small_log(source.frames(), log, shape, camera=camera)
                    result, figures = fpt.run(log, folder / "out.mcap", source, "defaults")
                    print(fpt.row(source, size, label, result, figures), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
